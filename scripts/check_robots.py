#!/usr/bin/env python3
"""Check the built-in robot URDFs in crates/embodiment/robots/ with pybullet.

Run with the bench venv (scripts/bench/setup-venv.sh):
    .venv-bench/bin/python scripts/check_robots.py [--out-dir DIR]

(a) franka.urdf: pybullet FK of panda_link1..8, panda_hand, panda_hand_tcp
    and the finger frames versus a numpy implementation of the modified
    (Craig) DH table, for 100 random configurations within the limits
    (max position error must be < 1e-9 m, rotation error < 1e-9).
(b) Renders RGB + segmentation images of both robots at their home pose
    from two viewpoints into DIR (default: demo-out/check_robots, not
    committed), and checks that projecting a few link origins with the
    OpenCV camera model lands on pixels of those links (camera convention).
(c) dual_arm/dual_arm.urdf: numeric IK (pybullet calculateInverseKinematics,
    iterated, clamped to the joint limits) for table-top targets
    x in {0.4, 0.5, 0.6}, y in {0, +-0.25} (each arm on its side and the
    middle), z in {0.9, 1.0, 1.1}: position-only and with the gripper
    pointing down; reports the residuals. Position-only residuals must be
    < 1 mm; the pointing-down (top-down grasp) numbers are informational:
    with 0.3 m + 0.3 m arm segments the far (x = 0.6) and high (z = 1.1)
    targets are out of reach with the gripper vertical. Set CHECK_VERBOSE=1
    for per-target residuals.

Exit status is non-zero if a check fails.
"""

from __future__ import annotations

import argparse
import math
import os
import sys

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(REPO, "scripts", "bench"))
import bench_common as bc  # noqa: E402

ROBOTS = os.path.join(REPO, "crates", "embodiment", "robots")
FRANKA = os.path.join(ROBOTS, "franka", "franka.urdf")
G1 = os.path.join(ROBOTS, "dual_arm", "dual_arm.urdf")

PANDA_HOME = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785]
DH = [  # (a, d, alpha), modified DH
    (0.0, 0.333, 0.0),
    (0.0, 0.0, -math.pi / 2),
    (0.0, 0.316, math.pi / 2),
    (0.0825, 0.0, math.pi / 2),
    (-0.0825, 0.384, -math.pi / 2),
    (0.0, 0.0, math.pi / 2),
    (0.088, 0.0, math.pi / 2),
    (0.0, 0.107, 0.0),
]


def rotx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def rotz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def trans(x, y, z):
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def dh_fk(q, finger=0.0):
    """Modified DH: T_i = RotX(alpha) TransX(a) RotZ(theta) TransZ(d)."""
    out = {}
    T = np.eye(4)
    for i, (a, d, alpha) in enumerate(DH):
        theta = q[i] if i < 7 else 0.0
        T = T @ rotx(alpha) @ trans(a, 0, 0) @ rotz(theta) @ trans(0, 0, d)
        out[f"panda_link{i + 1}"] = T
    hand = T @ rotz(-math.pi / 4)
    out["panda_hand"] = hand
    out["panda_hand_tcp"] = hand @ trans(0, 0, 0.1034)
    out["panda_leftfinger"] = hand @ trans(0, finger, 0.0584)
    out["panda_rightfinger"] = hand @ trans(0, -finger, 0.0584)
    return out


def rpy_matrix(r, p_, y):
    return (rotz(y) @ roty(p_) @ rotx(r))


def roty(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]])


def axis_angle(axis, a):
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K
    return T


def urdf_fk(path, qmap):
    """float64 FK straight from the URDF text (joints: origin * motion(axis, q)); mimic honoured."""
    import xml.etree.ElementTree as ET

    root = ET.parse(path).getroot()
    joints = root.findall("joint")
    vals = dict(qmap)
    for j in joints:
        m = j.find("mimic")
        if m is not None and m.get("joint") in vals:
            vals[j.get("name")] = float(m.get("multiplier", 1)) * vals[m.get("joint")] + float(m.get("offset", 0))
    by_child = {j.find("child").get("link"): j for j in joints}
    cache = {}

    def pose(link):
        if link in cache:
            return cache[link]
        j = by_child.get(link)
        if j is None:
            T = np.eye(4)
        else:
            o = j.find("origin")
            xyz = [float(v) for v in o.get("xyz", "0 0 0").split()] if o is not None else [0, 0, 0]
            rpy = [float(v) for v in o.get("rpy", "0 0 0").split()] if o is not None else [0, 0, 0]
            T = pose(j.find("parent").get("link")) @ trans(*xyz) @ rpy_matrix(*rpy)
            ax = j.find("axis")
            axis = [float(v) for v in ax.get("xyz").split()] if ax is not None else [1, 0, 0]
            qv = vals.get(j.get("name"), 0.0)
            if j.get("type") in ("revolute", "continuous"):
                T = T @ axis_angle(axis, qv)
            elif j.get("type") == "prismatic":
                a = np.asarray(axis) / np.linalg.norm(axis)
                T = T @ trans(*(a * qv))
        cache[link] = T
        return T

    return {l.get("name"): pose(l.get("name")) for l in root.findall("link")}


# ---------------------------------------------------------------------------


def check_fk(n=100, seed=0):
    from pybullet_fk import compute_fk

    active = bc.urdf_active_joints(FRANKA)
    names = [j.name for j in active]
    expect = [f"panda_joint{i}" for i in range(1, 8)] + ["panda_finger_joint1"]
    assert names == expect, f"active joint order {names} != {expect}"
    lo = np.array([j.lower for j in active])
    hi = np.array([j.upper for j in active])
    rng = np.random.default_rng(seed)
    q = lo + (hi - lo) * rng.random((n, len(active)))
    q[0] = PANDA_HOME + [0.04]
    links = [f"panda_link{i}" for i in range(1, 9)] + [
        "panda_hand",
        "panda_hand_tcp",
        "panda_leftfinger",
        "panda_rightfinger",
    ]
    links, _, _, mat = compute_fk(FRANKA, names, q, links)
    max_p = max_r = 0.0
    worst = None
    for t in range(n):
        ref = dh_fk(q[t, :7], q[t, 7])
        for k, name in enumerate(links):
            ep = np.abs(mat[t, k, :3, 3] - ref[name][:3, 3]).max()
            er = np.abs(mat[t, k, :3, :3] - ref[name][:3, :3]).max()
            if ep > max_p:
                max_p, worst = ep, (name, t)
            max_r = max(max_r, er)
    # pybullet keeps link transforms in float32 (0.333 comes back as
    # 0.3330000042915344), so 1e-9 is out of its reach: 1e-6 is the bound here.
    ok = max_p < 1e-6 and max_r < 5e-6
    print(
        f"[fk] pybullet(franka.urdf) vs modified DH: {n} configs x {len(links)} links: "
        f"max position error {max_p:.3e} m (worst {worst}), max rotation error {max_r:.3e} "
        "(pybullet is float32; bounds 1e-6 m, 5e-6) -> " + ("PASS" if ok else "FAIL")
    )
    # exact check of the URDF numbers: float64 FK parsed from the URDF text
    max_p = max_r = 0.0
    for t in range(n):
        ref = dh_fk(q[t, :7], q[t, 7])
        got = urdf_fk(FRANKA, dict(zip(names, q[t])))
        for name in links:
            max_p = max(max_p, np.abs(got[name][:3, 3] - ref[name][:3, 3]).max())
            max_r = max(max_r, np.abs(got[name][:3, :3] - ref[name][:3, :3]).max())
    ok2 = max_p < 1e-9 and max_r < 1e-9
    print(
        f"[fk] float64 URDF-parsed FK (franka.urdf) vs modified DH: {n} configs x {len(links)} links: "
        f"max position error {max_p:.3e} m, max rotation error {max_r:.3e} (bound 1e-9) -> "
        + ("PASS" if ok2 else "FAIL")
    )
    ok = ok and ok2
    home = dh_fk(PANDA_HOME, 0.04)
    print(f"[fk] franka home panda_hand_tcp position: {np.round(home['panda_hand_tcp'][:3, 3], 4).tolist()}")
    return ok


# ---------------------------------------------------------------------------


def render(p, client, body, cam, light=(2, -2, 3)):
    view, proj = bc.camera_matrices(cam)
    w, h = cam["width"], cam["height"]
    _, _, rgba, _, seg = p.getCameraImage(
        w,
        h,
        viewMatrix=view,
        projectionMatrix=proj,
        renderer=p.ER_TINY_RENDERER,
        flags=p.ER_SEGMENTATION_MASK_OBJECT_AND_LINKINDEX,
        lightDirection=list(light),
        shadow=0,
        physicsClientId=client,
    )
    rgba = np.asarray(rgba, dtype=np.uint8).reshape(h, w, 4)
    seg = np.asarray(seg, dtype=np.int64).reshape(h, w)
    label = np.where(seg >= 0, (seg >> 24) + 1, 0)  # 0 bg, 1 base, k+2 link k
    return rgba[:, :, :3], label


def check_render(out_dir):
    import pybullet as p

    os.makedirs(out_dir, exist_ok=True)
    client = p.connect(p.DIRECT)
    ok = True
    setups = [
        (
            "franka",
            FRANKA,
            dict(zip([f"panda_joint{i}" for i in range(1, 8)] + ["panda_finger_joint1"], PANDA_HOME + [0.04])),
            [((1.5, -0.9, 0.8), (0.25, 0.0, 0.45)), ((-0.2, 1.6, 0.6), (0.25, 0.0, 0.45))],
        ),
        (
            "dual_arm",
            G1,
            {},
            [((2.2, -1.2, 1.4), (0.0, 0.0, 0.9)), ((1.0, 2.2, 1.6), (0.0, 0.0, 0.9))],
        ),
    ]
    pal = bc.palette(64)
    for name, urdf, qmap, views in setups:
        body = p.loadURDF(urdf, [0, 0, 0], [0, 0, 0, 1], useFixedBase=True, physicsClientId=client)
        jidx, lidx = bc.pybullet_index_maps(p, body, client)
        mimics = [j for j in bc.urdf_joints(urdf) if j.mimic is not None]
        bc.set_joints(p, body, client, jidx, list(qmap.keys()), list(qmap.values()), mimics)
        for vi, (eye, target) in enumerate(views):
            cam = bc.look_at_camera(eye, target, 720, 480, 600.0)
            rgb, label = render(p, client, body, cam)
            img = np.concatenate([rgb, pal[label % 64]], axis=1)
            path = os.path.join(out_dir, f"{name}_view{vi}.png")
            bc.write_png(path, img)
            print(f"[render] {path}  robot pixels {int((label > 0).sum())}")
            if (label > 0).sum() < 5000:
                ok = False
        p.removeBody(body, physicsClientId=client)
    ok &= check_camera_convention(p, client)
    p.disconnect(physicsClientId=client)
    print("[render] " + ("PASS" if ok else "FAIL"))
    return ok


def check_camera_convention(p, client):
    """Small spheres at known points must render centred on their OpenCV projection.

    Uses an off-centre principal point so a wrong sign or a missing offset in
    the intrinsics -> OpenGL projection conversion shows up.
    """
    cam = bc.look_at_camera((1.6, -0.7, 1.0), (0.2, 0.1, 0.5), 720, 480, 610.0, 590.0, cx=331.0, cy=262.5)
    # a 5 x 4 grid of points 1.5 m in front of the camera (no overlaps)
    T = cam["world_from_camera"]
    pts = np.array(
        [T[:3, 3] + T[:3, :3] @ np.array([u, v, 1.5]) for u in np.linspace(-0.5, 0.5, 5) for v in np.linspace(-0.3, 0.3, 4)]
    )
    vis = p.createVisualShape(p.GEOM_SPHERE, radius=0.02, physicsClientId=client)
    bodies = [p.createMultiBody(0, -1, vis, basePosition=list(x), physicsClientId=client) for x in pts]
    view, proj = bc.camera_matrices(cam)
    seg = p.getCameraImage(
        cam["width"], cam["height"], viewMatrix=view, projectionMatrix=proj, renderer=p.ER_TINY_RENDERER,
        physicsClientId=client,
    )[4]
    seg = np.asarray(seg).reshape(cam["height"], cam["width"])
    uv = bc.project_points(cam, pts)
    worst = 0.0
    for b, (u, v) in zip(bodies, uv):
        ys, xs = np.nonzero(seg == b)
        if len(xs) == 0:
            worst = float("inf")
            continue
        worst = max(worst, math.hypot(xs.mean() - u, ys.mean() - v))
    for b in bodies:
        p.removeBody(b, physicsClientId=client)
    good = worst < 0.25
    print(
        f"[camera] OpenCV projection vs rendered sphere centroids (fx 610, fy 590, cx 331, cy 262.5): "
        f"max offset {worst:.3f} px -> " + ("PASS" if good else "FAIL")
    )
    return good


# ---------------------------------------------------------------------------


def check_g1_reach(out_dir):
    import pybullet as p

    client = p.connect(p.DIRECT)
    body = p.loadURDF(G1, [0, 0, 0], [0, 0, 0, 1], useFixedBase=True, physicsClientId=client)
    jidx, lidx = bc.pybullet_index_maps(p, body, client)
    # pybullet IK works on all non-fixed joints, in joint-index order
    dof = [
        i
        for i in range(p.getNumJoints(body, physicsClientId=client))
        if p.getJointInfo(body, i, physicsClientId=client)[2] != p.JOINT_FIXED
    ]
    lower = [p.getJointInfo(body, i, physicsClientId=client)[8] for i in dof]
    upper = [p.getJointInfo(body, i, physicsClientId=client)[9] for i in dof]
    ranges = [u - l for l, u in zip(lower, upper)]
    # rest pose: elbows bent, forearms forward (a natural working posture)
    rest_named = {
        "left_arm_joint1": -0.5,
        "right_arm_joint1": -0.5,
        "left_arm_joint4": -1.2,
        "right_arm_joint4": -1.2,
    }
    names = [p.getJointInfo(body, i, physicsClientId=client)[1].decode() for i in dof]
    rest = [rest_named.get(n, 0.0) for n in names]
    down = p.getQuaternionFromEuler([math.pi, 0, 0])  # gripper z (approach) pointing down

    all_q0 = [0.0] * len(dof)

    def arm_cols(side):
        return [k for k, n in enumerate(names) if n.startswith(f"{side}_arm_joint")]

    def fk(tcp):
        st = p.getLinkState(body, lidx[tcp], computeForwardKinematics=True, physicsClientId=client)
        return np.array(st[4]), st[5]

    def set_q(q):
        for i, v in zip(dof, q):
            p.resetJointState(body, i, float(v), physicsClientId=client)

    def errors(tcp, target, orn):
        pos, cur = fk(tcp)
        e_pos = float(np.linalg.norm(pos - target))
        if orn is None:
            return e_pos, 0.0
        d = p.getDifferenceQuaternion(cur, orn)
        return e_pos, 2 * math.acos(min(1.0, abs(d[3])))

    def refine(tcp, target, orn, q, cols, iters=300, lam=0.02):
        """Damped least squares on one arm's joints with pybullet's Jacobian, clamped to limits."""
        q = np.array(q, dtype=np.float64)
        for _ in range(iters):
            set_q(q)
            pos, cur = fk(tcp)
            e = target - pos
            jl, ja = p.calculateJacobian(
                body, lidx[tcp], [0, 0, 0], list(q), all_q0, all_q0, physicsClientId=client
            )
            J = np.array(jl)[:, cols]
            if orn is not None:
                R_cur = np.array(p.getMatrixFromQuaternion(cur)).reshape(3, 3)
                R_tgt = np.array(p.getMatrixFromQuaternion(orn)).reshape(3, 3)
                # small-angle rotation error (world frame)
                e_rot = 0.5 * sum(np.cross(R_cur[:, k], R_tgt[:, k]) for k in range(3))
                e = np.concatenate([e, 0.3 * e_rot])
                J = np.vstack([J, 0.3 * np.array(ja)[:, cols]])
            if np.linalg.norm(e) < 1e-7:
                break
            dq = J.T @ np.linalg.solve(J @ J.T + lam * lam * np.eye(len(e)), e)
            q[cols] = np.clip(q[cols] + dq, np.array(lower)[cols], np.array(upper)[cols])
        set_q(q)
        return q

    def solve(tcp, target, orn, seeds=8):
        """pybullet calculateInverseKinematics (null space towards `rest`), then a DLS refinement."""
        cols = arm_cols(tcp.split("_")[0])
        rng = np.random.default_rng(0)
        best = None
        for s_i in range(seeds):
            start = np.array(rest, dtype=np.float64)
            if s_i > 0:
                start[cols] += rng.normal(0, 0.8, len(cols))
                start = np.clip(start, lower, upper)
            set_q(start)
            kw = dict(
                lowerLimits=lower, upperLimits=upper, jointRanges=ranges, restPoses=list(start),
                maxNumIterations=200, residualThreshold=1e-6, physicsClientId=client,
            )
            for _ in range(20):
                if orn is None:
                    sol = p.calculateInverseKinematics(body, lidx[tcp], list(target), **kw)
                else:
                    sol = p.calculateInverseKinematics(body, lidx[tcp], list(target), orn, **kw)
                q = np.array(start)
                q[cols] = np.clip(np.array(sol)[cols], np.array(lower)[cols], np.array(upper)[cols])
                set_q(q)
            q = refine(tcp, target, orn, q, cols)
            e, a = errors(tcp, target, orn)
            if best is None or e + 0.05 * a < best[0]:
                best = (e + 0.05 * a, (e, a), q)
            if e < 1e-5 and a < 1e-3:
                break
        set_q(best[2])
        return best[1]

    ok = True
    # mirror symmetry: right arm at M q == left arm at q reflected in y
    M = np.array([1, -1, -1, 1, -1, 1, -1.0])
    rng = np.random.default_rng(3)
    lcols, rcols = arm_cols("left"), arm_cols("right")
    worst = 0.0
    for _ in range(50):
        q = np.array(all_q0)
        q[lcols] = rng.uniform(np.array(lower)[lcols], np.array(upper)[lcols])
        q[rcols] = M * q[lcols]
        set_q(q)
        pl, ql = fk("left_gripper_tcp")
        pr, qr = fk("right_gripper_tcp")
        Rl = np.array(p.getMatrixFromQuaternion(ql)).reshape(3, 3)
        Rr = np.array(p.getMatrixFromQuaternion(qr)).reshape(3, 3)
        S = np.diag([1, -1, 1.0])
        # reflected frame S Rl S (the y column flips handedness twice)
        worst = max(worst, np.abs(S @ pl - pr).max(), np.abs(S @ Rl @ S - Rr).max())
    sym = worst < 1e-5
    ok &= sym
    print(f"[reach] mirror symmetry right(M q) vs left(q) reflected: max error {worst:.2e} -> " + ("PASS" if sym else "FAIL"))
    for side, ys in (("left", (0.0, 0.25)), ("right", (0.0, -0.25))):
        tcp = f"{side}_gripper_tcp"
        for mode, orn in (("position", None), ("pointing-down", down)):
            errs, angs, worst = [], [], None
            for x in (0.4, 0.5, 0.6):
                for y in ys:
                    for z in (0.9, 1.0, 1.1):
                        e, a = solve(tcp, np.array([x, y, z]), orn)
                        if os.environ.get("CHECK_VERBOSE"):
                            print(f"    {side} {mode} {(x, y, z)}: {e * 1000:.2f} mm {math.degrees(a):.1f} deg")
                        errs.append(e)
                        angs.append(a)
                        if worst is None or e > worst[0]:
                            worst = (e, (x, y, z))
            msg = (
                f"[reach] {side} arm {mode:13s}: {len(errs)} targets, max position residual "
                f"{max(errs) * 1000:.3f} mm (worst at {worst[1]}), mean {np.mean(errs) * 1000:.3f} mm"
            )
            if orn is not None:
                msg += f", max orientation residual {math.degrees(max(angs)):.2f} deg"
            if mode == "position":
                good = max(errs) < 1e-3
                ok &= good
                msg += " -> " + ("PASS" if good else "FAIL")
            print(msg)
    # a picture of both arms reaching the same table-top targets
    for side, y in (("left", 0.2), ("right", -0.2)):
        solve(f"{side}_gripper_tcp", np.array([0.5, y, 0.95]), down)
        # keep this arm's solution, solve the other from its current state
        rest_now = [p.getJointState(body, i, physicsClientId=client)[0] for i in dof]
        rest[:] = rest_now
    cam = bc.look_at_camera((2.0, -1.4, 1.6), (0.2, 0.0, 0.9), 720, 480, 600.0)
    rgb, label = render(p, client, body, cam)
    path = os.path.join(out_dir, "dual_arm_reach.png")
    bc.write_png(path, np.concatenate([rgb, bc.palette(64)[label % 64]], axis=1))
    print(f"[reach] {path}")
    p.disconnect(physicsClientId=client)
    return ok


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out-dir", default=os.path.join(REPO, "demo-out", "check_robots"))
    ap.add_argument("--configs", type=int, default=100)
    args = ap.parse_args()
    out = bc.real_stdout()
    sys.stdout = out  # our prints go to stdout; native pybullet chatter to stderr
    results = {
        "fk": check_fk(args.configs),
        "render": check_render(args.out_dir),
        "reach": check_g1_reach(args.out_dir),
    }
    print("[check_robots] " + " ".join(f"{k}={'PASS' if v else 'FAIL'}" for k, v in results.items()))
    sys.exit(0 if all(results.values()) else 1)


if __name__ == "__main__":
    main()
