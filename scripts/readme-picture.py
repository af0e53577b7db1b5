"""Draws docs/images/demo.png, the README's picture, from a `bridgev2w demo`
output folder: the mask overlay of the middle frame (left) and, on the
right, rows of the prediction GIF (first frame | masks | prediction |
ground truth) at frames 0, 4 and 8.

    ./run demo --out demo-out && .venv/bin/python scripts/readme-picture.py demo-out
"""
import sys
from pathlib import Path

from PIL import Image

demo = Path(sys.argv[1] if len(sys.argv) > 1 else "demo-out")
out = Path(__file__).resolve().parent.parent / "docs" / "images" / "demo.png"
overlay = Image.open(demo / "overlay.png").convert("RGB")
gif = Image.open(demo / "prediction.gif")
rows = []
for frame in (0, gif.n_frames // 2, gif.n_frames - 1):
    gif.seek(frame)
    rows.append(gif.convert("RGB"))
row_w, row_h = rows[0].size
height = row_h * len(rows)
left = overlay.resize((overlay.width * height // overlay.height, height), Image.LANCZOS)
canvas = Image.new("RGB", (left.width + 8 + row_w, height), "white")
canvas.paste(left, (0, 0))
for i, r in enumerate(rows):
    canvas.paste(r, (left.width + 8, i * row_h))
tmp = out.with_suffix(".tmp.png")
canvas.save(tmp, optimize=True)
tmp.replace(out)
print(f"{out}: {canvas.width}x{canvas.height}")
