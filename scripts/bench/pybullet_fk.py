#!/usr/bin/env python3
"""Forward-kinematics reference: world poses of URDF link frames from pybullet.

The URDF is loaded with useFixedBase=True and the base at the origin. For each
joint configuration the named joints are set with resetJointState (mimic
joints follow their master per the URDF `<mimic>`), then
getLinkState(computeForwardKinematics=True) gives the URDF link frame
(worldLinkFramePosition / worldLinkFrameOrientation, indices 4 and 5; not
the centre of mass). The base link's pose is the identity.

Configurations come either from --joints FILE.npy ([T, n] or [n]) in the order
of --joint-names FILE.json (default: the URDF's active joints, i.e. movable
non-mimic joints in document order), or from --random N --seed S (uniform
within the URDF limits of the active joints).

Output (stdout, or --out FILE.json / FILE.npz):
  {"urdf": path, "joint_names": [...], "q": [[...], ...],
   "links": {name: {"position": [[x,y,z], ...],
                    "quaternion_xyzw": [[x,y,z,w], ...],
                    "matrix": [[4x4 row-major], ...]}}}
The .npz holds q [T,n], joint_names, link_names [L], position [T,L,3],
quaternion_xyzw [T,L,4] and matrix [T,L,4,4].

Example:
  .venv-bench/bin/python scripts/bench/pybullet_fk.py \
      --urdf crates/embodiment/robots/franka/franka.urdf --random 100 --seed 0 \
      --links panda_link8,panda_hand_tcp --out /tmp/fk.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import bench_common as bc  # noqa: E402


def quat_to_matrix(q):
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def compute_fk(urdf: str, names: list[str], q: np.ndarray, links: list[str] | None = None):
    """Returns (link_names, position [T,L,3], quaternion_xyzw [T,L,4], matrix [T,L,4,4])."""
    import pybullet as p

    client = p.connect(p.DIRECT)
    try:
        body = p.loadURDF(urdf, [0, 0, 0], [0, 0, 0, 1], useFixedBase=True, physicsClientId=client)
        joint_index, link_index = bc.pybullet_index_maps(p, body, client)
        if links is None:
            links = list(link_index.keys())
        missing = [n for n in names if n not in joint_index] + [n for n in links if n not in link_index]
        if missing:
            raise KeyError(f"not in URDF: {missing}")
        mimics = [j for j in bc.urdf_joints(urdf) if j.mimic is not None]
        T, L = len(q), len(links)
        pos = np.zeros((T, L, 3))
        quat = np.zeros((T, L, 4))
        mat = np.tile(np.eye(4), (T, L, 1, 1))
        for t in range(T):
            bc.set_joints(p, body, client, joint_index, names, q[t], mimics)
            for k, name in enumerate(links):
                li = link_index[name]
                if li < 0:
                    quat[t, k] = (0, 0, 0, 1)
                    continue
                st = p.getLinkState(body, li, computeForwardKinematics=True, physicsClientId=client)
                pos[t, k] = st[4]
                quat[t, k] = st[5]
                mat[t, k, :3, :3] = quat_to_matrix(st[5])
                mat[t, k, :3, 3] = st[4]
        return links, pos, quat, mat
    finally:
        p.disconnect(physicsClientId=client)


def random_configs(urdf: str, n: int, seed: int):
    active = bc.urdf_active_joints(urdf)
    rng = np.random.default_rng(seed)
    lo = np.array([j.lower for j in active])
    hi = np.array([j.upper for j in active])
    return [j.name for j in active], lo + (hi - lo) * rng.random((n, len(active)))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--urdf", required=True, help="URDF path or pybullet:<path in pybullet_data>")
    ap.add_argument("--joints", help="float array [T, n] (.npy)")
    ap.add_argument("--joint-names", help="JSON list of joint names (default: URDF active joints)")
    ap.add_argument("--random", type=int, help="use N random configurations within the joint limits")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--links", help="comma-separated link names (default: all links)")
    ap.add_argument("--out", help="write .json or .npz instead of printing JSON")
    args = ap.parse_args()
    out = bc.real_stdout()

    urdf = bc.resolve_urdf(args.urdf)
    if args.random is not None:
        names, q = random_configs(urdf, args.random, args.seed)
    elif args.joints:
        q = np.load(args.joints).astype(np.float64)
        q = q[None, :] if q.ndim == 1 else q
        if args.joint_names:
            with open(args.joint_names) as f:
                names = list(json.load(f))
        else:
            names = [j.name for j in bc.urdf_active_joints(urdf)]
        if q.shape[1] != len(names):
            ap.error(f"joints have {q.shape[1]} columns but {len(names)} joint names")
    else:
        ap.error("give --joints or --random")

    links = args.links.split(",") if args.links else None
    links, pos, quat, mat = compute_fk(urdf, names, q, links)

    if args.out and args.out.endswith(".npz"):
        np.savez(
            args.out,
            q=q,
            joint_names=np.array(names),
            link_names=np.array(links),
            position=pos,
            quaternion_xyzw=quat,
            matrix=mat,
        )
        print(json.dumps({"out": args.out, "configs": len(q), "links": len(links)}), file=out)
        return
    doc = {
        "urdf": urdf,
        "joint_names": names,
        "q": q.tolist(),
        "links": {
            name: {
                "position": pos[:, k].tolist(),
                "quaternion_xyzw": quat[:, k].tolist(),
                "matrix": mat[:, k].tolist(),
            }
            for k, name in enumerate(links)
        },
    }
    if args.out:
        with open(args.out, "w") as f:
            json.dump(doc, f)
        print(json.dumps({"out": args.out, "configs": len(q), "links": len(links)}), file=out)
    else:
        print(json.dumps(doc), file=out)


if __name__ == "__main__":
    main()
