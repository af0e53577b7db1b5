#!/usr/bin/env python3
"""Rebuild crates/embodiment/robots/agibot_g1/ (the real AgiBot G1 with the Omnipicker gripper).

Sources (read straight out of git at pinned commits; both MPL-2.0):

* AgibotTech/genie_sim @ ebfd1b227361a8919962012a88d6abe63a05bee1:
  source/geniesim/app/robot_cfg/G01/G01_omnipicker.urdf -- kinematics, joint/link names, limits, inertials,
  collision cylinders, and the (commented-out) collision boxes/cylinders/spheres of base_link, body_link1 and
  body_link2, used here as visual primitives. Its own meshes (FBX/DAE) are not public.
* fiveages-sim/robot_descriptions @ f609e7f902ac9c30231f1ef5e3b0fcac3bc464af:
  humanoid/Agibot/agibot_g1_description/ -- LICENSE (MPL-2.0), meshes/arm/{base_link,link1..link7}.obj (the G1
  arm, one set used for both arms exactly as that package's xacro does), meshes/base/{body_link1,head_link1,
  head_link2}.obj. Its urdf/G1_120s.urdf has the same arm/head/waist joint origins as genie_sim (only the lift
  joint's z differs: 0.4285 vs 0.6485; genie_sim's value is kept -- it matches the real data).

Usage:

    python3 -m venv /tmp/g1venv && /tmp/g1venv/bin/pip install numpy trimesh pymeshlab scipy scikit-image
    /tmp/g1venv/bin/python scripts/robots/agibot_g1.py \
        --genie-sim /path/to/genie_sim(.git) --robot-descriptions /path/to/robot_descriptions(.git) \
        [--out crates/embodiment/robots/agibot_g1] [--urdf-only]

Meshes: each OBJ is loaded with trimesh, voxelised (pitch in TARGETS), solid-filled, re-surfaced with marching
cubes (this closes the many open CAD shells into one watertight solid), decimated with pymeshlab's quadric edge
collapse (topology preserved, so the result stays closed) to the triangle budget in TARGETS and written as a
binary STL in the link frame (any visual origin baked in). README.md is hand-written and not touched here.

Modifications to the genie_sim URDF (all documented in README.md):
* new root link `agibot_world_base` (the frame AgiBot World records end poses and camera extrinsics in:
  0.3 m above genie_sim's base_link, i.e. on top of the 0.30 m chassis), fixed joint to base_link;
* `<loop_joint>` elements removed; the passive Omnipicker joints get `<mimic>` of the outer joint1 (linear fits
  of the closed-chain solution with parallel finger pads), so each gripper has one movable joint;
* visuals: meshes above, primitives for chassis/column/torso/gripper;
* fixed camera links `head_camera_optical`, `hand_left_camera_optical`, `hand_right_camera_optical` (OpenCV
  axes), mounts estimated from AgiBot World data by scripts/robots/check_agibot_g1.py (constants below).
"""
import argparse
import math
import os
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from check_agibot_g1 import Urdf, R_to_rpy, quat_xyzw_to_R  # noqa: E402

GENIE_COMMIT = 'ebfd1b227361a8919962012a88d6abe63a05bee1'
GENIE_URDF = 'source/geniesim/app/robot_cfg/G01/G01_omnipicker.urdf'
RD_COMMIT = 'f609e7f902ac9c30231f1ef5e3b0fcac3bc464af'
RD_DIR = 'humanoid/Agibot/agibot_g1_description/'

# out file -> (source obj, rpy of genie_sim's visual origin baked in, voxel pitch m, target triangles)
TARGETS = {
    'arm_base_link.stl': ('meshes/arm/base_link.obj', (0, 0, 0), 0.002, 2000),
    'arm_link1.stl': ('meshes/arm/link1.obj', (0, 0, 0), 0.002, 1800),
    'arm_link2.stl': ('meshes/arm/link2.obj', (0, 0, 0), 0.002, 2200),
    'arm_link3.stl': ('meshes/arm/link3.obj', (0, 0, 0), 0.002, 1800),
    'arm_link4.stl': ('meshes/arm/link4.obj', (0, 0, 0), 0.002, 2000),
    'arm_link5.stl': ('meshes/arm/link5.obj', (0, 0, 0), 0.002, 1600),
    'arm_link6.stl': ('meshes/arm/link6.obj', (0, 0, 0), 0.002, 2000),
    'arm_link7.stl': ('meshes/arm/link7.obj', (0, 0, 0), 0.002, 1800),
    'body_link1.stl': ('meshes/base/body_link1.obj', (0, 0, 0), 0.0025, 2500),
    'head_link1.stl': ('meshes/base/head_link1.obj', (0, 0, 0), 0.002, 1200),
    'head_link2.stl': ('meshes/base/head_link2.obj', (-math.pi, 0, 0), 0.0025, 2500),
}
LINK_MESH = {'body_link1': 'body_link1.stl', 'head_link1': 'head_link1.stl', 'head_link2': 'head_link2.stl',
             'arm_l_base_link': 'arm_base_link.stl', 'arm_r_base_link': 'arm_base_link.stl'}
for _s in 'lr':
    for _k in range(1, 8):
        LINK_MESH[f'arm_{_s}_link{_k}'] = f'arm_link{_k}.stl'

WORLD_Z = 0.3  # agibot_world_base is 0.3 m above base_link

# Camera mounts (parent, xyz, quaternion xyzw), estimated by check_agibot_g1.py from AgiBot World
# ge-sim-v2-demo_000 (mean over still frames): parent_from_camera, OpenCV optical axes.
CAMERAS = {
    'head_camera_optical': ('head_link2', (0.094020, -0.054519, -0.016130), (0.008852, 0.704563, 0.003900, 0.709582)),
    'hand_left_camera_optical': ('arm_l_link7', (-0.004321, -0.070545, 0.054142), (-0.228322, -0.008033, -0.000497, 0.973549)),
    'hand_right_camera_optical': ('arm_r_link7', (-0.003388, -0.058160, 0.040250), (-0.215912, -0.004907, 0.002650, 0.976397)),
}


def git_show(gitdir, commit, path):
    gd = gitdir if os.path.isdir(os.path.join(gitdir, 'objects')) else os.path.join(gitdir, '.git')
    return subprocess.run(['git', '--git-dir', gd, 'show', f'{commit}:{path}'], check=True,
                          capture_output=True).stdout


def f6(v):
    return ' '.join(f'{x:.9g}' if abs(x) > 1e-12 else '0' for x in v)


def build_mesh(obj_bytes, rpy, pitch, target, out_path):
    import trimesh
    import pymeshlab
    from check_agibot_g1 import rpy_to_R
    m = trimesh.load(trimesh.util.wrap_as_stream(obj_bytes), file_type='obj', force='mesh')
    T = np.eye(4); T[:3, :3] = rpy_to_R(*rpy); m.apply_transform(T)
    v = m.voxelized(pitch).fill()
    mc = v.marching_cubes; mc.apply_transform(v.transform)
    ms = pymeshlab.MeshSet(); ms.add_mesh(pymeshlab.Mesh(mc.vertices, mc.faces))
    ms.meshing_decimation_quadric_edge_collapse(targetfacenum=target, preservetopology=True, preservenormal=True,
                                                planarquadric=True, qualitythr=0.5)
    cm = ms.current_mesh()
    o = trimesh.Trimesh(cm.vertex_matrix(), cm.face_matrix(), process=True)
    trimesh.repair.fix_normals(o)
    if o.is_watertight and o.volume < 0:
        o.invert()
    o.export(out_path, file_type='stl')
    return len(o.faces), o.is_watertight


def sub(parent, tag, **attrs):
    e = ET.SubElement(parent, tag)
    for k, v in attrs.items():
        e.set(k, v)
    return e


def add_visual(link, geom, params, xyz=(0, 0, 0), rpy=(0, 0, 0), material='grey', mesh=None):
    v = sub(link, 'visual')
    sub(v, 'origin', xyz=f6(xyz), rpy=f6(rpy))
    g = sub(v, 'geometry')
    if geom == 'mesh':
        sub(g, 'mesh', filename=mesh)
    elif geom == 'box':
        sub(g, 'box', size=f6(params))
    elif geom == 'cylinder':
        sub(g, 'cylinder', radius=f'{params[0]:.9g}', length=f'{params[1]:.9g}')
    elif geom == 'sphere':
        sub(g, 'sphere', radius=f'{params[0]:.9g}')
    sub(v, 'material', name=material)
    return v


def bar(link, p0, p1, width, depth, material='black'):
    """Box from p0 to p1 (both in the link's xy plane), in-plane width, depth along the link z (joint axis)."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    d = p1 - p0; L = float(np.linalg.norm(d))
    add_visual(link, 'box', (L + width, width, depth), xyz=(p0 + p1) / 2, rpy=(0, 0, math.atan2(d[1], d[0])),
               material=material)


def gripper_names(side):
    o = '4' if side == 'l' else '8'; i = '3' if side == 'l' else '7'
    n = {}
    for part, pre in (('outer', o), ('inner', i)):
        n[part] = dict(j1=f'idx{pre}1_gripper_{side}_{part}_joint1', j3=f'idx{pre}2_gripper_{side}_{part}_joint3',
                       j4=f'idx{pre}3_gripper_{side}_{part}_joint4', j2=f'idx{pre}9_gripper_{side}_{part}_joint2')
    return n


def solve_gripper(u, side):
    """Closed-chain solution (parallel pads: j1 + j3 + j4 = 0) per finger, as linear fits in the master angle."""
    names = gripper_names(side); base = f'gripper_{side}_base_link'
    master = names['outer']['j1']
    fits = {}; worst = 0.0
    for part, sgn in (('outer', 1.0), ('inner', -1.0)):
        n = names[part]
        l2 = u.by_name[n['j2']]['child']; l4 = u.by_name[n['j4']]['child']
        pa = np.array([0.03123003, sgn * 0.010280428, 0, 1]); pb = np.array([0, sgn * 0.010280428, 0, 1])
        ths = np.linspace(0, 0.7853981633974483, 33); sol = []
        x = np.zeros(2)
        for th in ths:
            j1 = sgn * th  # inner joint1 = -outer joint1 (genie_sim mimic)

            def res(x):
                q = {n['j1']: j1, n['j3']: x[0], n['j4']: -j1 - x[0], n['j2']: x[1]}
                P = u.all_poses(q); B = np.linalg.inv(P[base])
                return ((B @ P[l2] @ pa) - (B @ P[l4] @ pb))[:3]
            for _ in range(30):
                e = res(x); Jm = np.zeros((3, 2))
                for k in range(2):
                    dx = np.zeros(2); dx[k] = 1e-7; Jm[:, k] = (res(x + dx) - e) / 1e-7
                x = x - np.linalg.lstsq(Jm, e, rcond=None)[0]
            worst = max(worst, float(np.linalg.norm(res(x))))
            sol.append(x.copy())
        sol = np.array(sol)
        a3, b3 = np.polyfit(ths, sol[:, 0], 1); a2, b2 = np.polyfit(ths, sol[:, 1], 1)
        fit_err = max(np.abs(np.polyval([a3, b3], ths) - sol[:, 0]).max(), np.abs(np.polyval([a2, b2], ths) - sol[:, 1]).max())
        j1m = sgn
        fits[part] = {n['j3']: (a3, b3), n['j4']: (-j1m - a3, -b3), n['j2']: (a2, b2)}
        if part == 'inner':
            fits[part][n['j1']] = (-1.0, 0.0)
        print(f'  gripper {side} {part}: closure residual {worst * 1000:.3f} mm, linear-fit max error {fit_err:.3f} rad')
    return master, fits


def build_urdf(genie_text, out_dir):
    root = ET.fromstring(genie_text)
    root.set('name', 'agibot_g1')
    with tempfile.NamedTemporaryFile('wb', suffix='.urdf', delete=False) as f:
        f.write(genie_text); tmp = f.name
    u = Urdf(tmp); os.unlink(tmp)
    links = {l.get('name'): l for l in root.findall('link')}
    joints = {j.get('name'): j for j in root.findall('joint')}

    # 1. drop loop joints (non-standard), visuals and commented collisions are rebuilt below
    for lj in root.findall('loop_joint'):
        root.remove(lj)
    for l in links.values():
        for v in l.findall('visual'):
            l.remove(v)
        for c in l.findall('collision'):  # genie_sim's arm collisions reference nothing external; keep them
            pass

    # 2. new root frame
    wl = ET.Element('link', name='agibot_world_base')
    wj = ET.Element('joint', name='agibot_world_base_joint', type='fixed')
    sub(wj, 'parent', link='agibot_world_base'); sub(wj, 'child', link='base_link')
    sub(wj, 'origin', xyz=f6((0, 0, -WORLD_Z)), rpy='0 0 0')
    first = list(root).index(links['base_link'])
    root.insert(first, wj); root.insert(first, wl)

    # 3. meshes
    for link, mesh in LINK_MESH.items():
        add_visual(links[link], 'mesh', None, mesh='meshes/' + mesh, material='white')

    # 4. primitives from genie_sim's (commented-out) collision shapes
    bl = links['base_link']
    add_visual(bl, 'box', (0.5996094, 0.449, 0.30273438), xyz=(0, 0, 0.15), material='grey')          # chassis
    add_visual(bl, 'box', (0.29833984, 0.3376392, 1.0), xyz=(-0.10913086, 0, 0.51171875), material='grey')  # lift column
    b2 = links['body_link2']
    add_visual(b2, 'cylinder', (0.09662318, 0.08697057), xyz=(0.0068359375, -0.00034356117, 0), material='white')
    add_visual(b2, 'sphere', (0.09662318,), xyz=(0.0068359375, -0.00034356117, 0.043485285), material='white')
    add_visual(b2, 'sphere', (0.09662318,), xyz=(0.0068359375, -0.00034356117, -0.043485285), material='white')
    add_visual(b2, 'box', (0.34570312, 0.18107724, 0.3125), xyz=(0.008, -0.248, 0), rpy=(0, 0, -math.pi / 2),
               material='white')

    # 5. Omnipicker gripper: mimics + primitives
    for side in 'lr':
        master, fits = solve_gripper(u, side)
        for part in fits.values():
            for jn, (k, off) in part.items():
                j = joints[jn]
                for m in j.findall('mimic'):
                    j.remove(m)
                sub(j, 'mimic', joint=master, multiplier=f'{k:.9g}', offset=f'{off:.9g}')
        base = links[f'gripper_{side}_base_link']
        add_visual(base, 'box', (0.062, 0.092, 0.076), xyz=(0, 0, 0.038), material='black')     # housing
        add_visual(base, 'cylinder', (0.034, 0.012), xyz=(0, 0, 0.006), material='grey')         # flange ring
        names = gripper_names(side)
        for part, sgn in (('outer', 1.0), ('inner', -1.0)):
            n = names[part]
            l1 = links[u.by_name[n['j1']]['child']]; l3 = links[u.by_name[n['j3']]['child']]
            l4n = u.by_name[n['j4']]['child']; l4 = links[l4n]; l2 = links[u.by_name[n['j2']]['child']]
            bar(l1, (0, 0, 0), (0.030852, sgn * 0.018551, 0), 0.012, 0.030)
            bar(l3, (0, 0, 0), (0.018118, sgn * 0.01574, 0), 0.012, 0.030)
            bar(l2, (0, 0, 0), (0.03123003, sgn * 0.010280428, 0), 0.010, 0.024)
            # finger pad: a box aligned with the gripper base axes (the pad stays parallel), from the link4
            # origin 0.055 m forward (+z of the gripper base), 0.016 m thick, slightly inside the origin
            q0 = {master: 0.3}
            for part2 in fits.values():
                for jn, (k, off) in part2.items():
                    q0[jn] = k * 0.3 + off
            P = u.all_poses(q0)
            Bl4 = np.linalg.inv(P[f'gripper_{side}_base_link']) @ P[l4n]
            c_base = Bl4[:3, 3] + np.array([0, -sgn * 0.006, 0.026])
            Rl4 = Bl4[:3, :3]
            c_l4 = Rl4.T @ (c_base - Bl4[:3, 3])
            add_visual(l4, 'box', (0.034, 0.016, 0.058), xyz=c_l4, rpy=R_to_rpy(Rl4.T), material='black')

    # 6. cameras
    end = list(root)
    for cam, (parent, xyz, q) in CAMERAS.items():
        root.append(ET.Element('link', name=cam))
        j = ET.Element('joint', name=cam + '_joint', type='fixed')
        sub(j, 'parent', link=parent); sub(j, 'child', link=cam)
        sub(j, 'origin', xyz=f6(xyz), rpy=f6(R_to_rpy(quat_xyzw_to_R(q))))
        root.append(j)

    ET.indent(root, space='  ')
    hdr = ('\n  AgiBot G1 (genie_sim G01 + Omnipicker), generated by scripts/robots/agibot_g1.py.\n'
           f'  Kinematics: AgibotTech/genie_sim @ {GENIE_COMMIT[:7]} {GENIE_URDF} (MPL-2.0).\n'
           f'  Arm/head/lift meshes: fiveages-sim/robot_descriptions @ {RD_COMMIT[:7]} {RD_DIR} (MPL-2.0).\n'
           '  Gripper/torso/chassis: primitives. Root agibot_world_base = AgiBot World recording frame. See README.md.\n')
    root.insert(0, ET.Comment(hdr))
    txt = '<?xml version="1.0"?>\n' + ET.tostring(root, encoding='unicode') + '\n'
    with open(os.path.join(out_dir, 'agibot_g1.urdf'), 'w') as f:
        f.write(txt)


def main():
    repo = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--genie-sim', required=True, help='AgibotTech/genie_sim git dir (bare mirror or clone)')
    ap.add_argument('--robot-descriptions', required=True, help='fiveages-sim/robot_descriptions git dir')
    ap.add_argument('--out', default=os.path.join(repo, 'crates/embodiment/robots/agibot_g1'))
    ap.add_argument('--urdf-only', action='store_true', help='rewrite the URDF (and LICENSE) only')
    a = ap.parse_args()
    os.makedirs(os.path.join(a.out, 'meshes'), exist_ok=True)
    genie = git_show(a.genie_sim, GENIE_COMMIT, GENIE_URDF)
    build_urdf(genie, a.out)
    with open(os.path.join(a.out, 'LICENSE'), 'wb') as f:
        f.write(git_show(a.robot_descriptions, RD_COMMIT, RD_DIR + 'LICENSE'))
    if not a.urdf_only:
        for out, (src, rpy, pitch, target) in TARGETS.items():
            n, wt = build_mesh(git_show(a.robot_descriptions, RD_COMMIT, RD_DIR + src), rpy, pitch, target,
                               os.path.join(a.out, 'meshes', out))
            print(f'  meshes/{out}: {n} triangles, watertight={wt}')
    print('wrote', a.out)


if __name__ == '__main__':
    main()
