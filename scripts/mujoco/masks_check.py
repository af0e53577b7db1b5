"""This project's embodiment masks against MuJoCo's renderer (issue 72, item 2).

MuJoCo loads the same URDF (its URDF importer, the visual geoms kept, the
meshes from the description folder), a camera is placed as the camera JSON
says (OpenCV axes turned into MuJoCo's, which look along -z with y up;
vertical field of view from fy and the height), the joints of each frame are
set (mimic joints as their URDF <mimic> says), and MuJoCo's segmentation
rendering (OpenGL rasterization, an independent renderer) gives the robot's
pixels. Each frame's IoU against `bridgev2w masks`' masks.npy is printed and
written as JSON.

    scripts/setup-mujoco-venv.sh
    bridgev2w masks --robot franka-robotiq --camera CAM.json --joints J.json --width 320 --height 240 --out M
    MUJOCO_GL=egl .venv-mujoco/bin/python scripts/mujoco/masks_check.py \
        --urdf crates/embodiment/robots/franka_robotiq/franka_robotiq.urdf \
        --camera CAM.json --joints J.json --masks M/masks.npy [--json OUT.json]

The camera must have square pixels and its principal point at the image
centre ((W - 1) / 2, (H - 1) / 2): MuJoCo's camera is a field of view.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import xml.etree.ElementTree as ET

import numpy as np

# The URDF import and the camera placement are the MuJoCo engine's own
# (`bridgev2w synth --engine mujoco`): one home for both.
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "../../crates/data/src/synth/mujoco"))
from mujoco_world import add_camera, fail, urdf_mimics, urdf_spec  # noqa: E402


def load_model(urdf: str, camera: dict):
    """The URDF with a camera `c`, compiled by MuJoCo."""
    try:
        import mujoco
    except ImportError as e:
        fail(f"cannot import mujoco ({e}): run scripts/setup-mujoco-venv.sh and use .venv-mujoco/bin/python")
    spec = urdf_spec(mujoco, urdf, balance_inertia=False)
    w, h = add_camera(mujoco, spec, camera)
    return mujoco, spec.compile(), (w, h)


def actuated(urdf: str) -> list[str]:
    """The actuated joints in document order (not fixed, not mimic): `--joints` columns."""
    names = []
    for j in ET.parse(urdf).getroot().findall("joint"):
        if j.get("type") != "fixed" and j.find("mimic") is None:
            names.append(j.get("name"))
    return names


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--urdf", required=True)
    p.add_argument("--camera", required=True, help="camera JSON (bridgev2w's)")
    p.add_argument("--joints", required=True, help="JSON rows of the actuated joints, as bridgev2w masks --joints")
    p.add_argument("--masks", required=True, help="masks.npy written by bridgev2w masks")
    p.add_argument("--json", help="also write the per-frame IoU here")
    a = p.parse_args()
    camera = json.load(open(a.camera, encoding="utf-8"))
    rows = json.load(open(a.joints, encoding="utf-8"))
    masks = np.load(a.masks)
    mujoco, model, (w, h) = load_model(a.urdf, camera)
    names = actuated(a.urdf)
    if masks.shape != (len(rows), h, w):
        fail(f"{a.masks}: shape {masks.shape}, expected {(len(rows), h, w)} (frames of {a.joints}, the camera's size)")
    if any(len(r) != len(names) for r in rows):
        fail(f"{a.joints}: rows of {sorted({len(r) for r in rows})} values, expected {len(names)} ({', '.join(names)})")
    mimic = urdf_mimics(a.urdf)
    data = mujoco.MjData(model)
    try:
        renderer = mujoco.Renderer(model, h, w)
    except Exception as e:  # no EGL / OSMesa / display
        fail(f"MuJoCo cannot render offscreen ({e}): set MUJOCO_GL=egl (Mesa's libEGL) or MUJOCO_GL=osmesa")
    renderer.enable_segmentation_rendering()
    frames = []
    for t, row in enumerate(rows):
        values = dict(zip(names, row))
        for joint, (source, k, offset) in mimic.items():
            values[joint] = k * values[source] + offset
        for joint, v in values.items():
            jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, joint)
            if jid < 0:
                fail(f"{a.urdf}: MuJoCo's model has no joint {joint!r}")
            data.qpos[model.jnt_qposadr[jid]] = v
        mujoco.mj_forward(model, data)
        renderer.update_scene(data, camera="c")
        theirs = renderer.render()[..., 0] >= 0
        ours = masks[t] > 0
        union = int((theirs | ours).sum())
        iou = float((theirs & ours).sum()) / union if union else 1.0
        frames.append({"frame": t, "iou": iou, "mujoco_px": int(theirs.sum()), "bridgev2w_px": int(ours.sum()),
                       "only_mujoco_px": int((theirs & ~ours).sum()), "only_bridgev2w_px": int((ours & ~theirs).sum())})
        print(f"frame {t}: IoU {iou:.4f} (MuJoCo {theirs.sum()} px, bridgev2w {ours.sum()} px)")
    ious = [f["iou"] for f in frames]
    summary = {"mujoco": mujoco.__version__, "urdf": a.urdf, "size": [w, h], "frames": frames,
               "mean_iou": float(np.mean(ious)), "min_iou": float(np.min(ious))}
    print(f"mean IoU {summary['mean_iou']:.4f}, lowest {summary['min_iou']:.4f} over {len(frames)} frames (MuJoCo {mujoco.__version__})")
    if a.json:
        with open(a.json, "w", encoding="utf-8") as f:
            json.dump(summary, f, indent=2)


if __name__ == "__main__":
    main()
