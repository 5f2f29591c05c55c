"""The test sweep's report hook: one line per point with its values and its last stage's total."""
import json


def write(points, out):
    lines = []
    for p in points:
        last = list(p["artifacts"].values())[-1]  # the point's last stage (evaluate, or --until)
        total = json.loads((last / "result.json").read_text())["total"]
        lines.append(f"{json.dumps(p['values'], sort_keys=True)} {total}")
    (out / "report.txt").write_text("\n".join(lines) + "\n")
    return out / "report.txt"
