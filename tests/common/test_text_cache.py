"""ROBOSCAPE_TEXT_CACHE: a file of precomputed instruction embeddings lets a machine without the text
encoder's package embed the instructions it holds; a malformed file is a clear error."""
import numpy as np
import pytest

import stages.common.text_encoder as te


@pytest.fixture
def fresh(monkeypatch):
    """The module as a new process sees it, with the model unloadable."""
    monkeypatch.setattr(te, "_cache", {})
    monkeypatch.setattr(te, "_preloaded", False)

    def no_model():
        raise ImportError("no text encoder here")

    monkeypatch.setattr(te, "_load", no_model)
    return monkeypatch


def test_the_cache_file_answers_without_the_model(tmp_path, fresh):
    emb = np.eye(2, te.TEXT_DIM, dtype=np.float32)  # (2, 384)
    np.savez(tmp_path / "c.npz", texts=np.array(["push the cube", "pull the cube"]), emb=emb)
    fresh.setenv(te.CACHE_ENV, str(tmp_path / "c.npz"))
    out = te.encode_texts(["pull the cube", "push the cube", "pull the cube"])
    assert np.array_equal(out, emb[[1, 0, 1]])
    with pytest.raises(ImportError):  # a string the file lacks still needs the model
        te.encode_texts(["lift the cube"])


@pytest.mark.parametrize("arrays, message", [({"texts": np.array(["a"])}, "not a text-embedding cache"),
                                             ({"texts": np.array(["a"]), "emb": np.zeros((1, 3))}, "expected (1, 384)")])
def test_a_malformed_cache_file_names_the_variable(tmp_path, fresh, arrays, message):
    np.savez(tmp_path / "bad.npz", **arrays)
    fresh.setenv(te.CACHE_ENV, str(tmp_path / "bad.npz"))
    with pytest.raises(ValueError, match=te.CACHE_ENV) as e:
        te.encode_texts(["a"])
    assert message in str(e.value)


def test_save_cache_round_trips_the_real_embeddings(tmp_path, monkeypatch):
    texts = ["put the small red cube in the bowl"]
    monkeypatch.setattr(te, "_preloaded", True)
    te.save_cache(texts, tmp_path / "c.npz")
    real = te.encode_texts(texts)
    monkeypatch.setattr(te, "_cache", {})
    monkeypatch.setattr(te, "_preloaded", False)
    monkeypatch.setattr(te, "_load", lambda: (_ for _ in ()).throw(ImportError("no model")))
    monkeypatch.setenv(te.CACHE_ENV, str(tmp_path / "c.npz"))
    assert np.array_equal(te.encode_texts(texts), real)
