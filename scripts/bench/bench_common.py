"""Shared helpers for the pybullet bench/reference scripts.

- URDF path resolution (`pybullet:<relative path>` -> pybullet_data path)
- URDF joint metadata (limits, mimic) parsed with ElementTree, because
  pybullet ignores `<mimic>` and orders joints by its own tree traversal
- OpenCV camera JSON -> pybullet (OpenGL) view / projection matrices
- a dependency-free PNG writer (zlib + struct) for debug images
"""

from __future__ import annotations

import json
import os
import struct
import xml.etree.ElementTree as ET
import zlib

import numpy as np

PYBULLET_PREFIX = "pybullet:"


def real_stdout():
    """Point fd 1 at stderr and return a text file on the original stdout.

    pybullet's native code prints banners and warnings with printf to fd 1;
    after this call they land on stderr and only what is written to the
    returned file reaches stdout (so stdout stays machine-readable).
    """
    import sys

    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    return os.fdopen(saved, "w")


def resolve_urdf(spec: str) -> str:
    """Resolve `pybullet:franka_panda/panda.urdf` into pybullet_data; plain paths pass through."""
    if spec.startswith(PYBULLET_PREFIX):
        import pybullet_data

        path = os.path.join(pybullet_data.getDataPath(), spec[len(PYBULLET_PREFIX):])
    else:
        path = spec
    path = os.path.abspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"URDF not found: {path}")
    return path


class UrdfJoint:
    def __init__(self, el):
        self.name = el.get("name")
        self.type = el.get("type")
        lim = el.find("limit")
        self.lower = float(lim.get("lower", 0)) if lim is not None else 0.0
        self.upper = float(lim.get("upper", 0)) if lim is not None else 0.0
        if self.type == "continuous":
            self.lower, self.upper = -np.pi, np.pi
        m = el.find("mimic")
        self.mimic = None
        if m is not None:
            self.mimic = (m.get("joint"), float(m.get("multiplier", 1)), float(m.get("offset", 0)))

    @property
    def movable(self) -> bool:
        return self.type not in ("fixed", "floating", "planar")


def urdf_joints(path: str) -> list[UrdfJoint]:
    """Joints in URDF document order."""
    root = ET.parse(path).getroot()
    return [UrdfJoint(el) for el in root.findall("joint")]


def urdf_active_joints(path: str) -> list[UrdfJoint]:
    """Movable joints in document order, mimic joints excluded (the action/joint order)."""
    return [j for j in urdf_joints(path) if j.movable and j.mimic is None]


def pybullet_index_maps(p, body, client):
    """name -> joint index and link name -> link index (base link = -1)."""
    joints, links = {}, {}
    base_name = p.getBodyInfo(body, physicsClientId=client)[0].decode()
    links[base_name] = -1
    for i in range(p.getNumJoints(body, physicsClientId=client)):
        info = p.getJointInfo(body, i, physicsClientId=client)
        joints[info[1].decode()] = i
        links[info[12].decode()] = i
    return joints, links


def set_joints(p, body, client, joint_index, names, q, mimics=()):
    """resetJointState for each named joint, then drive mimic joints from their masters."""
    vals = {}
    for n, v in zip(names, q):
        p.resetJointState(body, joint_index[n], float(v), physicsClientId=client)
        vals[n] = float(v)
    for j in mimics:
        master, mult, off = j.mimic
        if master in vals and j.name in joint_index:
            p.resetJointState(body, joint_index[j.name], mult * vals[master] + off, physicsClientId=client)


# ---------------------------------------------------------------------------
# Cameras
# ---------------------------------------------------------------------------

# OpenCV camera axes (x right, y down, z forward) -> OpenGL (x right, y up, z backward)
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def load_camera(path: str) -> dict:
    with open(path) as f:
        cam = json.load(f)
    for k in ("fx", "fy", "cx", "cy", "width", "height", "world_from_camera"):
        if k not in cam:
            raise KeyError(f"camera JSON {path} lacks '{k}'")
    cam["world_from_camera"] = np.asarray(cam["world_from_camera"], dtype=np.float64).reshape(4, 4)
    cam["width"], cam["height"] = int(cam["width"]), int(cam["height"])
    return cam


def gl_view_matrix(world_from_camera_cv: np.ndarray) -> np.ndarray:
    """4x4 OpenGL view matrix (gl_camera_from_world) from an OpenCV world_from_camera."""
    world_from_gl = world_from_camera_cv @ CV_TO_GL
    return np.linalg.inv(world_from_gl)


def gl_projection_matrix(fx, fy, cx, cy, width, height, near=0.01, far=10.0) -> np.ndarray:
    """4x4 OpenGL projection from pinhole intrinsics.

    OpenCV convention: the centre of pixel (u, v) is at coordinates (u, v),
    so the image spans [-0.5, W-0.5] x [-0.5, H-0.5]; row 0 is the top row.
    NDC x = -1 is the left edge of column 0, NDC y = +1 the top edge of row 0.
    """
    P = np.zeros((4, 4))
    P[0, 0] = 2.0 * fx / width
    P[0, 2] = 1.0 - 2.0 * (cx + 0.5) / width
    P[1, 1] = 2.0 * fy / height
    P[1, 2] = 2.0 * (cy + 0.5) / height - 1.0
    P[2, 2] = -(far + near) / (far - near)
    P[2, 3] = -2.0 * far * near / (far - near)
    P[3, 2] = -1.0
    return P


def to_pybullet(m: np.ndarray) -> list[float]:
    """pybullet takes 16 floats in OpenGL column-major order."""
    return [float(x) for x in np.asarray(m).T.reshape(-1)]


# pybullet's TinyRenderer rasterises bottom-up and samples each pixel at its
# lower-left corner instead of its centre. Measured with small spheres against
# the exact OpenCV projection (scripts/check_robots.py, [camera]): the plain
# projection puts objects +0.5 px right and -0.5 px up. Shifting the principal
# point by (-0.5, +0.5) px makes the sample points coincide with OpenCV pixel
# centres, so masks match a centre-sampling rasteriser.
TINYRENDERER_PIXEL_SHIFT = (-0.5, 0.5)


def camera_matrices(cam: dict, near=0.01, far=10.0, tinyrenderer=True):
    """pybullet view and projection matrices (flat column-major lists) for an OpenCV camera."""
    view = gl_view_matrix(cam["world_from_camera"])
    sx, sy = TINYRENDERER_PIXEL_SHIFT if tinyrenderer else (0.0, 0.0)
    proj = gl_projection_matrix(
        cam["fx"], cam["fy"], cam["cx"] + sx, cam["cy"] + sy, cam["width"], cam["height"], near, far
    )
    return to_pybullet(view), to_pybullet(proj)


def project_points(cam: dict, pts_world: np.ndarray) -> np.ndarray:
    """Pinhole projection (OpenCV) of world points -> pixel (u, v); [N, 2]."""
    cam_from_world = np.linalg.inv(cam["world_from_camera"])
    pts = np.asarray(pts_world, dtype=np.float64).reshape(-1, 3)
    pc = pts @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    u = cam["fx"] * pc[:, 0] / pc[:, 2] + cam["cx"]
    v = cam["fy"] * pc[:, 1] / pc[:, 2] + cam["cy"]
    return np.stack([u, v], axis=1)


def look_at_camera(eye, target, width, height, fx, fy=None, cx=None, cy=None, up=(0, 0, 1)) -> dict:
    """OpenCV camera at `eye` looking at `target` (image y down ~ -up)."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return {
        "fx": float(fx),
        "fy": float(fy if fy is not None else fx),
        "cx": float(cx if cx is not None else (width - 1) / 2.0),
        "cy": float(cy if cy is not None else (height - 1) / 2.0),
        "width": int(width),
        "height": int(height),
        "world_from_camera": T,
    }


def camera_to_json(cam: dict) -> dict:
    out = dict(cam)
    out["world_from_camera"] = [[float(v) for v in row] for row in np.asarray(cam["world_from_camera"])]
    return out


# ---------------------------------------------------------------------------
# PNG
# ---------------------------------------------------------------------------


def write_png(path: str, img: np.ndarray) -> None:
    """Write an 8-bit grey [H,W] or RGB [H,W,3] / RGBA [H,W,4] image."""
    img = np.ascontiguousarray(img, dtype=np.uint8)
    if img.ndim == 2:
        color_type, channels = 0, 1
    else:
        channels = img.shape[2]
        color_type = {3: 2, 4: 6}[channels]
    h, w = img.shape[:2]
    raw = b"".join(b"\x00" + img[r].tobytes() for r in range(h))

    def chunk(tag, data):
        c = tag + data
        return struct.pack(">I", len(data)) + c + struct.pack(">I", zlib.crc32(c) & 0xFFFFFFFF)

    png = b"\x89PNG\r\n\x1a\n"
    png += chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, color_type, 0, 0, 0))
    png += chunk(b"IDAT", zlib.compress(raw, 6))
    png += chunk(b"IEND", b"")
    with open(path, "wb") as f:
        f.write(png)


def palette(n: int) -> np.ndarray:
    """Distinct-ish colours for label images; index 0 = black background."""
    rng = np.random.default_rng(7)
    cols = rng.integers(60, 255, size=(max(n, 1), 3)).astype(np.uint8)
    cols[0] = 0
    return cols
