#!/usr/bin/env python3
"""Write example bench inputs: camera.json, joints.npy and joint_names.json.

- camera.json: 720x480 OpenCV pinhole camera (fx = fy = 600, principal point
  at the image centre) about 1.5 m from the robot, in front and to the side,
  looking at the middle of the arm. Format:
  {"fx","fy","cx","cy","width","height","world_from_camera": 4x4 row-major}
  with OpenCV camera axes (x right, y down, z forward).
- joints.npy: float64 [T, 7] Panda trajectory sweeping around the home pose
  q = [0, -0.785, 0, -2.356, 0, 1.571, 0.785] (T = 25 by default).
- joint_names.json: ["panda_joint1", ..., "panda_joint7"] (the names of
  pybullet's franka_panda/panda.urdf and of crates/embodiment/robots/franka/franka.urdf).

Prints the three paths as one JSON line.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import bench_common as bc  # noqa: E402

HOME = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])


def trajectory(frames: int) -> np.ndarray:
    t = np.linspace(0.0, 1.0, frames)
    q = np.tile(HOME, (frames, 1))
    q[:, 0] += 0.8 * np.sin(2 * np.pi * t)  # base sweep
    q[:, 1] += 0.35 * np.sin(4 * np.pi * t)  # shoulder nod
    q[:, 3] += 0.4 * (1 - np.cos(2 * np.pi * t)) / 2  # elbow opens a bit (stays < -0.07)
    q[:, 5] += 0.3 * np.sin(2 * np.pi * t)
    q[:, 6] += 0.6 * np.sin(2 * np.pi * t)
    return q


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out-dir", default="demo-out/bench", help="directory to write into (default: demo-out/bench)")
    ap.add_argument("--frames", type=int, default=25)
    ap.add_argument("--width", type=int, default=720)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--fx", type=float, default=600.0)
    args = ap.parse_args()

    os.makedirs(args.out_dir, exist_ok=True)
    cam = bc.look_at_camera(
        eye=(1.3, -0.75, 0.75), target=(0.1, 0.0, 0.4), width=args.width, height=args.height, fx=args.fx
    )
    paths = {
        "camera": os.path.join(args.out_dir, "camera.json"),
        "joints": os.path.join(args.out_dir, "joints.npy"),
        "joint_names": os.path.join(args.out_dir, "joint_names.json"),
    }
    with open(paths["camera"], "w") as f:
        json.dump(bc.camera_to_json(cam), f, indent=2)
    np.save(paths["joints"], trajectory(args.frames))
    with open(paths["joint_names"], "w") as f:
        json.dump([f"panda_joint{i}" for i in range(1, 8)], f)
    print(json.dumps(paths))


if __name__ == "__main__":
    main()
