"""Writes the preview image a training run logged to TensorBoard at a step
(`preview/truth_over_prediction`: the ground truth above the model's
prediction, what TensorBoard's Images tab shows) as a PNG, upscaled by an
integer factor for the docs.

    .venv/bin/python scripts/experiments/tensorboard-preview.py RUN STEP OUT.png [SCALE]

e.g. `tensorboard-preview.py runs/exp-motion4/bridgev2w 2000 docs/results/figures/tensorboard-preview.png 3`.
"""
import io
import sys

from PIL import Image

import bridgev2w.wandb_export as wx

run, step, out = sys.argv[1], int(sys.argv[2]), sys.argv[3]
scale = int(sys.argv[4]) if len(sys.argv) > 4 else 1
images = wx.read_events(run).images
if step not in images:
    sys.exit(f"{run}: no preview image at step {step} (steps with one: {sorted(images)})")
img = Image.open(io.BytesIO(images[step]["preview/truth_over_prediction"])).convert("RGB")
img = img.resize((img.width * scale, img.height * scale), Image.NEAREST)
img.save(out)
print(f"{out}: step {step}, {img.width}x{img.height}")
