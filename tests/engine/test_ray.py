"""The Ray executor runs the same stage functions with the same keys and outputs as local."""
from __future__ import annotations

import json

import pytest

from tests.engine.conftest import make_workspace

ray = pytest.importorskip("ray", reason="the optional ray extra is not installed (pip install 'ray[default]==2.60.0')")
pytestmark = pytest.mark.ray


def _artifacts(ws) -> dict[tuple[str, str], dict]:
    out = {}
    for m in ws.store.glob("*/*/*/manifest.json"):
        stage, key = m.parts[-4], m.parts[-2]
        out[(stage, key)] = json.loads((m.parent / "result.json").read_text())
    return out


def test_ray_executor_matches_local(tmp_path):
    local = make_workspace(tmp_path / "local")
    remote = make_workspace(tmp_path / "ray")
    args = ("run", "--set", "collect.shards=3", "--jobs", "2")
    local.cli(*args, "--executor", "local")
    remote.cli(*args, "--executor", "ray")
    a, b = _artifacts(local), _artifacts(remote)
    assert len(a) == 6 and a == b  # same keys, same outputs
    assert a[next(k for k in a if k[0] == "collect")]["shards"] == [0, 1, 4]
    remote.reset_log()
    remote.cli("run", "--set", "collect.shards=3", "--executor", "ray")
    assert remote.executions() == []
