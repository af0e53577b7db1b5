"""A copy of a `prior` run's backbone folder whose transformer weights are
the uniform average of several of its checkpoints (`trainable.safetensors`,
keys `backbone.<diffusers key>`).

    .venv/bin/python scripts/experiments/average-backbone.py BACKBONE_DIR OUT_DIR CKPT_DIR...
"""
import shutil
import sys
from pathlib import Path

from safetensors import safe_open
from safetensors.torch import load_file, save_file

backbone, out, ckpts = Path(sys.argv[1]), Path(sys.argv[2]), [Path(p) for p in sys.argv[3:]]
if out.exists():
    sys.exit(f"{out} exists: choose a new folder")
weights = backbone / "transformer" / "diffusion_pytorch_model.safetensors"
states = [load_file(c / "trainable.safetensors") for c in ckpts]
current = load_file(weights)
averaged = {}
for key, value in current.items():
    k = "backbone." + key
    if k not in states[0]:
        sys.exit(f"{ckpts[0]}: no {k}: not a checkpoint of this backbone's prior")
    averaged[key] = (sum(s[k].double() for s in states) / len(states)).to(value.dtype)
tmp = out.with_name(out.name + ".tmp")
shutil.rmtree(tmp, ignore_errors=True)
shutil.copytree(backbone, tmp)
meta = safe_open(str(weights), "pt").metadata()
save_file(averaged, tmp / "transformer" / "diffusion_pytorch_model.safetensors", metadata=meta)
tmp.rename(out)
print(f"{out}: transformer averaged over {len(ckpts)} checkpoints")
