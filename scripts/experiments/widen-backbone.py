"""A copy of a backbone folder (after the `vae` stage) whose transformer has
HEADS attention heads (width HEADS x attention_head_dim) and freshly
initialised weights (diffusers' init, seed 0), for a `prior` stage of
another width.

    .venv/bin/python scripts/experiments/widen-backbone.py BACKBONE_DIR OUT_DIR HEADS
"""
import json
import shutil
import sys
from pathlib import Path

import torch
from diffusers import CogVideoXTransformer3DModel

backbone, out, heads = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3])
if out.exists():
    sys.exit(f"{out} exists: choose a new folder")
tmp = out.with_name(out.name + ".tmp")
shutil.rmtree(tmp, ignore_errors=True)
shutil.copytree(backbone, tmp)
path = tmp / "transformer"
cfg = json.loads((path / "config.json").read_text())
cfg["num_attention_heads"] = heads
cfg["time_embed_dim"] = heads * cfg["attention_head_dim"]
torch.manual_seed(0)
model = CogVideoXTransformer3DModel(**{k: v for k, v in cfg.items() if not k.startswith("_")})
(path / "diffusion_pytorch_model.safetensors").unlink()
model.save_pretrained(path, safe_serialization=True)
tmp.rename(out)
width = heads * cfg["attention_head_dim"]
params = sum(p.numel() for p in model.parameters())
print(f"{out}: transformer width {width}, {params} parameters")
