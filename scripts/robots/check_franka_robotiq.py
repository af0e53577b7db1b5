#!/usr/bin/env python3
"""Checks for crates/embodiment/robots/franka_robotiq/ (numpy only; PyAV optional for the wrist overlay).

1. FK (a small URDF FK in numpy, mimic joints resolved) of every recorded DROID joint vector to
   `panda_link8` against the recorded flange pose (xyz + extrinsic-XYZ rpy), over all episodes in
   ../shared/realdata/droid (both the 5 Hz `joints`/`states` pairs and, where present, the 15 Hz
   `observation.state.joint_position`/`cartesian_position`). Prints max position error (mm), max angle
   error (deg) and frame counts; exits 1 if over 1 mm / 0.1 deg.
2. Gripper geometry: pad gap and TCP vs finger_joint, mesh bounds, triangle counts and sizes.
3. Renders (point splats of area-sampled mesh surfaces) into --out (default /tmp/droid_check):
   gripper_side.png (g=0 / g=1, two side views in the flange frame), robot_*.png (whole robot at a few
   recorded configurations, two views each), and with PyAV installed wrist_overlay_*.png (gripper
   projected through the wrist-camera link, approximate ZED Mini intrinsics, over the real wrist frame).

Usage: python scripts/robots/check_franka_robotiq.py [--data ../shared/realdata/droid] [--out /tmp/droid_check]
"""

import argparse
import glob
import json
import math
import os
import struct
import sys
import xml.etree.ElementTree as ET
import zlib

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
ROBOT_DIR = os.path.join(REPO, "crates/embodiment/robots/franka_robotiq")
URDF = os.path.join(ROBOT_DIR, "franka_robotiq.urdf")


# ---------------------------------------------------------------- URDF + FK
def rpy_to_R(r, p, y):
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def axis_angle(axis, a):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K


def vec(s, n=3, default=0.0):
    return [float(x) for x in s.split()] if s else [default] * n


class Robot:
    def __init__(self, path):
        root = ET.parse(path).getroot()
        self.dir = os.path.dirname(path)
        self.links = {}
        for l in root.findall("link"):
            vis = []
            for v in l.findall("visual"):
                o = v.find("origin")
                T = np.eye(4)
                if o is not None:
                    T[:3, :3] = rpy_to_R(*vec(o.get("rpy")))
                    T[:3, 3] = vec(o.get("xyz"))
                m = v.find("geometry/mesh")
                if m is not None:
                    vis.append((T, m.get("filename")))
            self.links[l.get("name")] = vis
        self.joints = []
        for j in root.findall("joint"):
            o = j.find("origin")
            T = np.eye(4)
            if o is not None:
                T[:3, :3] = rpy_to_R(*vec(o.get("rpy")))
                T[:3, 3] = vec(o.get("xyz"))
            ax = j.find("axis")
            lim = j.find("limit")
            mim = j.find("mimic")
            self.joints.append(
                dict(
                    name=j.get("name"),
                    type=j.get("type"),
                    parent=j.find("parent").get("link"),
                    child=j.find("child").get("link"),
                    T=T,
                    axis=vec(ax.get("xyz")) if ax is not None else [1.0, 0, 0],
                    lower=float(lim.get("lower", 0)) if lim is not None else 0.0,
                    upper=float(lim.get("upper", 0)) if lim is not None else 0.0,
                    mimic=(mim.get("joint"), float(mim.get("multiplier", 1)), float(mim.get("offset", 0)))
                    if mim is not None
                    else None,
                )
            )
        self.by_name = {j["name"]: j for j in self.joints}
        self.movable = [j["name"] for j in self.joints if j["type"] != "fixed" and j["mimic"] is None]
        children = {j["child"] for j in self.joints}
        roots = [l for l in self.links if l not in children]
        assert len(roots) == 1, roots
        self.root = roots[0]

    def joint_value(self, name, q):
        j = self.by_name[name]
        if j["mimic"] is None:
            return q[name]
        m, k, off = j["mimic"]
        return k * self.joint_value(m, q) + off

    def fk(self, qvec):
        q = dict(zip(self.movable, qvec))
        T = {self.root: np.eye(4)}
        pending = list(self.joints)
        while pending:
            rest = []
            for j in pending:
                if j["parent"] not in T:
                    rest.append(j)
                    continue
                M = T[j["parent"]] @ j["T"]
                if j["type"] in ("revolute", "continuous"):
                    R = np.eye(4)
                    R[:3, :3] = axis_angle(j["axis"], self.joint_value(j["name"], q))
                    M = M @ R
                elif j["type"] == "prismatic":
                    P = np.eye(4)
                    P[:3, 3] = np.asarray(j["axis"]) * self.joint_value(j["name"], q)
                    M = M @ P
                T[j["child"]] = M
            assert len(rest) < len(pending), "disconnected joints"
            pending = rest
        return T


# ---------------------------------------------------------------- meshes
def read_stl(path):
    with open(path, "rb") as f:
        data = f.read()
    n = struct.unpack("<I", data[80:84])[0]
    if 84 + 50 * n == len(data):
        rec = np.frombuffer(data, dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")], offset=84, count=n)
        return rec["v"].astype(np.float64)
    raise ValueError(f"{path}: not a binary STL")


def sample_surface(tris, n, rng):
    a = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
    idx = rng.choice(len(tris), size=n, p=a / a.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = tris[idx]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])


# ---------------------------------------------------------------- PNG
def write_png(path, img):
    img = np.ascontiguousarray(img.astype(np.uint8))
    h, w, _ = img.shape
    raw = b"".join(b"\x00" + img[y].tobytes() for y in range(h))

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    with open(path, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n")
        f.write(chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)))
        f.write(chunk(b"IDAT", zlib.compress(raw, 6)))
        f.write(chunk(b"IEND", b""))


def splat(points, colors, view_R, center, scale, size=(480, 480), bg=255, on_top=None):
    """Orthographic splat: view_R rows = (image right, image down, towards the viewer).
    on_top: optional (points, colors) drawn last, regardless of depth (markers)."""
    H, W = size
    img = np.full((H, W, 3), bg, np.uint8)
    p = (points - center) @ view_R.T
    u = np.round(W / 2 + p[:, 0] * scale).astype(int)
    v = np.round(H / 2 + p[:, 1] * scale).astype(int)
    d = p[:, 2]
    ok = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    u, v, d, c = u[ok], v[ok], d[ok], colors[ok]
    order = np.argsort(d)  # far first, near last wins
    img[v[order], u[order]] = c[order]
    if on_top is not None:
        q = (on_top[0] - center) @ view_R.T
        u = np.round(W / 2 + q[:, 0] * scale).astype(int)
        v = np.round(H / 2 + q[:, 1] * scale).astype(int)
        ok = (u >= 0) & (u < W) & (v >= 0) & (v < H)
        img[v[ok], u[ok]] = on_top[1][ok]
    return img


def label(img, text_rows):
    return img  # no font rendering in numpy-only mode; figures are printed instead


# ---------------------------------------------------------------- data
def load_episodes(data_dir):
    eps = []
    for f in sorted(glob.glob(os.path.join(data_dir, "**", "annotation", "**", "*.json"), recursive=True)):
        d = json.load(open(f))
        pairs = []
        if "joints" in d and "states" in d:
            j = np.asarray(d["joints"], float)
            s = np.asarray(d["states"], float)
            n = min(len(j), len(s))
            pairs.append(("5Hz joints/states", j[:n, :7], s[:n, :6], j[:n, 7] if j.shape[1] > 7 else s[:n, 6]))
        if "observation.state.joint_position" in d:
            j = np.asarray(d["observation.state.joint_position"], float)
            s = np.asarray(d["observation.state.cartesian_position"], float)
            g = np.asarray(d.get("observation.state.gripper_position", np.zeros(len(j))), float).reshape(-1)
            pairs.append(("15Hz observation.state", j[:, :7], s[:, :6], g))
        eps.append((os.path.relpath(f, data_dir), pairs))
    return eps


def rot_angle_deg(Ra, Rb):
    c = (np.trace(Ra.T @ Rb) - 1) / 2
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=os.path.join(os.path.dirname(REPO), "shared/realdata/droid"))
    ap.add_argument("--out", default="/tmp/droid_check")
    ap.add_argument("--no-render", action="store_true")
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    rob = Robot(URDF)
    ok = True

    print("movable joints (joint-vector order):", rob.movable)
    fj = rob.by_name["finger_joint"]
    print(f"finger_joint limits [{fj['lower']}, {fj['upper']}] (0 = open, upper = closed)")
    print("mimics:", {j["name"]: j["mimic"] for j in rob.joints if j["mimic"]})

    # ---- frames
    q0 = np.array([0, -math.pi / 5, 0, -4 * math.pi / 5, 0, 3 * math.pi / 5, 0, 0.0])
    T = rob.fk(q0)
    F = T["panda_link8"]
    inv = np.linalg.inv(F)
    for name in ("robotiq_arg2f_base_link", "robotiq_tcp", "droid_wrist_camera_left_optical"):
        M = inv @ T[name]
        print(f"flange -> {name}: xyz {np.round(M[:3, 3], 5).tolist()}  R rows {np.round(M[:3, :3], 4).tolist()}")

    # ---- gripper geometry vs finger_joint
    print("finger_joint q | pad-face gap (mm) | pad-centre z from flange (mm) | g if linear in width")
    gaps = []
    for qf in np.linspace(0, fj["upper"], 9):
        T = rob.fk(np.r_[q0[:7], qf])
        Fi = np.linalg.inv(T["panda_link8"])
        pl = (Fi @ T["left_inner_finger_pad"])[:3, 3]
        pr = (Fi @ T["right_inner_finger_pad"])[:3, 3]
        gap = np.linalg.norm(pl - pr) * 1000 - 6.35
        gaps.append(gap)
        print(f"  {qf:.3f} | {gap:6.1f} | {pl[2] * 1000:6.1f} | {1 - gap / gaps[0]:.3f}")

    # ---- meshes
    tot_t = tot_b = tot_r = 0
    for f in sorted(glob.glob(os.path.join(ROBOT_DIR, "meshes", "*.stl"))):
        t = read_stl(f)
        uses = sum(1 for vis in rob.links.values() for _, fn in vis if fn == "meshes/" + os.path.basename(f))
        tot_t += len(t)
        tot_r += len(t) * uses
        tot_b += os.path.getsize(f)
        lo, hi = t.reshape(-1, 3).min(0), t.reshape(-1, 3).max(0)
        print(f"  {os.path.basename(f):28s} {len(t):5d} tris x{uses} {os.path.getsize(f):7d} B "
              f"{np.round(lo, 3).tolist()}..{np.round(hi, 3).tolist()}")
    print(f"meshes: {tot_t} triangles in files ({tot_r} rendered), {tot_b} bytes")

    # ---- 1. FK vs recorded flange poses
    eps = load_episodes(args.data)
    print(f"episodes: {len(eps)} under {args.data}")
    stats = {}
    worst = (0, 0, "")
    configs = []
    for name, pairs in eps:
        for kind, J, S, G in pairs:
            st = stats.setdefault(kind, [0, 0.0, 0.0, 0])
            st[3] += 1
            for k in range(len(J)):
                T = rob.fk(np.r_[J[k], 0.0])["panda_link8"]
                dp = np.linalg.norm(T[:3, 3] - S[k, :3]) * 1000
                R = rpy_to_R(*S[k, 3:6])  # extrinsic XYZ = Rz(yaw) Ry(pitch) Rx(roll)
                da = rot_angle_deg(T[:3, :3], R)
                st[0] += 1
                st[1] = max(st[1], dp)
                st[2] = max(st[2], da)
                if dp > worst[0]:
                    worst = (dp, da, f"{name} {kind} frame {k}")
            if kind.startswith("5Hz") and len(configs) < 64:
                configs.append((name, J, G))
    total = 0
    for kind, (n, dp, da, ne) in stats.items():
        total += n
        print(f"FK {kind}: {ne} episodes, {n} frames, max |dp| = {dp:.3e} mm, max angle = {da:.3e} deg")
        ok &= dp < 1.0 and da < 0.1
    print(f"FK total frames {total}; worst position at {worst[2]}")
    if not eps:
        print("no data found: FK check skipped")

    if args.no_render:
        return 0 if ok else 1

    # ---- 3. renders
    rng = np.random.default_rng(0)
    pts = {}
    for link_name, vis in rob.links.items():
        for Tv, fn in vis:
            t = read_stl(os.path.join(ROBOT_DIR, fn))
            n = 30000 if "link" in fn and "robotiq" not in fn else 12000
            p = sample_surface(t, n, rng)
            pts.setdefault(link_name, []).append(p @ Tv[:3, :3].T + Tv[:3, 3])
    pts = {k: np.concatenate(v) for k, v in pts.items()}
    palette = {}
    for i, k in enumerate(sorted(pts)):
        if k.startswith("panda"):
            palette[k] = np.array([90 + 20 * (i % 8), 110, 200 - 15 * (i % 8)])
        elif "finger" in k and "left" in k:
            palette[k] = np.array([220, 60, 40])
        elif "finger" in k and "right" in k:
            palette[k] = np.array([40, 170, 60])
        elif "knuckle" in k:
            palette[k] = np.array([230, 150, 30])
        else:
            palette[k] = np.array([40, 40, 40])

    def world_points(qv, frame=None, only=None):
        T = rob.fk(qv)
        base = np.linalg.inv(T[frame]) if frame else np.eye(4)
        P, C = [], []
        for k, p in pts.items():
            if only is not None and not only(k):
                continue
            M = base @ T[k]
            P.append(p @ M[:3, :3].T + M[:3, 3])
            C.append(np.tile(palette[k], (len(p), 1)))
        return np.concatenate(P), np.concatenate(C).astype(np.uint8)

    # gripper side views in the flange frame (flange z pointing down the image)
    views = {
        # looking along flange -x (from +x): image right = +y, image down = +z
        "from_plus_x": np.array([[0, 1, 0], [0, 0, 1], [1, 0, 0]], float),
        # looking along flange +y (from -y): image right = +x, image down = +z
        "from_minus_y": np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], float),
    }
    tiles = []
    for g in (0.0, 1.0):
        qv = np.r_[q0[:7], fj["lower"] + g * (fj["upper"] - fj["lower"])]
        P, C = world_points(qv, "panda_link8", only=lambda k: not k.startswith("panda") or k == "panda_link7")
        keep = P[:, 2] > -0.03
        P, C = P[keep], C[keep]
        # markers: flange origin (blue), robotiq_tcp (magenta), 1 cm grid ticks along the flange z axis (cyan)
        T = rob.fk(qv)
        tcp = (np.linalg.inv(T["panda_link8"]) @ T["robotiq_tcp"])[:3, 3]
        mk = [np.zeros(3), tcp] + [np.array([0.0, 0.0, z]) for z in np.arange(0.0, 0.18, 0.01)]
        mc = [(0, 0, 255), (255, 0, 255)] + [(0, 200, 200)] * 18
        MP, MC = [], []
        for m, c in zip(mk, mc):
            MP.append(m + rng.normal(scale=0.0015 if c != (0, 200, 200) else 0.0005, size=(300, 3)))
            MC.append(np.tile(np.array(c, np.uint8), (300, 1)))
        top = (np.concatenate(MP), np.concatenate(MC))
        row = [splat(P, C, R, np.array([0, 0, 0.085]), 1800, (400, 400), on_top=top) for R in views.values()]
        tiles.append(np.concatenate(row, 1))
    img = np.concatenate(tiles, 0)
    # flange plane (z=0) and TCP marks
    write_png(os.path.join(args.out, "gripper_side.png"), img)
    print("wrote gripper_side.png: rows g=0 (open), g=1 (closed); cols view from flange +x, view from flange -y;"
          " flange z points down; 1800 px/m; blue = flange origin, magenta = robotiq_tcp, cyan = 1 cm ticks on the flange z axis")

    # whole robot for a few recorded configurations
    pick = [configs[i] for i in np.linspace(0, len(configs) - 1, 4).astype(int)] if configs else []
    for ci, (name, J, G) in enumerate(pick):
        k = len(J) // 2
        qv = np.r_[J[k], fj["lower"] + float(G[k]) * (fj["upper"] - fj["lower"])]
        P, C = world_points(qv)
        side = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float)  # from -y: right = +x, down = -z
        front = np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]], float)  # from +x looking back
        tiles = [splat(P, C, R, np.array([0.3, 0, 0.5]), 520, (560, 560)) for R in (side, front)]
        fn = f"robot_{ci}.png"
        write_png(os.path.join(args.out, fn), np.concatenate(tiles, 1))
        print(f"wrote {fn}: {name} frame {k} q={np.round(qv, 3).tolist()} (left: from -y, right: from +x)")

    # wrist overlay (PyAV optional)
    try:
        import av  # noqa: F401
    except ImportError:
        print("PyAV not installed: wrist overlay skipped")
        return 0 if ok else 1
    import av

    # ZED Mini HD720 left eye, approximate: fx ~ 530 px at 1280x720 -> /4 at 320x180, then y * 192/180
    fx = 640 / 4.0  # ZED Mini spec: 90 deg horizontal FOV at 1280x720 -> fx 640 px; /4 for 320 px
    fy = fx * 192 / 180
    cx, cy = 160, 90 * 192 / 180
    for e in ("droid_new_setup/annotation/val/0007.json", "droid_subset/annotation/val/1799.json"):
        path = os.path.join(args.data, e)
        if not os.path.exists(path):
            continue
        d = json.load(open(path))
        S = np.asarray(d["states"], float)
        vid = os.path.join(args.data, e.replace("annotation", "videos")[:-5], "2.mp4")
        frames = [f.to_ndarray(format="rgb24") for f in av.open(vid).decode(video=0)]
        g = S[:, 6]
        out = []
        for k in (0, int(np.argmax(g))):
            qv = np.r_[0, -0.5, 0, -2.3, 0, 1.8, 0, fj["lower"] + g[k] * (fj["upper"] - fj["lower"])]
            P, C = world_points(qv, "droid_wrist_camera_left_optical")
            m = P[:, 2] > 0.02
            P, C = P[m], C[m]
            u = np.round(fx * P[:, 0] / P[:, 2] + cx).astype(int)
            v = np.round(fy * P[:, 1] / P[:, 2] + cy).astype(int)
            ok2 = (u >= 0) & (u < 320) & (v >= 0) & (v < 192)
            im = frames[k].copy()
            ov = im.copy()
            ov[v[ok2], u[ok2]] = C[ok2]
            out.append(np.concatenate([im, (0.5 * im + 0.5 * ov).astype(np.uint8)], 1))
        fn = "wrist_overlay_" + e.split("/")[0] + "_" + os.path.basename(e)[:-5] + ".png"
        write_png(os.path.join(args.out, fn), np.concatenate(out, 0))
        print(f"wrote {fn}: rows first frame (g={g[0]:.2f}) and most-closed frame (g={g.max():.2f}); left real, right"
              " overlay of the model's gripper through droid_wrist_camera_left_optical (fx=160 px, spec value)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
