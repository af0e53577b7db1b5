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
import re
import sys
import tempfile
import xml.etree.ElementTree as ET

import numpy as np


def fail(message: str) -> None:
    print(f"masks_check: {message}", file=sys.stderr)
    sys.exit(2)


def load_model(urdf: str, camera: dict):
    """The URDF with a camera `c`, compiled by MuJoCo."""
    try:
        import mujoco
    except ImportError as e:
        fail(f"cannot import mujoco ({e}): run scripts/setup-mujoco-venv.sh and use .venv-mujoco/bin/python")
    folder = os.path.dirname(os.path.abspath(urdf))
    text = open(urdf, encoding="utf-8").read()
    # MuJoCo's URDF extension: keep visual geoms, keep every link a body,
    # meshes by file name from the description's meshes/ folder.
    ext = (
        f'<mujoco><compiler meshdir="{folder}/meshes" strippath="true" '
        'discardvisual="false" fusestatic="false"/></mujoco>'
    )
    text, n = re.subn(r"(<robot[^>]*>)", lambda m: m.group(1) + ext, text, count=1)
    if n != 1:
        fail(f"{urdf}: no <robot> element")
    with tempfile.NamedTemporaryFile("w", suffix=".urdf", delete=False) as f:
        f.write(text)
        tmp = f.name
    try:
        spec = mujoco.MjSpec.from_file(tmp)
    finally:
        os.unlink(tmp)
    w, h = int(camera["width"]), int(camera["height"])
    for key, centre in (("cx", (w - 1) / 2), ("cy", (h - 1) / 2)):
        if abs(float(camera[key]) - centre) > 1e-6:
            fail(f"camera {key} {camera[key]}: expected the image centre {centre} (MuJoCo's camera is a field of view)")
    if abs(float(camera["fx"]) - float(camera["fy"])) > 1e-6:
        fail(f"camera fx {camera['fx']}, fy {camera['fy']}: expected square pixels")
    world_from_camera = np.asarray(camera["world_from_camera"], float)
    rotation = world_from_camera[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, rotation.flatten())
    cam = spec.worldbody.add_camera(name="c", pos=world_from_camera[:3, 3], quat=quat)
    cam.fovy = float(np.degrees(2 * np.arctan((h / 2) / float(camera["fy"]))))
    return mujoco, spec.compile(), (w, h)


def mimics(urdf: str) -> dict[str, tuple[str, float, float]]:
    """`joint -> (source joint, multiplier, offset)` of the URDF's <mimic> tags."""
    out = {}
    for j in ET.parse(urdf).getroot().findall("joint"):
        m = j.find("mimic")
        if m is not None:
            out[j.get("name")] = (m.get("joint"), float(m.get("multiplier", 1)), float(m.get("offset", 0)))
    return out


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
    mimic = mimics(a.urdf)
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
