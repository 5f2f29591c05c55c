"""scripts/takeover_probe.py's summary of its rows."""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))


def test_the_summary_pools_files_and_counts_rested_takeovers_apart(tmp_path, capsys):
    import json

    from takeover_probe import main

    def row(task, split, rested, takeover):
        return {"task": task, "split": split, "policy_success": False, "rested": rested, "takeover": takeover}

    a, b = tmp_path / "ind.jsonl", tmp_path / "ood.jsonl"
    a.write_text("\n".join(json.dumps(r) for r in [row("push", "ind", True, "success"), row("push", "ind", False, "no_plan")]))
    b.write_text(json.dumps(row("pull", "ood", True, "failed")) + "\n")
    main(["--summarize", str(a), str(b)])
    out = capsys.readouterr().out
    assert "| push | ind | 2 | 0 | 1 | 1/2 [" in out and "| 1 | 1/1 [" in out
    assert "| all | all | 3 | 0 | 2 | 1/3 [" in out and "| 1 | 1/2 [" in out.splitlines()[-1]
