#!/usr/bin/env python3
"""Generate the built-in robot URDFs in crates/embodiment/robots/.

The URDFs are plain text and are committed; this script is the single source
of truth for their numbers (geometry, inertials, limits) so they can be
regenerated after an edit:

    python3 scripts/gen_robot_urdfs.py            # writes both URDFs
    python3 scripts/gen_robot_urdfs.py --check    # exit 1 if the files differ

Only primitive geometry (box, cylinder, sphere) is used. Inertials are
computed from the primitive shapes with a given mass per link (solid bodies,
mass split by volume), so they are consistent with the geometry.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
OUT_DIR = REPO / "crates" / "embodiment" / "robots"

PI = math.pi


def fmt(x: float) -> str:
    """Short, exact-enough decimal formatting (no exponent for normal values)."""
    if abs(x) < 1e-15:
        return "0"
    s = repr(float(x))
    if "e" in s:
        s = f"{x:.12f}".rstrip("0").rstrip(".")
    if s.endswith(".0"):
        s = s[:-2]
    return s


def vec(v) -> str:
    return " ".join(fmt(c) for c in v)


# ---------------------------------------------------------------------------
# Geometry primitives: (kind, params, xyz, rpy)
#   box:      params = (sx, sy, sz)
#   cylinder: params = (radius, length)   axis along local z
#   sphere:   params = (radius,)
# ---------------------------------------------------------------------------


def box(size, xyz=(0, 0, 0), rpy=(0, 0, 0)):
    return ("box", tuple(size), tuple(xyz), tuple(rpy))


def cyl(radius, length, xyz=(0, 0, 0), rpy=(0, 0, 0)):
    return ("cylinder", (radius, length), tuple(xyz), tuple(rpy))


def sph(radius, xyz=(0, 0, 0)):
    return ("sphere", (radius,), tuple(xyz), (0, 0, 0))


# Cylinder orientations: local z onto a given axis.
ALONG_X = (0, PI / 2, 0)
ALONG_Y = (PI / 2, 0, 0)
ALONG_Z = (0, 0, 0)


def cyl_between(radius, p0, p1):
    """Cylinder whose axis runs from p0 to p1 (p0, p1 differ along one axis)."""
    d = [b - a for a, b in zip(p0, p1)]
    axis = max(range(3), key=lambda i: abs(d[i]))
    others = [i for i in range(3) if i != axis]
    assert all(abs(d[i]) < 1e-12 for i in others), "cyl_between needs an axis-aligned segment"
    length = abs(d[axis])
    mid = tuple((a + b) / 2 for a, b in zip(p0, p1))
    rpy = (ALONG_X, ALONG_Y, ALONG_Z)[axis]
    return cyl(radius, length, mid, rpy)


def shape_volume(g) -> float:
    kind, p, _, _ = g
    if kind == "box":
        return p[0] * p[1] * p[2]
    if kind == "cylinder":
        return PI * p[0] ** 2 * p[1]
    return 4.0 / 3.0 * PI * p[0] ** 3


def rot_rpy(rpy):
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    # URDF: R = Rz(yaw) * Ry(pitch) * Rx(roll)
    return [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]


def shape_local_inertia(g, m):
    """Diagonal inertia about the shape centre in the shape frame."""
    kind, p, _, _ = g
    if kind == "box":
        sx, sy, sz = p
        return [m / 12 * (sy * sy + sz * sz), m / 12 * (sx * sx + sz * sz), m / 12 * (sx * sx + sy * sy)]
    if kind == "cylinder":
        r, h = p
        ixx = m / 12 * (3 * r * r + h * h)
        return [ixx, ixx, m / 2 * r * r]
    r = p[0]
    i = 2.0 / 5.0 * m * r * r
    return [i, i, i]


def inertial(shapes, mass):
    """Mass properties of a union of solid shapes (overlaps ignored)."""
    vols = [shape_volume(g) for g in shapes]
    vtot = sum(vols)
    masses = [mass * v / vtot for v in vols]
    com = [sum(m * g[2][i] for m, g in zip(masses, shapes)) / mass for i in range(3)]
    inertia = [[0.0] * 3 for _ in range(3)]
    for m, g in zip(masses, shapes):
        R = rot_rpy(g[3])
        d = shape_local_inertia(g, m)
        # R * diag(d) * R^T
        for i in range(3):
            for j in range(3):
                inertia[i][j] += sum(R[i][k] * d[k] * R[j][k] for k in range(3))
        # parallel axis theorem
        r = [g[2][i] - com[i] for i in range(3)]
        rr = sum(c * c for c in r)
        for i in range(3):
            for j in range(3):
                inertia[i][j] += m * ((rr if i == j else 0.0) - r[i] * r[j])
    return com, inertia


def round_sig(x, sig=4):
    if x == 0:
        return 0.0
    return round(x, sig - 1 - int(math.floor(math.log10(abs(x)))))


# ---------------------------------------------------------------------------
# URDF writer
# ---------------------------------------------------------------------------


class Urdf:
    def __init__(self, name: str, header: str):
        self.lines = ['<?xml version="1.0"?>', f"<!-- {header} -->", f'<robot name="{name}">']
        self.materials: dict[str, tuple] = {}

    def material(self, name, rgba):
        self.materials[name] = rgba
        self.lines.append(f'  <material name="{name}">')
        self.lines.append(f'    <color rgba="{vec(rgba)}"/>')
        self.lines.append("  </material>")

    def comment(self, text):
        self.lines.append(f"  <!-- {text} -->")

    @staticmethod
    def _geom(g, indent):
        kind, p, _, _ = g
        if kind == "box":
            return f'{indent}<box size="{vec(p)}"/>'
        if kind == "cylinder":
            return f'{indent}<cylinder radius="{fmt(p[0])}" length="{fmt(p[1])}"/>'
        return f'{indent}<sphere radius="{fmt(p[0])}"/>'

    def link(self, name, shapes=(), mass=None, material=None, collision=True):
        L = self.lines
        L.append(f'  <link name="{name}">')
        if shapes:
            com, inertia = inertial(shapes, mass)
            L.append("    <inertial>")
            L.append(f'      <origin xyz="{vec(round_sig(c, 4) for c in com)}" rpy="0 0 0"/>')
            L.append(f'      <mass value="{fmt(mass)}"/>')
            I = [[round_sig(inertia[i][j], 4) for j in range(3)] for i in range(3)]
            L.append(
                f'      <inertia ixx="{fmt(I[0][0])}" ixy="{fmt(I[0][1])}" ixz="{fmt(I[0][2])}" '
                f'iyy="{fmt(I[1][1])}" iyz="{fmt(I[1][2])}" izz="{fmt(I[2][2])}"/>'
            )
            L.append("    </inertial>")
        elif mass is not None:
            L.append("    <inertial>")
            L.append('      <origin xyz="0 0 0" rpy="0 0 0"/>')
            L.append(f'      <mass value="{fmt(mass)}"/>')
            L.append('      <inertia ixx="1e-06" ixy="0" ixz="0" iyy="1e-06" iyz="0" izz="1e-06"/>')
            L.append("    </inertial>")
        for tag in ("visual", "collision") if collision else ("visual",):
            for g in shapes:
                L.append(f"    <{tag}>")
                L.append(f'      <origin xyz="{vec(g[2])}" rpy="{vec(g[3])}"/>')
                L.append("      <geometry>")
                L.append(self._geom(g, "        "))
                L.append("      </geometry>")
                if tag == "visual" and material:
                    L.append(f'      <material name="{material}"/>')
                L.append(f"    </{tag}>")
        L.append("  </link>")

    def joint(self, name, kind, parent, child, xyz=(0, 0, 0), rpy=(0, 0, 0), axis=None, limit=None, mimic=None):
        L = self.lines
        L.append(f'  <joint name="{name}" type="{kind}">')
        L.append(f'    <parent link="{parent}"/>')
        L.append(f'    <child link="{child}"/>')
        L.append(f'    <origin xyz="{vec(xyz)}" rpy="{vec(rpy)}"/>')
        if axis is not None:
            L.append(f'    <axis xyz="{vec(axis)}"/>')
        if limit is not None:
            lo, hi, effort, velocity = limit
            L.append(
                f'    <limit lower="{fmt(lo)}" upper="{fmt(hi)}" effort="{fmt(effort)}" velocity="{fmt(velocity)}"/>'
            )
        if mimic is not None:
            L.append(f'    <mimic joint="{mimic}" multiplier="1" offset="0"/>')
        if kind != "fixed":
            L.append('    <dynamics damping="0.1" friction="0"/>' if kind == "revolute" else '    <dynamics damping="1" friction="0"/>')
        L.append("  </joint>")

    def text(self):
        return "\n".join(self.lines + ["</robot>", ""])


# ---------------------------------------------------------------------------
# Franka Emika Panda
# ---------------------------------------------------------------------------

# Modified (Craig) DH: (a, d, alpha) for joints 1..7 and the flange.
PANDA_DH = [
    (0.0, 0.333, 0.0),
    (0.0, 0.0, -PI / 2),
    (0.0, 0.316, PI / 2),
    (0.0825, 0.0, PI / 2),
    (-0.0825, 0.384, -PI / 2),
    (0.0, 0.0, PI / 2),
    (0.088, 0.0, PI / 2),
    (0.0, 0.107, 0.0),  # flange (panda_joint8, fixed)
]
PANDA_LOWER = [-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973]
PANDA_UPPER = [2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973]
PANDA_EFFORT = [87, 87, 87, 87, 12, 12, 12]
PANDA_VELOCITY = [2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61]


def dh_origin(a, d, alpha):
    """URDF origin equal to RotX(alpha) * TransX(a) * TransZ(d)."""
    xyz = (a, -math.sin(alpha) * d, math.cos(alpha) * d)
    # clean up -0.0 / 1e-17 noise
    xyz = tuple(0.0 if abs(c) < 1e-15 else c for c in xyz)
    return xyz, (alpha, 0.0, 0.0)


def panda() -> str:
    u = Urdf(
        "panda",
        "Franka Emika Panda with parallel gripper, primitive geometry. Generated by "
        "scripts/gen_robot_urdfs.py; kinematics from the modified DH table "
        "(a, d, alpha): J1 0/0.333/0, J2 0/0/-pi/2, J3 0/0.316/pi/2, J4 0.0825/0/pi/2, "
        "J5 -0.0825/0.384/-pi/2, J6 0/0/pi/2, J7 0.088/0/pi/2, flange 0/0.107/0.",
    )
    u.material("panda_white", (0.92, 0.92, 0.92, 1))
    u.material("panda_dark", (0.25, 0.25, 0.28, 1))
    u.material("panda_black", (0.08, 0.08, 0.08, 1))

    r = 0.06  # nominal link radius
    # Link shapes, each in its own link frame (derived from the frame
    # orientations produced by the DH origins; comments give the directions
    # at q = 0 in the base frame).
    links = {
        # Base: a foot plate plus the lower housing up to z = 0.14.
        "panda_link0": (
            [
                box((0.26, 0.2, 0.02), (-0.04, 0, 0.01)),
                cyl_between(0.07, (0, 0, 0.02), (0, 0, 0.14)),
                box((0.1, 0.12, 0.1), (-0.08, 0, 0.07)),
            ],
            2.9,
            "panda_white",
        ),
        # Link1 frame sits on the J2 axis height (z=0.333), z up: vertical
        # column from the base housing (z=-0.193) up to the J2 axis.
        "panda_link1": (
            [cyl_between(r, (0, 0, -0.193), (0, 0, -0.03)), sph(r, (0, 0, 0))],
            4.97,
            "panda_white",
        ),
        # Link2 frame: z = base +y (J2 axis), -y = base up. Shoulder housing
        # around the J2 axis plus the lower half of the upper arm.
        "panda_link2": (
            [cyl(r, 0.13, (0, 0, 0), ALONG_Z), cyl_between(r, (0, 0, 0), (0, -0.17, 0))],
            0.65,
            "panda_white",
        ),
        # Link3 frame: at the top of the upper arm (0.316 above J2), z up.
        # Upper half of the upper arm plus the elbow offset towards +x.
        "panda_link3": (
            [
                cyl_between(r, (0, 0, -0.146), (0, 0, -0.02)),
                sph(r, (0, 0, 0)),
                cyl_between(r * 0.95, (0, 0, 0), (0.0825, 0, 0)),
            ],
            3.23,
            "panda_white",
        ),
        # Link4 frame: at the elbow (J4 axis = base -y), y = forearm direction.
        # Elbow housing around J4, a short stub of the forearm, and the crank
        # that carries the J5 bearing over to the J5 axis (x = -0.0825 here).
        "panda_link4": (
            [
                cyl(r, 0.13, (0, 0, 0), ALONG_Z),
                cyl_between(r * 0.95, (0, 0, 0), (0, 0.13, 0)),
                box((0.18, 0.08, 0.1), (-0.04125, 0.13, 0)),
            ],
            3.59,
            "panda_white",
        ),
        # Link5 frame: at the wrist (J6 axis), z = forearm axis (J5) pointing
        # away from the elbow. The forearm is coaxial with J5 from the J5
        # bearing on link4's crank (z = -0.384 + 0.13) up to the wrist.
        "panda_link5": (
            [
                cyl_between(0.055, (0, 0, -0.254), (0, 0, -0.06)),
                box((0.07, 0.1, 0.12), (0.0, 0, -0.16)),
                cyl_between(0.05, (0, 0, -0.06), (0, 0, 0.0)),
            ],
            1.23,
            "panda_white",
        ),
        # Link6 frame: at the wrist, z = J6 axis (base -y), y = base up at q=0.
        # Wrist housing around J6 plus the head reaching the J7 axis at x=0.088.
        "panda_link6": (
            [cyl(0.055, 0.13, (0, 0, 0), ALONG_Z), box((0.14, 0.1, 0.1), (0.06, 0, 0))],
            1.67,
            "panda_white",
        ),
        # Link7 frame: on the J7 axis, z = flange direction (base down at q=0).
        "panda_link7": (
            [cyl_between(0.05, (0, 0, 0.05), (0, 0, 0.1))],
            0.74,
            "panda_dark",
        ),
        # Flange: a thin disk on the mounting face.
        "panda_link8": ([cyl_between(0.04, (0, 0, -0.007), (0, 0, 0))], 0.05, "panda_dark"),
        # Hand: fingers move along hand y; body spans z 0..0.066 under the flange.
        "panda_hand": (
            [cyl_between(0.04, (0, 0, 0), (0, 0, 0.012)), box((0.06, 0.2, 0.054), (0, 0, 0.039))],
            0.73,
            "panda_white",
        ),
        # Fingers: 0.02 (x) by 0.01 (y) by 0.054 (z) pads whose inner faces
        # touch at y = 0 when the joint is at 0 (closed).
        "panda_leftfinger": ([box((0.02, 0.01, 0.054), (0, 0.005, 0.027))], 0.015, "panda_black"),
        "panda_rightfinger": ([box((0.02, 0.01, 0.054), (0, -0.005, 0.027))], 0.015, "panda_black"),
    }

    def add_link(name):
        shapes, mass, mat = links[name]
        u.link(name, shapes, mass, mat)

    add_link("panda_link0")
    parent = "panda_link0"
    for i, (a, d, alpha) in enumerate(PANDA_DH):
        child = f"panda_link{i + 1}"
        add_link(child)
        xyz, rpy = dh_origin(a, d, alpha)
        if i < 7:
            u.joint(
                f"panda_joint{i + 1}",
                "revolute",
                parent,
                child,
                xyz,
                rpy,
                axis=(0, 0, 1),
                limit=(PANDA_LOWER[i], PANDA_UPPER[i], PANDA_EFFORT[i], PANDA_VELOCITY[i]),
            )
        else:
            u.joint("panda_joint8", "fixed", parent, child, xyz, rpy)
        parent = child

    add_link("panda_hand")
    u.joint("panda_hand_joint", "fixed", "panda_link8", "panda_hand", (0, 0, 0), (0, 0, -PI / 4))
    u.link("panda_hand_tcp", mass=0.001)
    u.joint("panda_hand_tcp_joint", "fixed", "panda_hand", "panda_hand_tcp", (0, 0, 0.1034), (0, 0, 0))
    add_link("panda_leftfinger")
    add_link("panda_rightfinger")
    u.joint(
        "panda_finger_joint1",
        "prismatic",
        "panda_hand",
        "panda_leftfinger",
        (0, 0, 0.0584),
        axis=(0, 1, 0),
        limit=(0.0, 0.04, 100, 0.2),
    )
    u.joint(
        "panda_finger_joint2",
        "prismatic",
        "panda_hand",
        "panda_rightfinger",
        (0, 0, 0.0584),
        axis=(0, -1, 0),
        limit=(0.0, 0.04, 100, 0.2),
        mimic="panda_finger_joint1",
    )
    return u.text()


# ---------------------------------------------------------------------------
# dual_arm: an invented dual-arm robot (the synthetic world's second robot; not the AgiBot G1)
# ---------------------------------------------------------------------------

SHOULDER_Y = 0.2  # torso centre to the J1 (shoulder pitch) frame
TORSO_Z = 0.3  # base_link origin (floor) to torso frame
SHOULDER_Z = 1.0  # torso frame to shoulder axis (world z = 1.3)

# (name suffix, axis, xyz from parent (left arm), limits (left arm), effort, velocity)
# Axis conventions at q = 0 (arm hanging straight down):
#   J1 shoulder pitch (y), J2 shoulder roll (x), J3 upper-arm yaw (z),
#   J4 elbow pitch (y), J5 forearm/wrist yaw (z), J6 wrist pitch (y),
#   J7 wrist roll (x).
G1_ARM = [
    ("joint1", (0, 1, 0), (0, SHOULDER_Y, SHOULDER_Z), (-3.1, 1.2), 60, 3.0),
    ("joint2", (1, 0, 0), (0, 0.075, 0), (-0.35, 2.6), 60, 3.0),
    ("joint3", (0, 0, 1), (0, 0, -0.08), (-2.9, 2.9), 30, 3.0),
    ("joint4", (0, 1, 0), (0, 0, -0.22), (-2.6, 0.0), 30, 3.0),
    ("joint5", (0, 0, 1), (0, 0, -0.1), (-2.9, 2.9), 10, 4.0),
    ("joint6", (0, 1, 0), (0, 0, -0.2), (-1.6, 1.6), 10, 4.0),
    ("joint7", (1, 0, 0), (0, 0, -0.055), (-1.6, 1.6), 10, 4.0),
]
# Joints whose angle flips sign under the left/right (y -> -y) mirror.
G1_MIRRORED_AXES = {(1, 0, 0), (0, 0, 1)}


def g1_arm_shapes(side_sign):
    s = side_sign
    return {
        # Shoulder pitch housing: cylinder along y from the torso side outward.
        "link1": ([cyl_between(0.055, (0, 0, 0), (0, s * 0.075, 0))], 1.2),
        # Shoulder roll housing: ball at the roll axis plus a short cap.
        "link2": ([sph(0.055, (0, 0, 0)), cyl_between(0.05, (0, 0, 0), (0, 0, -0.08))], 1.0),
        # Upper arm down to the elbow.
        "link3": ([cyl_between(0.048, (0, 0, 0), (0, 0, -0.19))], 1.4),
        # Elbow housing along the elbow axis plus the start of the forearm.
        "link4": ([cyl(0.05, 0.1, (0, 0, 0), ALONG_Y), cyl_between(0.045, (0, 0, 0), (0, 0, -0.1))], 0.9),
        # Forearm down to the wrist.
        "link5": ([cyl_between(0.042, (0, 0, 0), (0, 0, -0.17))], 0.8),
        # Wrist pitch housing.
        "link6": ([cyl(0.04, 0.085, (0, 0, 0), ALONG_Y), cyl_between(0.036, (0, 0, 0), (0, 0, -0.055))], 0.4),
        # Wrist roll housing and flange.
        "link7": ([cyl(0.036, 0.075, (0, 0, 0), ALONG_X), cyl_between(0.038, (0, 0, 0), (0, 0, -0.05))], 0.3),
    }


G1_GRIPPER_BASE_Z = 0.05  # link7 frame to gripper base (along the arm)
G1_FINGER_Z = 0.075  # gripper base to the finger joints, along the approach axis
G1_FINGER_LEN = 0.055
G1_TCP_Z = G1_FINGER_Z + 0.045  # fingertip centre (between the pads near the tips)


def dual_arm() -> str:
    u = Urdf(
        "dual_arm",
        "An invented dual-arm mobile manipulator (the synthetic world's second robot; NOT the "
        "AgiBot G1), primitive geometry. Generated by "
        "scripts/gen_robot_urdfs.py. base_link origin on the floor, x forward, z up; "
        "arms hang straight down at q = 0; shoulders at z = 1.3 m.",
    )
    u.material("g1_white", (0.93, 0.93, 0.95, 1))
    u.material("g1_grey", (0.55, 0.57, 0.6, 1))
    u.material("g1_dark", (0.15, 0.15, 0.17, 1))
    u.material("g1_black", (0.05, 0.05, 0.05, 1))

    # Wheeled base: chassis box plus four wheels (visual parts of base_link).
    wheels = [cyl(0.06, 0.05, (x, y, 0.06), ALONG_Y) for x in (-0.2, 0.17) for y in (-0.2, 0.2)]
    u.link(
        "base_link",
        [box((0.56, 0.46, 0.24), (-0.02, 0, 0.19))] + wheels + [box((0.3, 0.3, 0.02), (-0.02, 0, 0.32))],
        40.0,
        "g1_dark",
    )
    # Torso: column from the base top up to a chest block carrying the shoulders.
    u.link(
        "torso",
        [
            box((0.16, 0.22, 0.66), (0, 0, 0.33 + 0.02)),
            box((0.2, 0.33, 0.36), (0, 0, 0.87)),
        ],
        15.0,
        "g1_white",
    )
    u.joint("torso_joint", "fixed", "base_link", "torso", (0, 0, TORSO_Z))
    u.link(
        "head",
        [cyl_between(0.04, (0, 0, 0), (0, 0, 0.06)), box((0.17, 0.2, 0.18), (0.01, 0, 0.15))],
        2.0,
        "g1_white",
    )
    u.joint("head_joint", "fixed", "torso", "head", (0, 0, 1.05))
    # Head camera housing (a dark visor) as a separate fixed link.
    u.link("head_camera", [box((0.02, 0.14, 0.05), (0, 0, 0))], 0.1, "g1_black")
    u.joint("head_camera_joint", "fixed", "head", "head_camera", (0.1, 0, 0.16))

    for side, s in (("left", 1.0), ("right", -1.0)):
        shapes = g1_arm_shapes(s)
        parent = "torso"
        for i, (jn, axis, xyz, (lo, hi), effort, vel) in enumerate(G1_ARM):
            child = f"{side}_arm_link{i + 1}"
            link_shapes, mass = shapes[f"link{i + 1}"]
            u.link(child, link_shapes, mass, "g1_white" if i % 2 == 0 else "g1_grey")
            mxyz = (xyz[0], s * xyz[1], xyz[2])
            if s < 0 and tuple(axis) in G1_MIRRORED_AXES:
                lo, hi = -hi, -lo
            u.joint(f"{side}_arm_{jn}", "revolute", parent, child, mxyz, axis=axis, limit=(lo, hi, effort, vel))
            parent = child
        # Gripper: base frame z = approach direction (down at q = 0), fingers
        # slide along gripper y.
        gb = f"{side}_gripper_base"
        u.link(
            gb,
            [cyl_between(0.035, (0, 0, 0), (0, 0, 0.015)), box((0.05, 0.13, 0.06), (0, 0, 0.045))],
            0.5,
            "g1_dark",
        )
        u.joint(f"{side}_gripper_base_joint", "fixed", parent, gb, (0, 0, -G1_GRIPPER_BASE_Z), (PI, 0, 0))
        f1, f2 = f"{side}_gripper_finger1", f"{side}_gripper_finger2"
        u.link(f1, [box((0.022, 0.012, G1_FINGER_LEN), (0, 0.006, G1_FINGER_LEN / 2))], 0.03, "g1_black")
        u.link(f2, [box((0.022, 0.012, G1_FINGER_LEN), (0, -0.006, G1_FINGER_LEN / 2))], 0.03, "g1_black")
        u.joint(
            f"{side}_gripper_joint",
            "prismatic",
            gb,
            f1,
            (0, 0, G1_FINGER_Z),
            axis=(0, 1, 0),
            limit=(0.0, 0.04, 50, 0.2),
        )
        u.joint(
            f"{side}_gripper_joint_mimic",
            "prismatic",
            gb,
            f2,
            (0, 0, G1_FINGER_Z),
            axis=(0, -1, 0),
            limit=(0.0, 0.04, 50, 0.2),
            mimic=f"{side}_gripper_joint",
        )
        tcp = f"{side}_gripper_tcp"
        u.link(tcp, mass=0.001)
        u.joint(f"{side}_gripper_tcp_joint", "fixed", gb, tcp, (0, 0, G1_TCP_Z))
    return u.text()


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--check", action="store_true", help="only check that the committed files are up to date")
    ap.add_argument("--out-dir", type=Path, default=OUT_DIR)
    args = ap.parse_args()
    outputs = {"franka/franka.urdf": panda(), "dual_arm/dual_arm.urdf": dual_arm()}
    stale = []
    for name, text in outputs.items():
        path = args.out_dir / name
        if args.check:
            if not path.exists() or path.read_text() != text:
                stale.append(str(path))
        else:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
            print(f"wrote {path}")
    if stale:
        print("out of date: " + ", ".join(stale), file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
