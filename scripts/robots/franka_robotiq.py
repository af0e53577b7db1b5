#!/usr/bin/env python3
"""Rebuild crates/embodiment/robots/franka_robotiq/ (DROID's Franka Panda + Robotiq 2F-85).

Sources (read straight out of git, pinned commits):

* frankaemika/franka_ros @ c11f000c2737acc22ed8dfeff40555b2644a4294 (Apache-2.0, LICENSE + NOTICE):
  franka_description/meshes/visual/link{0..7}.dae (metres, Z up, several nodes per file);
  kinematics/limits from franka_description/robots/common/franka_arm.xacro and
  robots/panda/joint_limits.yaml (the standard Panda values, written out below).
* ros-industrial/robotiq @ 45196f6558fe8ba9d89bc8a105396c68c3e7e892 (BSD, LICENSE "Copyright (c) 2013, ROS-Industrial"):
  robotiq_2f_85_gripper_visualization/meshes/visual/robotiq_arg2f_85_{base_link,outer_knuckle,outer_finger,
  inner_knuckle,inner_finger,pad}.dae (millimetres: the xacro scales them by 0.001), robotiq_gripper_coupling.stl
  (millimetres), and the joint origins / mimics of urdf/robotiq_arg2f_85_model_macro.xacro (written out below).

Usage (get the two repositories as bare mirrors or clones first, e.g. `git clone --mirror`):

    python -m venv /tmp/frvenv && /tmp/frvenv/bin/pip install numpy trimesh fast-simplification pycollada lxml
    /tmp/frvenv/bin/python scripts/robots/franka_robotiq.py \
        --franka-ros /path/to/franka_ros(.git) --robotiq /path/to/robotiq(.git) \
        [--out crates/embodiment/robots/franka_robotiq]

Each mesh is loaded with trimesh (DAE node transforms applied, unit scale applied by hand: the Robotiq
DAEs carry no <unit> and are in mm), vertices merged, decimated with fast-simplification to the
triangle budget in TARGETS, and written as binary STL in the link frame (visual origin = identity).
The Robotiq pad mesh is merged into inner_finger.stl (it is given in the inner_finger frame).
"""

import argparse
import io
import math
import os
import subprocess
import sys

import numpy as np

FRANKA_COMMIT = "c11f000c2737acc22ed8dfeff40555b2644a4294"
ROBOTIQ_COMMIT = "45196f6558fe8ba9d89bc8a105396c68c3e7e892"
RQ = "robotiq_2f_85_gripper_visualization/meshes/visual/"

# output name -> (repo key, [source paths], scale, target triangles)
TARGETS = {
    "link0.stl": ("franka", ["franka_description/meshes/visual/link0.dae"], 1.0, 3500),
    "link1.stl": ("franka", ["franka_description/meshes/visual/link1.dae"], 1.0, 3500),
    "link2.stl": ("franka", ["franka_description/meshes/visual/link2.dae"], 1.0, 3500),
    "link3.stl": ("franka", ["franka_description/meshes/visual/link3.dae"], 1.0, 4000),
    "link4.stl": ("franka", ["franka_description/meshes/visual/link4.dae"], 1.0, 4000),
    "link5.stl": ("franka", ["franka_description/meshes/visual/link5.dae"], 1.0, 4000),
    "link6.stl": ("franka", ["franka_description/meshes/visual/link6.dae"], 1.0, 4500),
    "link7.stl": ("franka", ["franka_description/meshes/visual/link7.dae"], 1.0, 3000),
    "robotiq_coupling.stl": ("robotiq", [RQ + "robotiq_gripper_coupling.stl"], 0.001, 1200),
    "robotiq_base_link.stl": ("robotiq", [RQ + "robotiq_arg2f_85_base_link.dae"], 0.001, 5000),
    "robotiq_outer_knuckle.stl": ("robotiq", [RQ + "robotiq_arg2f_85_outer_knuckle.dae"], 0.001, 700),
    "robotiq_outer_finger.stl": ("robotiq", [RQ + "robotiq_arg2f_85_outer_finger.dae"], 0.001, 800),
    "robotiq_inner_knuckle.stl": ("robotiq", [RQ + "robotiq_arg2f_85_inner_knuckle.dae"], 0.001, 800),
    "robotiq_inner_finger.stl": (
        "robotiq",
        [RQ + "robotiq_arg2f_85_inner_finger.dae", RQ + "robotiq_arg2f_85_pad.dae"],
        0.001,
        900,
    ),
}

# ---- Mount (see README.md): Robotiq ISO-50 coupling (13.9 mm thick per the ROS-I coupling mesh, z -7.0..6.9 mm)
# on the flange, gripper base face on top of it; gripper yaw 0 about the flange z so that the fingers open along
# the flange y axis (DROID's wrist-camera calibration has image-x = -flange y and the fingers appear left/right
# in every DROID wrist video).
COUPLING_THICKNESS = 0.0139
COUPLING_CENTRE_Z = 0.0070  # coupling mesh origin is 7.0 mm above its bottom face
GRIPPER_YAW = 0.0
# ---- DROID wrist camera (ZED Mini, left eye, OpenCV optical axes x right, y down, z forward) relative to the
# flange: droid-dataset/droid @ 1548722f199772a43217c0d4c811c639be66e380, droid/calibration/calibration_info.json,
# entry "19824535_left" (xyz, then extrinsic-xyz Euler = URDF rpy); the hand-camera calibration is camera-to-
# "gripper pose" where the gripper pose is DROID's cartesian_position (= panda_link8), composed as
# T_base_cam = T_base_flange @ T_flange_cam (droid/robot_env.py, change_pose_frame). One rig's calibration.
WRIST_CAM_XYZ = (-0.07528310648512061, 0.02872136764193708, 0.023316565592628957)
WRIST_CAM_RPY = (-0.3255773557130956, 0.006247432431090383, -1.562874530416053)
WRIST_CAM_RIGHT_XYZ = (-0.06961440752114842, -0.035396599227355253, 0.020410786906711484)
WRIST_CAM_RIGHT_RPY = (-0.31886273624702377, 0.007822018427507738, -1.552143062181081)

PI = math.pi
HALF_PI = PI / 2
# Panda: name, origin xyz, origin rpy, lower, upper, effort, velocity (franka_arm.xacro / joint_limits.yaml)
PANDA = [
    ("panda_joint1", (0, 0, 0.333), (0, 0, 0), -2.8973, 2.8973, 87.0, 2.175),
    ("panda_joint2", (0, 0, 0), (-HALF_PI, 0, 0), -1.7628, 1.7628, 87.0, 2.175),
    ("panda_joint3", (0, -0.316, 0), (HALF_PI, 0, 0), -2.8973, 2.8973, 87.0, 2.175),
    ("panda_joint4", (0.0825, 0, 0), (HALF_PI, 0, 0), -3.0718, -0.0698, 87.0, 2.175),
    ("panda_joint5", (-0.0825, 0.384, 0), (-HALF_PI, 0, 0), -2.8973, 2.8973, 12.0, 2.61),
    ("panda_joint6", (0, 0, 0), (HALF_PI, 0, 0), -0.0175, 3.7525, 12.0, 2.61),
    ("panda_joint7", (0.088, 0, 0), (HALF_PI, 0, 0), -2.8973, 2.8973, 12.0, 2.61),
]

# The finger_joint closed value: q at which the two pad faces meet in this model (computed by
# check_franka_robotiq.py; 0.8 is the ROS-I upper limit).
FINGER_UPPER = 0.8


def read_source(root, commit, path):
    """Bytes of `path` from a git dir/clone (at `commit`) or from a plain directory."""
    plain = os.path.join(root, path)
    if os.path.isfile(plain) and not os.path.isdir(os.path.join(root, "objects")):
        with open(plain, "rb") as f:
            return f.read()
    gitdir = root
    if os.path.isdir(os.path.join(root, ".git")):
        gitdir = os.path.join(root, ".git")
    return subprocess.check_output(["git", "--git-dir", gitdir, "show", f"{commit}:{path}"])


def load_mesh(data, name, scale):
    import trimesh

    ext = os.path.splitext(name)[1].lower().lstrip(".")
    loaded = trimesh.load(io.BytesIO(data), file_type=ext)
    if isinstance(loaded, trimesh.Scene):
        mesh = loaded.to_geometry()  # applies node transforms
    else:
        mesh = loaded
    mesh = trimesh.Trimesh(vertices=np.asarray(mesh.vertices) * scale, faces=np.asarray(mesh.faces), process=True)
    mesh.merge_vertices()
    return mesh


def decimate(mesh, target):
    import fast_simplification
    import trimesh

    n = len(mesh.faces)
    if n <= target:
        return mesh
    v, f = fast_simplification.simplify(
        np.asarray(mesh.vertices, dtype=np.float32), np.asarray(mesh.faces, dtype=np.int32), 1.0 - target / n
    )
    return trimesh.Trimesh(vertices=v, faces=f, process=True)


def write_stl(mesh, path):
    tri = np.asarray(mesh.vertices, dtype=np.float64)[np.asarray(mesh.faces)]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(ln > 0, n / np.maximum(ln, 1e-30), 0.0)
    rec = np.zeros(len(tri), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
    rec["n"] = n
    rec["v"] = tri
    with open(path, "wb") as f:
        f.write(b"bridgev2w franka_robotiq binary STL, metres".ljust(80, b" "))
        f.write(np.uint32(len(tri)).tobytes())
        f.write(rec.tobytes())


def fmt(x):
    s = f"{x:.10g}"
    return "0" if s in ("-0", "0") else s


def v3(t):
    return " ".join(fmt(x) for x in t)


def link(name, mesh=None, rgba=None):
    if mesh is None:
        return f'  <link name="{name}"/>\n'
    return (
        f'  <link name="{name}">\n'
        f"    <visual>\n"
        f'      <origin xyz="0 0 0" rpy="0 0 0"/>\n'
        f'      <geometry><mesh filename="meshes/{mesh}"/></geometry>\n'
        f'      <material name="{name}_material"><color rgba="{rgba}"/></material>\n'
        f"    </visual>\n"
        f"    <collision>\n"
        f'      <origin xyz="0 0 0" rpy="0 0 0"/>\n'
        f'      <geometry><mesh filename="meshes/{mesh}"/></geometry>\n'
        f"    </collision>\n"
        f"  </link>\n"
    )


def joint(name, jtype, parent, child, xyz, rpy, axis=None, limit=None, mimic=None):
    s = f'  <joint name="{name}" type="{jtype}">\n'
    s += f'    <origin xyz="{v3(xyz)}" rpy="{v3(rpy)}"/>\n'
    s += f'    <parent link="{parent}"/>\n    <child link="{child}"/>\n'
    if axis is not None:
        s += f'    <axis xyz="{v3(axis)}"/>\n'
    if limit is not None:
        lo, hi, eff, vel = limit
        s += f'    <limit lower="{fmt(lo)}" upper="{fmt(hi)}" effort="{fmt(eff)}" velocity="{fmt(vel)}"/>\n'
    if mimic is not None:
        s += f'    <mimic joint="{mimic[0]}" multiplier="{fmt(mimic[1])}" offset="{fmt(mimic[2])}"/>\n'
    return s + "  </joint>\n"


# Robotiq 2F-85 (ROS-I robotiq_arg2f_85_model_macro.xacro), link frames as there.
PAD_XYZ = (0, -0.0220203446692936, 0.03242)
TCP_Z_FROM_BASE = None  # filled in by tcp_offset()


def finger_z_of_pad_centre(q):
    """Pad-centre position in the gripper base frame for the left finger at finger_joint q (numpy FK)."""

    def T(xyz, rpy):
        r, p, y = rpy
        cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
        M = np.eye(4)
        M[:3, :3] = np.array(
            [
                [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                [-sp, cp * sr, cp * cr],
            ]
        )
        M[:3, 3] = xyz
        return M

    def Rx(a):
        return T((0, 0, 0), (a, 0, 0))

    M = T((0, -0.0306011, 0.054904), (0, 0, PI)) @ Rx(q)  # finger_joint
    M = M @ T((0, 0.0315, -0.0041), (0, 0, 0))  # outer finger
    M = M @ T((0, 0.0061, 0.0471), (0, 0, 0)) @ Rx(-q)  # inner finger
    M = M @ T(PAD_XYZ, (0, 0, 0))
    return M[:3, 3]


def tcp_offset(q_closed):
    p = finger_z_of_pad_centre(q_closed)
    return p[2]


def build_urdf():
    white = "0.95 0.95 0.95 1"
    dark = "0.25 0.25 0.25 1"
    black = "0.1 0.1 0.1 1"
    grey = "0.79 0.82 0.93 1"
    out = ['<?xml version="1.0"?>\n']
    out.append(
        "<!-- DROID's robot: Franka Emika Panda + Robotiq 2F-85 on the Robotiq ISO-50 coupling.\n"
        "     Generated by scripts/robots/franka_robotiq.py; see README.md here for provenance, licences,\n"
        "     frames, joint order and gripper mapping. Units: metres, radians. -->\n"
    )
    out.append('<robot name="franka_robotiq">\n')
    colors = [white, white, white, white, dark, white, white, dark]
    out.append(link("panda_link0", "link0.stl", white))
    parent = "panda_link0"
    for i, (jn, xyz, rpy, lo, hi, eff, vel) in enumerate(PANDA):
        child = f"panda_link{i + 1}"
        out.append(link(child, f"link{i + 1}.stl", colors[i + 1]))
        out.append(joint(jn, "revolute", parent, child, xyz, rpy, (0, 0, 1), (lo, hi, eff, vel)))
        parent = child
    out.append(link("panda_link8"))
    out.append(joint("panda_joint8", "fixed", "panda_link7", "panda_link8", (0, 0, 0.107), (0, 0, 0)))
    # coupling + gripper base
    out.append(link("robotiq_coupling", "robotiq_coupling.stl", black))
    out.append(
        joint(
            "robotiq_coupling_joint", "fixed", "panda_link8", "robotiq_coupling", (0, 0, COUPLING_CENTRE_Z),
            (0, 0, GRIPPER_YAW),
        )
    )
    out.append(link("robotiq_arg2f_base_link", "robotiq_base_link.stl", black))
    out.append(
        joint(
            "robotiq_base_joint", "fixed", "panda_link8", "robotiq_arg2f_base_link", (0, 0, COUPLING_THICKNESS),
            (0, 0, GRIPPER_YAW),
        )
    )
    B = "robotiq_arg2f_base_link"
    lim = lambda lo, hi: (lo, hi, 1000.0, 2.0)  # noqa: E731
    # left finger chain (finger_joint is the driver)
    out.append(link("left_outer_knuckle", "robotiq_outer_knuckle.stl", grey))
    out.append(
        joint("finger_joint", "revolute", B, "left_outer_knuckle", (0, -0.0306011, 0.054904), (0, 0, PI), (1, 0, 0),
              lim(0.0, FINGER_UPPER))
    )
    for side, reflect in (("left", 1.0), ("right", -1.0)):
        if side == "right":
            out.append(link("right_outer_knuckle", "robotiq_outer_knuckle.stl", grey))
            out.append(
                joint("right_outer_knuckle_joint", "revolute", B, "right_outer_knuckle", (0, 0.0306011, 0.054904),
                      (0, 0, 0), (1, 0, 0), lim(0.0, FINGER_UPPER), ("finger_joint", 1, 0))
            )
        out.append(link(f"{side}_outer_finger", "robotiq_outer_finger.stl", black))
        out.append(
            joint(f"{side}_outer_finger_joint", "fixed", f"{side}_outer_knuckle", f"{side}_outer_finger",
                  (0, 0.0315, -0.0041), (0, 0, 0))
        )
        out.append(link(f"{side}_inner_knuckle", "robotiq_inner_knuckle.stl", black))
        out.append(
            joint(f"{side}_inner_knuckle_joint", "revolute", B, f"{side}_inner_knuckle",
                  (0, reflect * -0.0127, 0.06142), (0, 0, (1 + reflect) * PI / 2), (1, 0, 0),
                  lim(0.0, FINGER_UPPER), ("finger_joint", 1, 0))
        )
        out.append(link(f"{side}_inner_finger", "robotiq_inner_finger.stl", black))
        out.append(
            joint(f"{side}_inner_finger_joint", "revolute", f"{side}_outer_finger", f"{side}_inner_finger",
                  (0, 0.0061, 0.0471), (0, 0, 0), (1, 0, 0), lim(-FINGER_UPPER, 0.0), ("finger_joint", -1, 0))
        )
        out.append(link(f"{side}_inner_finger_pad"))
        out.append(
            joint(f"{side}_inner_finger_pad_joint", "fixed", f"{side}_inner_finger", f"{side}_inner_finger_pad",
                  PAD_XYZ, (0, 0, 0))
        )
    # TCP: centre between the pad centres with the gripper closed, on the flange z axis.
    tcp_z = COUPLING_THICKNESS + tcp_offset(FINGER_UPPER)
    out.append(link("robotiq_tcp"))
    out.append(joint("robotiq_tcp_joint", "fixed", "panda_link8", "robotiq_tcp", (0, 0, tcp_z), (0, 0, GRIPPER_YAW)))
    # wrist camera (ZED Mini left eye, OpenCV optical frame), from DROID's example calibration
    out.append(link("droid_wrist_camera_left_optical"))
    out.append(joint("droid_wrist_camera_left_joint", "fixed", "panda_link8", "droid_wrist_camera_left_optical",
                     WRIST_CAM_XYZ, WRIST_CAM_RPY))
    out.append(link("droid_wrist_camera_right_optical"))
    out.append(joint("droid_wrist_camera_right_joint", "fixed", "panda_link8", "droid_wrist_camera_right_optical",
                     WRIST_CAM_RIGHT_XYZ, WRIST_CAM_RIGHT_RPY))
    out.append("</robot>\n")
    return "".join(out), tcp_z


def main():
    here = os.path.dirname(os.path.abspath(__file__))
    repo = os.path.dirname(os.path.dirname(here))
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--franka-ros", required=True, help="frankaemika/franka_ros git dir, clone or checkout")
    ap.add_argument("--robotiq", required=True, help="ros-industrial/robotiq git dir, clone or checkout")
    ap.add_argument("--out", default=os.path.join(repo, "crates/embodiment/robots/franka_robotiq"))
    ap.add_argument("--urdf-only", action="store_true", help="rewrite the URDF only")
    args = ap.parse_args()
    roots = {"franka": (args.franka_ros, FRANKA_COMMIT), "robotiq": (args.robotiq, ROBOTIQ_COMMIT)}
    os.makedirs(os.path.join(args.out, "meshes"), exist_ok=True)
    if not args.urdf_only:
        total_t, total_b = 0, 0
        for out_name, (key, paths, scale, target) in TARGETS.items():
            root, commit = roots[key]
            import trimesh

            parts = [load_mesh(read_source(root, commit, p), p, scale) for p in paths]
            src = trimesh.util.concatenate(parts) if len(parts) > 1 else parts[0]
            dec = decimate(src, target)
            path = os.path.join(args.out, "meshes", out_name)
            write_stl(dec, path)
            size = os.path.getsize(path)
            total_t += len(dec.faces)
            total_b += size
            lo, hi = dec.bounds
            print(f"{out_name:28s} {len(src.faces):6d} -> {len(dec.faces):5d} tris {size:8d} B "
                  f"bounds {np.round(lo, 4).tolist()} .. {np.round(hi, 4).tolist()}")
        print(f"total {total_t} triangles, {total_b} bytes")
        for lic_root, commit, src_path, dst in (
            (args.franka_ros, FRANKA_COMMIT, "LICENSE", "LICENSE-franka_ros-Apache-2.0.txt"),
            (args.franka_ros, FRANKA_COMMIT, "NOTICE", "NOTICE-franka_ros.txt"),
            (args.robotiq, ROBOTIQ_COMMIT, "LICENSE", "LICENSE-ros-industrial-robotiq-BSD.txt"),
        ):
            with open(os.path.join(args.out, dst), "wb") as f:
                f.write(read_source(lic_root, commit, src_path))
    urdf, tcp_z = build_urdf()
    with open(os.path.join(args.out, "franka_robotiq.urdf"), "w") as f:
        f.write(urdf)
    print(f"wrote {args.out}/franka_robotiq.urdf; flange -> robotiq_tcp z = {tcp_z:.5f} m")


if __name__ == "__main__":
    sys.exit(main())
