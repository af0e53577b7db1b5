#!/usr/bin/env python3
"""Check crates/embodiment/robots/agibot_g1/ against real AgiBot World data (numpy only).

Usage:
    python3 scripts/robots/check_agibot_g1.py [--robot crates/embodiment/robots/agibot_g1/agibot_g1.urdf]
        [--realdata ../shared/realdata/agibot-world] [--overlays /tmp/g1_check]

Needs numpy only (Pillow optional: with it, overlay PNGs are written). Checks:

1. FK: ge-sim-v2-demo_000 (AgibotTech/GE-Sim-V2 @ 4a34498, assets/demo_000; AgiBot World data, CC BY-NC-SA 4.0,
   not redistributed): FK of the recorded joints (arms 14, head 2, waist 2: column 18 = pitch rad,
   column 19 = lift m) in the URDF root `agibot_world_base` vs the recorded flange poses `state_eef_poses_0`
   (xyz + extrinsic-xyz rpy) of `arm_l_link7` / `arm_r_link7`, every frame.
2. Camera mounts: inv(FK(parent link)) @ recorded camera-to-world extrinsic, per frame, vs the fixed
   `*_camera_optical` links of the URDF (spread over frames where the arm is still; the hand extrinsics lag
   the joint states by ~1.5 frames, so moving frames are left out of the spread).
3. Projection: mesh vertices / primitive surface points of the arms projected through the recorded
   calibration into cur_{head,left,right}.png -> overlay PNGs.
4. genie-envisioner samples (no joints): hand camera mount from recorded flange pose vs camera pose;
   waist lift/pitch and head angles solved from the recorded head camera pose.
5. Mesh sanity: triangle counts, sizes, watertightness (edge-manifold closed), parent/child mesh contact.
6. Omnipicker pads (informational): the modelled pad inner-edge ends projected into the hand photos of
   ge-sim-v2 frame 0 vs pixel positions measured by eye on the real photos (GRIPPER_PAD_PX); overlay pads_*.png.
"""
import argparse
import math
import os
import struct
import sys
import xml.etree.ElementTree as ET

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))


# ----------------------------------------------------------------------------- small URDF FK (numpy)
def rpy_to_R(r, p, y):
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def R_to_rpy(R):
    """URDF rpy (= extrinsic x-y-z) of a rotation matrix."""
    p = math.asin(max(-1.0, min(1.0, -R[2, 0])))
    if abs(math.cos(p)) > 1e-9:
        r = math.atan2(R[2, 1], R[2, 2]); y = math.atan2(R[1, 0], R[0, 0])
    else:
        r = math.atan2(-R[1, 2], R[1, 1]); y = 0.0
    return r, p, y


def T_from(xyz, rpy):
    T = np.eye(4); T[:3, :3] = rpy_to_R(*rpy); T[:3, 3] = xyz
    return T


def axis_angle(axis, a):
    axis = np.asarray(axis, float); axis = axis / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K


def quat_xyzw_to_R(q):
    x, y, z, w = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def R_to_quat_xyzw(R):
    w = math.sqrt(max(0.0, 1 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1 + R[0, 0] - R[1, 1] - R[2, 2])) / 2, R[2, 1] - R[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1 - R[0, 0] + R[1, 1] - R[2, 2])) / 2, R[0, 2] - R[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1 - R[0, 0] - R[1, 1] + R[2, 2])) / 2, R[1, 0] - R[0, 1])
    q = np.array([x, y, z, w]); q /= np.linalg.norm(q)
    return q if q[3] >= 0 else -q


def mean_rotation(Rs):
    """Chordal L2 mean of rotation matrices."""
    U, _, Vt = np.linalg.svd(np.sum(Rs, axis=0))
    D = np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def rot_angle_deg(Ra, Rb):
    c = (np.trace(Ra.T @ Rb) - 1) / 2
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def _vec(s, default):
    return [float(v) for v in s.split()] if s is not None else list(default)


class Urdf:
    def __init__(self, path):
        self.path = path
        self.root = ET.parse(path).getroot()
        self.joints = []
        for j in self.root.findall('joint'):
            o = j.find('origin'); ax = j.find('axis'); lim = j.find('limit'); mim = j.find('mimic')
            self.joints.append(dict(
                name=j.get('name'), type=j.get('type'), parent=j.find('parent').get('link'),
                child=j.find('child').get('link'),
                T=T_from(_vec(o.get('xyz') if o is not None else None, [0, 0, 0]),
                         _vec(o.get('rpy') if o is not None else None, [0, 0, 0])),
                axis=_vec(ax.get('xyz') if ax is not None else None, [1, 0, 0]),
                lower=float(lim.get('lower', 0)) if lim is not None else None,
                upper=float(lim.get('upper', 0)) if lim is not None else None,
                mimic=(mim.get('joint'), float(mim.get('multiplier', 1)), float(mim.get('offset', 0)))
                if mim is not None else None))
        self.by_child = {j['child']: j for j in self.joints}
        self.by_name = {j['name']: j for j in self.joints}
        self.links = {l.get('name'): l for l in self.root.findall('link')}
        roots = [l for l in self.links if l not in self.by_child]
        assert len(roots) == 1, roots
        self.root_link = roots[0]

    def movable(self):
        return [j['name'] for j in self.joints if j['type'] != 'fixed' and j['mimic'] is None]

    def q_of(self, name, q):
        j = self.by_name[name]
        if j['mimic'] is not None:
            m, k, off = j['mimic']
            return k * self.q_of(m, q) + off
        return q.get(name, 0.0)

    def link_pose(self, link, q, cache=None):
        if cache is None:
            cache = {}
        if link in cache:
            return cache[link]
        if link == self.root_link:
            T = np.eye(4)
        else:
            j = self.by_child[link]
            T = self.link_pose(j['parent'], q, cache) @ j['T']
            v = self.q_of(j['name'], q) if j['type'] != 'fixed' else 0.0
            if j['type'] in ('revolute', 'continuous'):
                M = np.eye(4); M[:3, :3] = axis_angle(j['axis'], v); T = T @ M
            elif j['type'] == 'prismatic':
                a = np.asarray(j['axis'], float)
                M = np.eye(4); M[:3, 3] = a / np.linalg.norm(a) * v; T = T @ M
        cache[link] = T
        return T

    def all_poses(self, q):
        c = {}
        for l in self.links:
            self.link_pose(l, q, c)
        return c

    def visuals(self, link):
        """[(T_link_visual, kind, params)] kind in mesh/box/cylinder/sphere."""
        out = []
        for v in self.links[link].findall('visual'):
            o = v.find('origin')
            T = T_from(_vec(o.get('xyz') if o is not None else None, [0, 0, 0]),
                       _vec(o.get('rpy') if o is not None else None, [0, 0, 0]))
            g = v.find('geometry')[0]
            if g.tag == 'mesh':
                out.append((T, 'mesh', os.path.join(os.path.dirname(self.path), g.get('filename'))))
            elif g.tag == 'box':
                out.append((T, 'box', _vec(g.get('size'), None)))
            elif g.tag == 'cylinder':
                out.append((T, 'cylinder', (float(g.get('radius')), float(g.get('length')))))
            elif g.tag == 'sphere':
                out.append((T, 'sphere', (float(g.get('radius')),)))
        return out


# ----------------------------------------------------------------------------- STL + primitive points
def read_stl(path):
    with open(path, 'rb') as f:
        data = f.read()
    n = struct.unpack('<I', data[80:84])[0]
    assert len(data) == 84 + 50 * n, 'not a binary STL: ' + path
    rec = np.frombuffer(data[84:], dtype=np.dtype([('n', '<f4', 3), ('v', '<f4', (3, 3)), ('a', '<u2')]), count=n)
    return rec['v'].astype(np.float64)  # n x 3 x 3


def closed_and_manifold(tris):
    """Every undirected edge used by exactly two triangles, in opposite directions."""
    V, inv = np.unique(np.round(tris.reshape(-1, 3), 7), axis=0, return_inverse=True)
    F = inv.reshape(-1, 3)
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    und = np.sort(e, axis=1)
    _, cnt = np.unique(und, axis=0, return_counts=True)
    _, dcnt = np.unique(e, axis=0, return_counts=True)
    return bool(np.all(cnt == 2) and np.all(dcnt == 1))


def primitive_points(kind, params, n=3000):
    rng = np.random.default_rng(0)
    if kind == 'box':
        s = np.asarray(params) / 2
        p = rng.uniform(-1, 1, (n, 3)); ax = rng.integers(0, 3, n)
        p[np.arange(n), ax] = np.sign(p[np.arange(n), ax]); return p * s
    if kind == 'cylinder':
        r, L = params; t = rng.uniform(0, 2 * np.pi, n); z = rng.uniform(-L / 2, L / 2, n)
        return np.stack([r * np.cos(t), r * np.sin(t), z], 1)
    if kind == 'sphere':
        p = rng.normal(size=(n, 3)); return p / np.linalg.norm(p, axis=1, keepdims=True) * params[0]


def robot_points(u, q, links=None):
    """[(link, Nx3 points in the root frame)] for the visuals of the robot."""
    P = u.all_poses(q); out = []
    for link in (links or u.links):
        for T, kind, prm in u.visuals(link):
            if kind == 'mesh':
                tri = read_stl(prm); pts = np.concatenate([tri.reshape(-1, 3), tri.mean(1)])
            else:
                pts = primitive_points(kind, prm)
            M = P[link] @ T
            out.append((link, pts @ M[:3, :3].T + M[:3, 3]))
    return out


# ----------------------------------------------------------------------------- data helpers
ARM_L = [f'idx2{k}_arm_l_joint{k}' for k in range(1, 8)]
ARM_R = [f'idx6{k}_arm_r_joint{k}' for k in range(1, 8)]


def q_from_state20(s):
    """ge-sim-v2 state_joints row (20): left arm 7, right arm 7, grippers 2 (raw 0..~120), head 2, waist 2 (pitch, lift)."""
    q = {n: float(s[i]) for i, n in enumerate(ARM_L)}
    q.update({n: float(s[7 + i]) for i, n in enumerate(ARM_R)})
    q['idx11_head_joint1'] = float(s[16]); q['idx12_head_joint2'] = float(s[17])
    q['idx02_body_joint2'] = float(s[18]); q['idx01_body_joint1'] = float(s[19])
    for side, g in (('l', s[14]), ('r', s[15])):
        g = min(max(float(g) / 120.0, 0.0), 1.0)  # ge-sim-v2 stores raw AgiBot units (~0 open .. ~120 closed)
        name = 'idx41_gripper_l_outer_joint1' if side == 'l' else 'idx81_gripper_r_outer_joint1'
        q[name] = GRIP_OPEN * (1.0 - g)
    return q


GRIP_OPEN = 0.7853981633974483  # outer_joint1 upper limit = open; 0 = closed


def project(K, T_cam_world, pts):
    pc = pts @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    ok = pc[:, 2] > 0.02
    uv = (pc[ok] / pc[ok, 2:3]) @ K.T
    return uv[:, :2], pc[ok, 2]


def fmt(v, n=6):
    return ' '.join(f'{x:.{n}f}' for x in v)


# ----------------------------------------------------------------------------- checks
def check_fk(u, D):
    J = np.load(os.path.join(D, 'state_joints_0.npy')).astype(float)
    E = np.load(os.path.join(D, 'state_eef_poses_0.npy')).astype(float)
    print(f'\n== 1. FK vs recorded flange poses (ge-sim-v2-demo_000, {len(J)} frames, root {u.root_link})')
    worst = {}
    for side, link, o in (('left', 'arm_l_link7', 0), ('right', 'arm_r_link7', 7)):
        dp, da = [], []
        for t in range(len(J)):
            P = u.link_pose(link, q_from_state20(J[t]))
            dp.append(np.linalg.norm(P[:3, 3] - E[t, o:o + 3]))
            da.append(rot_angle_deg(P[:3, :3], rpy_to_R(*E[t, o + 3:o + 6])))
        worst[side] = (1000 * max(dp), max(da))
        print(f'  {side:5s} flange {link}: max position error {1000 * max(dp):.4f} mm, '
              f'max rotation error {max(da):.4f} deg')
    ok = all(p < 1.0 and a < 0.1 for p, a in worst.values())
    print('  PASS' if ok else '  FAIL', '(limit 1 mm / 0.1 deg in every frame)')
    return ok


def estimate_mount(Fs, Xs):
    M = np.array([np.linalg.inv(F) @ X for F, X in zip(Fs, Xs)])
    p = M[:, :3, 3].mean(0); R = mean_rotation(M[:, :3, :3])
    sp = 1000 * np.linalg.norm(M[:, :3, 3] - p, axis=1).max()
    sa = max(rot_angle_deg(R, m[:3, :3]) for m in M)
    return p, R, sp, sa


def check_cameras(u, D):
    J = np.load(os.path.join(D, 'state_joints_0.npy')).astype(float)
    X = np.load(os.path.join(D, 'extrinsic_alignstate_0.npy')).astype(float)
    print('\n== 2. Camera mounts (ge-sim-v2-demo_000): inv(FK(parent)) @ recorded camera-to-world')
    ok = True
    for ci, cam, jcols in ((0, 'head_camera_optical', slice(16, 20)), (1, 'hand_left_camera_optical', slice(0, 7)),
                           (2, 'hand_right_camera_optical', slice(7, 14))):
        parent = u.by_child[cam]['parent']
        v = np.r_[0, np.abs(np.diff(J[:, jcols], axis=0)).max(1)]
        still = [t for t in range(len(J)) if v[max(0, t - 4):t + 5].max() < 1e-3]
        Fs = [u.link_pose(parent, q_from_state20(J[t])) for t in still]
        p, R, sp, sa = estimate_mount(Fs, X[ci, still])
        Fall = [u.link_pose(parent, q_from_state20(J[t])) for t in range(len(J))]
        _, _, sp_all, sa_all = estimate_mount(Fall, X[ci])
        Tu = u.by_child[cam]['T']
        dpos = 1000 * np.linalg.norm(Tu[:3, 3] - p); drot = rot_angle_deg(Tu[:3, :3], R)
        print(f'  {cam} on {parent}: estimate xyz [{fmt(p)}] quat_xyzw [{fmt(R_to_quat_xyzw(R))}] rpy [{fmt(R_to_rpy(R))}]')
        print(f'    spread over {len(still)} still frames: {sp:.3f} mm, {sa:.3f} deg; over all {len(J)} frames: '
              f'{sp_all:.2f} mm, {sa_all:.2f} deg; URDF mount differs from estimate by {dpos:.3f} mm, {drot:.3f} deg')
        ok &= dpos < 1.0 and drot < 0.1 and sp < 2.0 and sa < 0.5
    print('  PASS' if ok else '  FAIL')
    return ok


def overlays(u, D, out):
    try:
        from PIL import Image
    except ImportError:
        print('\n== 3. overlays skipped (no Pillow)'); return
    os.makedirs(out, exist_ok=True)
    J = np.load(os.path.join(D, 'state_joints_0.npy')).astype(float)
    X = np.load(os.path.join(D, 'extrinsic_alignstate_0.npy')).astype(float)
    K = np.load(os.path.join(D, 'intrinsic.npy')).astype(float)
    q = q_from_state20(J[0])
    arm_links = [l for l in u.links if l.startswith(('arm_l', 'arm_r', 'gripper_l', 'gripper_r'))]
    pts = robot_points(u, q, arm_links)
    print('\n== 3. Overlays (frame 0; red = left arm+gripper, blue = right, green = URDF-camera frame of the '
          'other links)')
    for ci, (cam, img) in enumerate((('head_camera_optical', 'cur_head.png'), ('hand_left_camera_optical', 'cur_left.png'),
                                     ('hand_right_camera_optical', 'cur_right.png'))):
        im = np.asarray(Image.open(os.path.join(D, img)).convert('RGB')).astype(float)
        H, W = im.shape[:2]
        # camera pose from the URDF (FK + fixed mount), not the recorded extrinsic
        Tcw = np.linalg.inv(u.link_pose(cam, q))
        mask = np.zeros((H, W, 3), bool); hit = 0
        for link, P in pts:
            uv, _ = project(K[ci], Tcw, P)
            c = 0 if '_l_' in link else 2
            ij = np.round(uv).astype(int); m = (ij[:, 0] >= 0) & (ij[:, 0] < W) & (ij[:, 1] >= 0) & (ij[:, 1] < H)
            mask[ij[m, 1], ij[m, 0], c] = True; hit += m.sum()
        o = im.copy()
        for c, col in ((0, (255, 0, 0)), (2, (0, 80, 255))):
            o[mask[..., c]] = 0.45 * o[mask[..., c]] + 0.55 * np.array(col)
        # recorded flange positions as crosses (through the recorded extrinsic)
        for o3 in (0, 7):
            E = np.load(os.path.join(D, 'state_eef_poses_0.npy')).astype(float)[0, o3:o3 + 3]
            uv, _ = project(K[ci], np.linalg.inv(X[ci, 0]), E[None])
            for x, y in np.round(uv).astype(int):
                for d in range(-6, 7):
                    for (a, b) in ((y, x + d), (y + d, x)):
                        if 0 <= a < H and 0 <= b < W:
                            o[a, b] = (0, 255, 0)
        path = os.path.join(out, 'overlay_' + img)
        Image.fromarray(o.clip(0, 255).astype(np.uint8)).save(path)
        print(f'  {path}: {hit} projected points inside the image')


def check_genie_envisioner(u, root):
    print('\n== 4. genie-envisioner samples (no joints)')
    for s in range(3):
        Dn = os.path.join(root, 'genie-envisioner-samples', f'sample_{s}')
        if not os.path.isdir(Dn):
            continue
        a = np.load(os.path.join(Dn, 'actions.npy')).astype(float)
        for cam, o, mount in (('hand_left', 0, 'hand_left_camera_optical'), ('hand_right', 8, 'hand_right_camera_optical')):
            X = np.load(os.path.join(Dn, f'extrinsic_{cam}.npy')).astype(float)
            Fs = []
            for t in range(len(a)):
                F = np.eye(4); F[:3, :3] = quat_xyzw_to_R(a[t, o + 3:o + 7]); F[:3, 3] = a[t, o:o + 3]; Fs.append(F)
            M = np.array([np.linalg.inv(F) @ Xt for F, Xt in zip(Fs, X)])
            med = np.median(M[:, :3, 3], 0)
            Tu = u.by_child[mount]['T']
            print(f'  sample_{s} {cam}: mount from recorded flange + camera poses: xyz [{fmt(med, 4)}] (median); '
                  f'vs URDF mount {1000 * np.linalg.norm(med - Tu[:3, 3]):.1f} mm, '
                  f'{rot_angle_deg(mean_rotation(M[:, :3, :3]), Tu[:3, :3]):.2f} deg')
        Xh = np.load(os.path.join(Dn, 'extrinsic_head.npy')).astype(float)[0]
        x, res = solve_waist_head(u, Xh)
        print(f'  sample_{s} head camera -> lift {x[0]:.4f} m, pitch {x[1]:.4f} rad, head yaw {x[2]:.4f}, head pitch '
              f'{x[3]:.4f} rad; residual {1000 * res[0]:.2f} mm, {res[1]:.3f} deg')
        xd, resd = solve_waist_head(u, Xh, fixed=dict(idx01_body_joint1=0.27, idx02_body_joint2=0.5061,
                                                      idx11_head_joint1=0.0, idx12_head_joint2=0.4363))
        print(f'    with the ge-sim-v2 default waist/head (0.27 m, 0.5061, 0, 0.4363) the head camera would be off by '
              f'{1000 * resd[0]:.1f} mm, {resd[1]:.2f} deg')


# Omnipicker pads, measured by eye on ge-sim-v2-demo_000 frame 0 (cur_left.png / cur_right.png, 512x384, both grippers
# at raw 0.217 = "open"): pixel (u, v) of the distal (top) end and of the lower end of the black rubber strip on the
# inner face of each finger, +-3 px. 'outer' = the finger on idx41/idx81 (image-left in the left hand camera,
# image-right in the right hand camera).
GRIPPER_PAD_PX = {
    ('l', 'outer', 'tip'): (150, 188), ('l', 'outer', 'bottom'): (165, 242),
    ('l', 'inner', 'tip'): (411, 244), ('l', 'inner', 'bottom'): (402, 270),
    ('r', 'inner', 'tip'): (158, 233), ('r', 'inner', 'bottom'): (165, 270),
    ('r', 'outer', 'tip'): (393, 188), ('r', 'outer', 'bottom'): (378, 303),
}


def pad_keypoints(u, q, side, part):
    """Distal and proximal midpoints of the inner edge of the modelled pad box on the finger's link4, root frame."""
    pre = {'l': {'outer': '4', 'inner': '3'}, 'r': {'outer': '8', 'inner': '7'}}[side][part]
    link = u.by_name[f'idx{pre}3_gripper_{side}_{part}_joint4']['child']
    P = u.all_poses(q); B = P[f'gripper_{side}_base_link']; Bi = np.linalg.inv(B)
    boxes = [(T, prm) for T, kind, prm in u.visuals(link) if kind == 'box']
    T, size = boxes[-1]
    s = np.asarray(size) / 2
    corners = np.array([[a, b, c, 1.0] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)]) * np.r_[s, 1]
    cb = (Bi @ P[link] @ T @ corners.T).T[:, :3]          # corners in the gripper base frame
    inner = cb[np.argsort(np.abs(cb[:, 1]))[:4]]         # the 4 corners of the inner face (smallest |y|)
    inner = inner[np.argsort(inner[:, 2])]
    out = {}
    for name, sel in (('tip', inner[2:]), ('bottom', inner[:2])):
        pb = sel.mean(0); out[name] = (B @ np.r_[pb, 1.0])[:3]
    return out


def check_gripper_pads(u, D, out=None):
    """Modelled pad inner-edge ends vs the hand-camera pixels measured on the real photos (informational)."""
    J = np.load(os.path.join(D, 'state_joints_0.npy')).astype(float)
    K = np.load(os.path.join(D, 'intrinsic.npy')).astype(float)
    q = q_from_state20(J[0])
    print(f'\n== 6. Omnipicker pads vs measured pixels (ge-sim-v2 frame 0, gripper raw {J[0, 14]:.3f} / {J[0, 15]:.3f}, '
          f'outer joint1 = {q["idx41_gripper_l_outer_joint1"]:.4f} / {q["idx81_gripper_r_outer_joint1"]:.4f} rad)')
    res = []; draw = {}
    for side, ci, cam in (('l', 1, 'hand_left_camera_optical'), ('r', 2, 'hand_right_camera_optical')):
        Tcw = np.linalg.inv(u.link_pose(cam, q))
        for part in ('outer', 'inner'):
            kp = pad_keypoints(u, q, side, part)
            for which in ('tip', 'bottom'):
                uv, _ = project(K[ci], Tcw, kp[which][None])
                m = np.array(GRIPPER_PAD_PX[(side, part, which)], float)
                d = uv[0] - m; res.append(np.linalg.norm(d))
                draw.setdefault(side, []).append((m, uv[0]))
                print(f'  {side} {part:5s} {which:6s}: measured ({m[0]:.0f}, {m[1]:.0f}) model ({uv[0, 0]:.0f}, {uv[0, 1]:.0f}) '
                      f'error ({d[0]:+.0f}, {d[1]:+.0f}) px')
    res = np.array(res)
    print(f'  pad keypoint error: rms {np.sqrt((res ** 2).mean()):.1f} px, max {res.max():.1f} px (8 points; '
          'informational, not a pass/fail check: the Omnipicker is not calibrated, see README)')
    if out:
        try:
            from PIL import Image, ImageDraw
        except ImportError:
            return res
        for side, img in (('l', 'cur_left.png'), ('r', 'cur_right.png')):
            im = Image.open(os.path.join(D, img)).convert('RGB'); dr = ImageDraw.Draw(im)
            for m, p in draw[side]:
                dr.line([tuple(m), tuple(p)], fill=(255, 255, 0))
                dr.ellipse((m[0] - 4, m[1] - 4, m[0] + 4, m[1] + 4), outline=(0, 255, 0), width=2)
                dr.rectangle((p[0] - 4, p[1] - 4, p[0] + 4, p[1] + 4), outline=(255, 0, 255), width=2)
            path = os.path.join(out, 'pads_' + img); im.save(path)
            print(f'  {path}: green = measured, magenta = model, yellow = error')
    return res


WH = ['idx01_body_joint1', 'idx02_body_joint2', 'idx11_head_joint1', 'idx12_head_joint2']


def solve_waist_head(u, X, fixed=None):
    def err(x):
        q = dict(zip(WH, x)); T = u.link_pose('head_camera_optical', q)
        dR = T[:3, :3].T @ X[:3, :3]
        w = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) / 2
        return np.concatenate([T[:3, 3] - X[:3, 3], 0.3 * w])
    if fixed is not None:
        x = np.array([fixed[n] for n in WH])
    else:
        best = None
        for x0 in ([0.2, 0.5, 0, 0.3], [0.0, 0.2, 0, 0], [0.4, 0.8, 0, 0.4]):
            x = np.array(x0, float)
            for _ in range(50):
                e = err(x); Jm = np.zeros((6, 4))
                for k in range(4):
                    dx = np.zeros(4); dx[k] = 1e-6; Jm[:, k] = (err(x + dx) - e) / 1e-6
                x = x - np.linalg.lstsq(Jm, e, rcond=None)[0]
            n = np.linalg.norm(err(x))
            if best is None or n < best[0]:
                best = (n, x)
        x = best[1]
    T = u.link_pose('head_camera_optical', dict(zip(WH, x)))
    return x, (np.linalg.norm(T[:3, 3] - X[:3, 3]), rot_angle_deg(T[:3, :3], X[:3, :3]))


def check_meshes(u):
    print('\n== 5. Meshes')
    folder = os.path.dirname(u.path); files = {}
    for link in u.links:
        for T, kind, prm in u.visuals(link):
            if kind == 'mesh':
                files.setdefault(prm, []).append(link)
    tot_tri = tot_bytes = rendered = 0; ok = True
    for f, links in sorted(files.items()):
        tri = read_stl(f); n = len(tri); b = os.path.getsize(f)
        closed = closed_and_manifold(tri)
        tot_tri += n; tot_bytes += b; rendered += n * len(links)
        print(f'  {os.path.relpath(f, folder):28s} {n:6d} triangles {b / 1024:7.1f} KiB closed={closed} used by {", ".join(links)}')
        ok &= closed
    print(f'  total: {tot_tri} triangles in files ({tot_bytes / 1e6:.2f} MB); {rendered} triangles rendered for the '
          f'whole robot (meshes used twice count twice)')
    # contact between consecutive arm meshes at the zero pose and at a random pose
    P = u.all_poses({})
    worst = 0.0
    for side in 'lr':
        chain = [f'arm_{side}_base_link'] + [f'arm_{side}_link{k}' for k in range(1, 8)]
        for a, b in zip(chain, chain[1:]):
            pa = [p for l, p in robot_points(u, {}, [a])][0]; pb = [p for l, p in robot_points(u, {}, [b])][0]
            d = np.min(np.linalg.norm(pa[::7, None, :] - pb[None, ::7, :], axis=2))
            worst = max(worst, d)
    print(f'  consecutive arm meshes touch (max over pairs of the min vertex distance, subsampled): {1000 * worst:.1f} mm')
    return ok


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--robot', default=os.path.join(REPO, 'crates/embodiment/robots/agibot_g1/agibot_g1.urdf'))
    ap.add_argument('--realdata', default=os.path.join(os.path.dirname(REPO), 'shared/realdata/agibot-world'))
    ap.add_argument('--overlays', default='/tmp/g1_check')
    a = ap.parse_args()
    u = Urdf(a.robot)
    print('root link:', u.root_link)
    mv = u.movable()
    print(f'movable joints ({len(mv)}):', ', '.join(mv))
    ok = check_meshes(u)
    D = os.path.join(a.realdata, 'ge-sim-v2-demo_000')
    if not os.path.isdir(D):
        print('real data not found at', D, '- skipping the data checks'); return 0 if ok else 1
    ok &= check_fk(u, D)
    ok &= check_cameras(u, D)
    overlays(u, D, a.overlays)
    check_genie_envisioner(u, a.realdata)
    check_gripper_pads(u, D, a.overlays)
    print('\nALL PASS' if ok else '\nSOME CHECKS FAILED')
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
