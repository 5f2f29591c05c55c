"""Engine overhead, measured in one run on this machine.

Prints: the wall time of a fully cached `run` of the six-stage test pipeline (the real CLI, in a
subprocess); the wall time of `status --sweep` on a 100-point sweep; and the ratio of the time to
compute every key when the first stage's output is 1 GiB vs 1 MiB (keys chain upstream keys and
never read artifact bytes, so the ratio should be ~1; the target is <= 1.2).

    .venv/bin/python benchmarks/engine_overhead.py
"""
from __future__ import annotations

import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.engine.conftest import make_workspace  # noqa: E402  (the same test stages the tests use)


def wall(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def main() -> None:
    from pipeline.plan import Project

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        ws = make_workspace(tmp / "cached")
        ws.cli("run")
        cached_run = wall(lambda: ws.cli("run"), 5)

        ws.spec.write_text(ws.spec.read_text() + "  hundred:\n    axes:\n      rl.value: " + str(list(range(25))) + "\n      rl.seed: [0, 1, 2, 3]\n")
        status_sweep = wall(lambda: ws.cli("status", "--sweep", "hundred"), 3)

        key_times = {}
        for mb in (1, 1024):
            w = make_workspace(tmp / f"blob{mb}")
            w.spec.write_text(w.spec.read_text().replace("config: {value: 1}", f"config: {{value: 1, blob_mb: {mb}}}"))
            w.cli("run", "--until", "tokenize")
            blob = next((w.store / "collect").glob("*/*/blob.bin"))
            assert blob.stat().st_size == mb << 20

            def plan_all(root=w.root):
                project = Project(root / "pipeline.yaml")
                nodes = project.plan(["evaluate"], "toy", {}, label="toy")
                assert nodes[0].status == "cached"

            plan_all()  # warm imports
            key_times[mb] = wall(plan_all, 20)
            sys.path.remove(str(w.root)) if str(w.root) in sys.path else None

    print("engine overhead (median wall time; this machine, one run)")
    print(f"  fully cached `run`, 6-stage test pipeline (CLI subprocess): {cached_run:.3f} s")
    print(f"  `status --sweep` on a 100-point sweep (CLI subprocess):     {status_sweep:.3f} s")
    print(f"  key computation, 6 stages, upstream output 1 MiB:  {key_times[1] * 1e3:.1f} ms")
    print(f"  key computation, 6 stages, upstream output 1 GiB:  {key_times[1024] * 1e3:.1f} ms")
    print(f"  ratio 1 GiB / 1 MiB: {key_times[1024] / key_times[1]:.2f} (target <= 1.2)")


if __name__ == "__main__":
    main()
