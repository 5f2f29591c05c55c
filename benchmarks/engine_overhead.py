"""Engine overhead, measured in one run on this machine.

Prints: the wall time of a fully cached `run` of the six-stage test pipeline (the real CLI, in a
subprocess); the wall time of `status --sweep` on a 100-point sweep; the ratio of the time to
compute every key, and of a fully cached `run`, when the first stage's output is 1 GiB vs 1 MiB
(keys chain upstream keys and never read artifact bytes, so the ratio should be ~1; the target is
<= 1.2); and what verifying a
stage's inputs (re-hashing them against their manifests, which happens only when a stage starts)
adds, alone and in a forced `run --only tokenize` on the CLI, with 1 MiB vs 1 GiB of input.

    .venv/bin/python benchmarks/engine_overhead.py
"""
from __future__ import annotations

import os
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
    from pipeline.execute import verify_inputs
    from pipeline.plan import Project

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        ws = make_workspace(tmp / "cached")
        ws.cli("run")
        cached_run = wall(lambda: ws.cli("run"), 5)

        ws.spec.write_text(ws.spec.read_text() + "  hundred:\n    axes:\n      rl.value: " + str(list(range(25))) + "\n      rl.seed: [0, 1, 2, 3]\n")
        status_sweep = wall(lambda: ws.cli("status", "--sweep", "hundred"), 3)

        workspaces = {}
        for mb in (1, 1024):
            w = make_workspace(tmp / f"blob{mb}")
            w.spec.write_text(w.spec.read_text().replace("config: {value: 1}", f"config: {{value: 1, blob_mb: {mb}}}"))
            w.cli("run")
            blob = next((w.store / "collect").glob("*/*/blob.bin"))
            assert blob.stat().st_size == mb << 20
            workspaces[mb] = w
        os.sync()  # the kernel writing the fresh GiB back to disk would slow whatever is timed next

        def plan_all(root: Path) -> None:
            project = Project(root / "pipeline.yaml")
            nodes = project.plan(["evaluate"], "toy", {}, label="toy")
            assert all(n.status == "cached" for n in nodes)

        for w in workspaces.values():
            plan_all(w.root)  # warm imports
        # the two sizes interleaved, so load from other jobs on the machine hits both alike
        key_times: dict = {mb: [] for mb in workspaces}
        run_times: dict = {mb: [] for mb in workspaces}
        for _ in range(20):
            for mb, w in workspaces.items():
                t = time.perf_counter()
                plan_all(w.root)
                key_times[mb].append(time.perf_counter() - t)
        for _ in range(5):
            for mb, w in workspaces.items():
                t = time.perf_counter()
                w.cli("run")
                run_times[mb].append(time.perf_counter() - t)
        key_times = {mb: statistics.median(v) for mb, v in key_times.items()}
        run_times = {mb: statistics.median(v) for mb, v in run_times.items()}

        verify_times, start_times = {}, {}
        for mb, w in workspaces.items():
            project = Project(w.root / "pipeline.yaml")
            collect_key = project.plan(["collect"], "toy", {}, label="toy")[0].key
            verify_times[mb] = wall(lambda: verify_inputs(project.store, {"collect": collect_key}), 5)
            start_times[mb] = wall(lambda: w.cli("run", "--only", "tokenize", "--force", "tokenize"), 3)

    print("engine overhead (median wall time; this machine, one run)")
    print(f"  fully cached `run`, 6-stage test pipeline (CLI subprocess): {cached_run:.3f} s")
    print(f"  `status --sweep` on a 100-point sweep (CLI subprocess):     {status_sweep:.3f} s")
    print(f"  key computation, 6 stages, upstream output 1 MiB:  {key_times[1] * 1e3:.1f} ms")
    print(f"  key computation, 6 stages, upstream output 1 GiB:  {key_times[1024] * 1e3:.1f} ms")
    print(f"  ratio 1 GiB / 1 MiB: {key_times[1024] / key_times[1]:.2f} (target <= 1.2)")
    print(f"  fully cached `run` (CLI subprocess), upstream output 1 MiB: {run_times[1]:.3f} s")
    print(f"  fully cached `run` (CLI subprocess), upstream output 1 GiB: {run_times[1024]:.3f} s")
    print(f"  ratio 1 GiB / 1 MiB: {run_times[1024] / run_times[1]:.2f} (target <= 1.2)")
    print("input verification (only when a stage starts; page cache warm)")
    print(f"  verify_inputs, 1 MiB of input:  {verify_times[1] * 1e3:.1f} ms")
    print(f"  verify_inputs, 1 GiB of input:  {verify_times[1024] * 1e3:.1f} ms  ({1 / verify_times[1024]:.2f} GiB/s blake3)")
    print(f"  forced `run --only tokenize` (CLI subprocess), 1 MiB of input: {start_times[1]:.3f} s")
    print(f"  forced `run --only tokenize` (CLI subprocess), 1 GiB of input: {start_times[1024]:.3f} s")


if __name__ == "__main__":
    main()
