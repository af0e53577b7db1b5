"""How near a planner's gripper came to one goal of each trial, from the
`trials.jsonl` of `bridgev2w plan --trace DIR`: per trial the closest TCP
distance to goal GOAL's expert TCP position over the steps that pursued it or
an earlier goal, and how far the task's object moved (the spread of the task
error over the steps).

    python3 scripts/experiments/trace-approach.py TRACE_DIR [GOAL]

GOAL defaults to 2: with 2 waypoints per key goal, pick_place's grasp
(`goal_tcp_m` lists the goals in the order pursued).
"""
import json
import math
import sys
from pathlib import Path

trace = Path(sys.argv[1]) / "trials.jsonl"
goal = int(sys.argv[2]) if len(sys.argv) > 2 else 2
print("trial\tsuccess\terror_m\tsteps\tclosest_to_goal_m\tobject_moved_m")
for line in trace.read_text().splitlines():
    t = json.loads(line)
    target = t["goal_tcp_m"][goal]
    before = [s for s in t["steps"] if s["goal"] <= goal]
    closest = min((math.dist(s["ee"][:3], target) for s in before), default=float("nan"))
    errors = [s["task_error_m"] for s in t["steps"] if s["task_error_m"] is not None]
    moved = max(errors) - min(errors) if errors else float("nan")
    print(f"{t['trial']}\t{t['success']}\t{t['error_m']:.3f}\t{len(t['steps'])}\t{closest:.3f}\t{moved:.3f}")
