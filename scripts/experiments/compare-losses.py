"""Mean diffusion loss of two runs over the same step windows (runs with the
same seed draw the same data and noise, so the windows pair up), and the
median seconds per step.

    python3 scripts/experiments/compare-losses.py RUN_A RUN_B [LO-HI ...]

e.g. `compare-losses.py runs/reproduce/prior /tmp/w256/prior 400-499 900-999 1400-1499`.
"""
import json
import sys
from pathlib import Path


def load(run):
    path = Path(run) / "metrics.jsonl"
    return {d["step"]: d for d in map(json.loads, path.read_text().splitlines())}


a, b = load(sys.argv[1]), load(sys.argv[2])
windows = sys.argv[3:] or ["400-499", "900-999", "1400-1499"]
for w in windows:
    lo, hi = map(int, w.split("-"))
    row = f"steps {lo}-{hi}:"
    for name, run in (("A", a), ("B", b)):
        steps = [k for k in range(lo, hi + 1) if k in run]
        if steps:
            row += f" {name} {sum(run[k]['diffusion'] for k in steps) / len(steps):.4f} ({len(steps)} steps)"
        else:
            row += f" {name} -"
    print(row)
for name, run in (("A", a), ("B", b)):
    secs = sorted(d["secs"] for k, d in run.items() if k >= 100)
    if secs:
        print(f"{name}: median {secs[len(secs) // 2]:.3f} s per step from step 100 ({len(secs)} steps)")
