#!/usr/bin/env python3
"""Render robot segmentation masks with pybullet's TinyRenderer (reference + benchmark).

For every frame of a joint trajectory the named joints are set with
resetJointState (mimic joints of the URDF follow their master) and
getCameraImage(ER_TINY_RENDERER) is called in a DIRECT client; only the
segmentation buffer is kept.

Output masks (--out, uint8 [T, H, W]): 0 = background, 1 = base link,
k + 2 = pybullet link index k (i.e. the child link of pybullet joint k).
Threshold > 0 for a binary robot mask.

Prints one JSON line:
  {"renderer":"pybullet-tinyrenderer","frames":..,"seconds":..,"masks_per_s":..,
   "width":..,"height":..,"workers":..}
`seconds` is the wall time of the render phase only (from the first worker
starting its first frame to the last worker finishing), excluding process
start-up and URDF loading.

Example:
  .venv-bench/bin/python scripts/bench/pybullet_masks.py \
      --urdf pybullet:franka_panda/panda.urdf --joints ex/joints.npy \
      --joint-names ex/joint_names.json --camera ex/camera.json --workers 2
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import bench_common as bc  # noqa: E402


def _render_chunk(args):
    urdf, names, q_chunk, cam, want_masks = args
    import pybullet as p

    client = p.connect(p.DIRECT)
    try:
        body = p.loadURDF(urdf, [0, 0, 0], [0, 0, 0, 1], useFixedBase=True, physicsClientId=client)
        joint_index, _ = bc.pybullet_index_maps(p, body, client)
        missing = [n for n in names if n not in joint_index]
        if missing:
            raise KeyError(f"joints not in URDF: {missing}")
        mimics = [j for j in bc.urdf_joints(urdf) if j.mimic is not None]
        view, proj = bc.camera_matrices(cam)
        w, h = cam["width"], cam["height"]
        out = np.zeros((len(q_chunk), h, w), dtype=np.uint8) if want_masks else None
        t0 = time.time()
        for i, q in enumerate(q_chunk):
            bc.set_joints(p, body, client, joint_index, names, q, mimics)
            _, _, _, _, seg = p.getCameraImage(
                w,
                h,
                viewMatrix=view,
                projectionMatrix=proj,
                renderer=p.ER_TINY_RENDERER,
                flags=p.ER_SEGMENTATION_MASK_OBJECT_AND_LINKINDEX,
                shadow=0,
                physicsClientId=client,
            )
            if want_masks:
                seg = np.asarray(seg, dtype=np.int64).reshape(h, w)
                obj = seg & ((1 << 24) - 1)
                link = (seg >> 24) - 1
                m = np.where((seg >= 0) & (obj == body), link + 2, 0)
                out[i] = m.astype(np.uint8)
        t1 = time.time()
        return t0, t1, out
    finally:
        p.disconnect(physicsClientId=client)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--urdf", required=True, help="URDF path or pybullet:<path in pybullet_data>")
    ap.add_argument("--print-urdf-path", action="store_true", help="print the resolved URDF path and exit")
    ap.add_argument("--joints", help="float array [T, n] (.npy)")
    ap.add_argument("--joint-names", help="JSON list of the n joint names (default: URDF active joints)")
    ap.add_argument("--camera", help="camera JSON (OpenCV intrinsics + world_from_camera)")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=1, help="render the trajectory R times")
    ap.add_argument("--out", help="save uint8 masks [T*R, H, W] (.npy)")
    args = ap.parse_args()
    out = bc.real_stdout()  # native pybullet chatter goes to stderr from here on

    urdf = bc.resolve_urdf(args.urdf)
    if args.print_urdf_path:
        print(urdf, file=out, flush=True)
        return
    if not args.joints or not args.camera:
        ap.error("--joints and --camera are required")

    q = np.load(args.joints).astype(np.float64)
    if q.ndim == 1:
        q = q[None, :]
    if args.joint_names:
        with open(args.joint_names) as f:
            names = list(json.load(f))
    else:
        names = [j.name for j in bc.urdf_active_joints(urdf)]
    if q.shape[1] != len(names):
        ap.error(f"joints have {q.shape[1]} columns but {len(names)} joint names")
    q = np.tile(q, (max(args.repeat, 1), 1))
    cam = bc.load_camera(args.camera)
    workers = max(1, min(args.workers, len(q)))
    want = args.out is not None

    chunks = [c for c in np.array_split(q, workers) if len(c)]
    jobs = [(urdf, names, c, cam, want) for c in chunks]
    if workers == 1:
        results = [_render_chunk(jobs[0])]
    else:
        ctx = mp.get_context("fork")
        with ctx.Pool(workers) as pool:
            results = pool.map(_render_chunk, jobs)

    seconds = max(r[1] for r in results) - min(r[0] for r in results)
    if want:
        masks = np.concatenate([r[2] for r in results], axis=0)
        np.save(args.out, masks)
    print(
        json.dumps(
            {
                "renderer": "pybullet-tinyrenderer",
                "frames": int(len(q)),
                "seconds": round(seconds, 4),
                "masks_per_s": round(len(q) / seconds, 2) if seconds > 0 else None,
                "width": cam["width"],
                "height": cam["height"],
                "workers": workers,
            }
        ),
        file=out,
        flush=True,
    )


if __name__ == "__main__":
    main()
