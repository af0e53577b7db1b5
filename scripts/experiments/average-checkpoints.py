"""Averages the weights of several checkpoints of one run into a new
checkpoint folder (a uniform average: the poor man's EMA), so that
`bridgev2w eval-run CONFIG --run OUT_DIR` scores it. The optimizer state and
state.json are the last checkpoint's.

    .venv/bin/python scripts/experiments/average-checkpoints.py OUT_DIR CKPT_DIR...

Used in docs/results.md (section `levers`, session 18) with the
fine-tuning's checkpoints 1500, 1750 and 2000 and the prior's 3000, 3500, 4000.
"""
import shutil
import sys
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

out, ckpts = Path(sys.argv[1]), [Path(p) for p in sys.argv[2:]]
if len(ckpts) < 2:
    sys.exit("usage: average-checkpoints.py OUT_DIR CKPT_DIR CKPT_DIR...")
if out.exists():
    sys.exit(f"{out} exists: choose a new folder")
tmp = out.with_name(out.name + ".tmp")
shutil.rmtree(tmp, ignore_errors=True)
shutil.copytree(ckpts[-1], tmp)
for name in ("weights.safetensors", "trainable.safetensors"):
    states = [load_file(c / name) for c in ckpts]
    averaged = {}
    for key, last in states[-1].items():
        if last.is_floating_point():
            total = sum(s[key].double() for s in states)
            averaged[key] = (total / len(states)).to(last.dtype)
        else:
            averaged[key] = last
    save_file(averaged, tmp / name)
    print(f"{name}: {len(averaged)} tensors averaged over {len(states)} checkpoints")
tmp.rename(out)
