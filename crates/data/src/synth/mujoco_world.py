"""One synthetic episode simulated and rendered by MuJoCo (issue 72).

Run by `bridgev2w synth --engine mujoco` (embedded in the binary, written to
a temporary file and run with the MuJoCo venv's Python), one call per
episode:

    python mujoco_world.py EPISODE.json OUT_DIR

EPISODE.json (written by the Rust side, `synth::mujoco`):
  urdf            path of the robot's URDF (meshes beside it, in meshes/)
  joint_names     the actuated joints, the columns of `joints`
  mimic           optional {joint: [source, multiplier, offset]}; default: the URDF's <mimic> tags
  joints          [T][n] commanded joint positions per frame
  fps             frames per second of the episode
  camera          fx, fy, cx, cy, width, height, world_from_camera (4x4)
  table           z_m, x_m [lo, hi], y_m [lo, hi], colors [[r,g,b] x2], texture_png (optional)
  background      [[r,g,b] x2]
  to_light_world  unit vector towards the light
  objects         [{kind: box|cylinder, size_m | radius_m+height_m, color, position_m (bottom centre), yaw_rad}]
  substeps        physics steps per frame

OUT_DIR receives rgb.npy (uint8 [T,H,W,3]), robot.npy (uint8 [T,H,W], 1
where MuJoCo's segmentation shows a robot geom), joints.npy (float64 [T,n],
the joints the position-controlled arm reached), objects.npy (float64
[T,K,4]: bottom-centre x, y, z and yaw), contacts.npy (uint8 [T,K], 1 where
a robot geom touches the object in that frame) and report.json ({"stable":
bool, "reason": str, "mujoco": version}).

The robot is position-controlled (a position actuator per actuated joint,
its gravity compensated), mimic joints follow by equality constraints; the
objects are free bodies with MuJoCo's contact and friction; the table is
static. Exit code 0 also for an unstable episode (report.json says why);
2 for bad input or a missing MuJoCo/OpenGL, with the reason on stderr.
"""

from __future__ import annotations

import json
import math
import os
import re
import sys
import tempfile

import numpy as np


def fail(message: str) -> None:
    print(f"mujoco_world: {message}", file=sys.stderr)
    sys.exit(2)


def rgba(c, a=1.0):
    return [c[0] / 255.0, c[1] / 255.0, c[2] / 255.0, a]


KP_REVOLUTE, TORQUE_REVOLUTE = 4000.0, 300.0  # N m / rad, N m
KP_PRISMATIC, FORCE_PRISMATIC = 4000.0, 100.0  # N / m, N
ROBOT_GROUP = 2  # contype of robot geoms: they touch the objects and the table, not each other


def urdf_mimics(urdf: str) -> dict:
    """`joint -> [source joint, multiplier, offset]` of the URDF's <mimic> tags."""
    import xml.etree.ElementTree as ET

    out = {}
    for j in ET.parse(urdf).getroot().findall("joint"):
        m = j.find("mimic")
        if m is not None:
            out[j.get("name")] = [m.get("joint"), float(m.get("multiplier", 1)), float(m.get("offset", 0))]
    return out


def build(mujoco, ep: dict):
    urdf = ep["urdf"]
    ep.setdefault("mimic", urdf_mimics(urdf))
    folder = os.path.dirname(os.path.abspath(urdf))
    text = open(urdf, encoding="utf-8").read()
    ext = (
        f'<mujoco><compiler meshdir="{folder}/meshes" strippath="true" '
        'discardvisual="false" fusestatic="false" balanceinertia="true"/></mujoco>'
    )
    text, n = re.subn(r"(<robot[^>]*>)", lambda m: m.group(1) + ext, text, count=1)
    if n != 1:
        fail(f"{urdf}: no <robot> element")
    with tempfile.NamedTemporaryFile("w", suffix=".urdf", delete=False) as f:
        f.write(text)
        tmp = f.name
    try:
        spec = mujoco.MjSpec.from_file(tmp)
    except Exception as e:  # the importer's own message names the element
        fail(f"{urdf}: MuJoCo cannot load it: {e}")
    finally:
        os.unlink(tmp)
    spec.option.timestep = 0.002
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = 10
    robot_bodies = [b for b in spec.bodies if b.name != "world"]
    for b in robot_bodies:
        b.gravcomp = 1.0
    # The importer makes a URDF <visual> a geom of group 1 that touches
    # nothing and a <collision> one of group 0: the collision geoms touch
    # the objects and the table (not each other) and are not drawn (group 3;
    # a mesh drawn twice flickers), the visual ones are what the camera sees.
    for g in spec.geoms:
        if g.contype == 0 and g.conaffinity == 0:
            continue
        g.contype = ROBOT_GROUP
        g.conaffinity = 1
        g.group = 3
        g.friction = [1.5, 0.01, 0.001]
        g.condim = 4
    # Actuators: arm joints stiff, the gripper softer so that it squeezes.
    names = ep["joint_names"]
    for j in spec.joints:
        j.damping[0] = max(float(j.damping[0]), 2.0)
        j.armature = max(j.armature, 0.01)
    for name in names:
        joint = spec.joint(name)
        if joint is None:
            fail(f"{urdf}: MuJoCo's model has no joint {name!r} (joint_names)")
        prismatic = joint.type == mujoco.mjtJoint.mjJNT_SLIDE
        act = spec.add_actuator(name=f"act_{name}", target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        # Stiff, critically damped (kv from the joint's inertia): the arm
        # follows its plan within a few milliradians; the force limit keeps
        # a blocked joint (a gripper closed on an object) from crushing.
        act.set_to_position(kp=KP_PRISMATIC if prismatic else KP_REVOLUTE, dampratio=1.0)
        act.forcerange = [-FORCE_PRISMATIC, FORCE_PRISMATIC] if prismatic else [-TORQUE_REVOLUTE, TORQUE_REVOLUTE]
        act.forcelimited = True
    for joint, (source, k, offset) in ep.get("mimic", {}).items():
        eq = spec.add_equality(type=mujoco.mjtEq.mjEQ_JOINT, name1=joint, name2=source)
        eq.data[:5] = [offset, k, 0, 0, 0]
    world = spec.worldbody
    # Static scene: the table and a backdrop, lit from `to_light_world`.
    t = ep["table"]
    cx, cy = (t["x_m"][0] + t["x_m"][1]) / 2, (t["y_m"][0] + t["y_m"][1]) / 2
    hx, hy = (t["x_m"][1] - t["x_m"][0]) / 2, (t["y_m"][1] - t["y_m"][0]) / 2
    # The table: a thick box that objects rest on (not drawn), its top a
    # plane drawn with the built-in world's pattern (texture_png, the table's
    # extent, row 0 at its largest y) or its first colour.
    mat = "table"
    if t.get("texture_png"):
        # The compiler strips folders from file names (strippath, for the
        # URDF's meshes): the texture is found in texturedir.
        spec.compiler.texturedir = os.path.dirname(os.path.abspath(t["texture_png"]))
        tex = spec.add_texture(name="table", type=mujoco.mjtTexture.mjTEXTURE_2D,
                               file=os.path.basename(t["texture_png"]))
        m = spec.add_material(name=mat, texrepeat=[1, 1], texuniform=False)
        m.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = tex.name
    else:
        spec.add_material(name=mat, rgba=rgba(t["colors"][0]))
    world.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_BOX, pos=[cx, cy, t["z_m"] - 0.1],
                   size=[hx, hy, 0.1], rgba=rgba(t["colors"][0]), group=3, contype=1, conaffinity=3,
                   friction=[1.0, 0.01, 0.001], condim=4)
    world.add_geom(name="table_top", type=mujoco.mjtGeom.mjGEOM_PLANE, pos=[cx, cy, t["z_m"]],
                   size=[hx, hy, 0.05], material=mat, contype=0, conaffinity=0)
    b0, b1 = ep["background"]
    spec.add_texture(name="sky", type=mujoco.mjtTexture.mjTEXTURE_SKYBOX,
                     builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT,
                     rgb1=rgba(b0)[:3], rgb2=rgba(b1)[:3], width=64, height=64)
    light = np.asarray(ep["to_light_world"], float)
    light = light / max(np.linalg.norm(light), 1e-9)
    world.add_light(name="sun", type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL, dir=-light,
                    pos=[cx + light[0], cy + light[1], t["z_m"] + light[2]], castshadow=True, diffuse=[0.7, 0.7, 0.7],
                    specular=[0.1, 0.1, 0.1])
    # The shadow map spans the model's extent about the light: the
    # workspace, the light a metre from it (a wider map or a farther light
    # shows shadow acne on the table).
    spec.stat.extent = 1.0
    spec.stat.center = [cx, cy, t["z_m"]]
    spec.visual.headlight.ambient = [0.35, 0.35, 0.35]
    spec.visual.headlight.diffuse = [0.2, 0.2, 0.2]
    spec.visual.quality.shadowsize = 4096  # 2048 shows shadow acne on the table
    # The objects: free bodies on the table.
    for i, o in enumerate(ep["objects"]):
        yaw = float(o["yaw_rad"])
        quat = [math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)]
        if o["kind"] == "box":
            sx, sy, sz = o["size_m"]
            size, kind, half_h = [sx / 2, sy / 2, sz / 2], mujoco.mjtGeom.mjGEOM_BOX, sz / 2
        elif o["kind"] == "cylinder":
            r, h = o["radius_m"], o["height_m"]
            size, kind, half_h = [r, h / 2, 0], mujoco.mjtGeom.mjGEOM_CYLINDER, h / 2
        else:
            fail(f"object {i}: kind {o['kind']!r}, expected box or cylinder")
        p = o["position_m"]
        body = world.add_body(name=f"object{i}", pos=[p[0], p[1], p[2] + half_h], quat=quat)
        body.add_freejoint(name=f"object{i}")
        body.add_geom(name=f"object{i}", type=kind, size=size, rgba=rgba(o["color"]), density=400,
                      contype=1, conaffinity=3, friction=[1.5, 0.01, 0.001], condim=4)
    # The camera: OpenCV axes (x right, y down, z forward) to MuJoCo's (looking along -z, y up).
    cam = ep["camera"]
    w, h = int(cam["width"]), int(cam["height"])
    world_from_camera = np.asarray(cam["world_from_camera"], float)
    rotation = world_from_camera[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, rotation.flatten())
    c = world.add_camera(name="c", pos=world_from_camera[:3, 3], quat=quat)
    c.fovy = float(np.degrees(2 * np.arctan((h / 2) / float(cam["fy"]))))
    spec.visual.global_.offwidth = max(w, 640)
    spec.visual.global_.offheight = max(h, 480)
    try:
        model = spec.compile()
    except Exception as e:
        fail(f"the scene does not compile: {e}")
    return model, (w, h)


def main() -> None:
    if len(sys.argv) != 3:
        fail("usage: mujoco_world.py EPISODE.json OUT_DIR")
    try:
        import mujoco
    except ImportError as e:
        fail(f"cannot import mujoco ({e}): run scripts/setup-mujoco-venv.sh (it makes .venv-mujoco)")
    ep = json.load(open(sys.argv[1], encoding="utf-8"))
    out = sys.argv[2]
    model, (w, h) = build(mujoco, ep)
    cam = ep["camera"]
    for key, centre in (("cx", (w - 1) / 2), ("cy", (h - 1) / 2)):
        if abs(float(cam[key]) - centre) > 1e-6:
            fail(f"camera {key} {cam[key]}: expected the image centre {centre} (MuJoCo's camera is a field of view)")
    if abs(float(cam["fx"]) - float(cam["fy"])) > 1e-6:
        fail(f"camera fx {cam['fx']}, fy {cam['fy']}: expected square pixels")
    data = mujoco.MjData(model)
    try:
        renderer = mujoco.Renderer(model, h, w)
        seg = mujoco.Renderer(model, h, w)
    except Exception as e:
        fail(f"MuJoCo cannot render offscreen ({e}): set MUJOCO_GL=egl (Mesa's libEGL, Debian's libegl1 libegl-mesa0 libgl1-mesa-dri) or MUJOCO_GL=osmesa (libosmesa6)")
    seg.enable_segmentation_rendering()
    names = ep["joint_names"]
    joints = np.asarray(ep["joints"], float)
    if joints.ndim != 2 or joints.shape[1] != len(names):
        fail(f"joints: shape {joints.shape}, expected [T, {len(names)}] ({', '.join(names)})")
    qadr = [model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n)] for n in names]
    mimic = ep.get("mimic", {})
    jids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n) for n in names]
    limited = np.array([bool(model.jnt_limited[j]) for j in jids])
    lo = np.where(limited, [model.jnt_range[j][0] for j in jids], -np.inf)
    hi = np.where(limited, [model.jnt_range[j][1] for j in jids], np.inf)
    madr = {j: model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, j)] for j in mimic}
    # Start at the first frame's joints, at rest, and let the objects settle.
    data.qpos[qadr] = joints[0]
    for j, (source, k, offset) in mimic.items():
        data.qpos[madr[j]] = k * joints[0][names.index(source)] + offset
    data.ctrl[:] = joints[0]
    mujoco.mj_forward(model, data)
    for _ in range(100):
        mujoco.mj_step(model, data)
    objects = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f"object{i}") for i in range(len(ep["objects"]))]
    # The robot's geoms: those of bodies other than the world and the objects.
    robot_geoms = np.array([model.geom_bodyid[g] != 0 and model.geom_bodyid[g] not in objects
                            for g in range(model.ngeom)])
    object_geoms = {model.body_geomadr[b]: i for i, b in enumerate(objects)}
    half_h = []
    for o in ep["objects"]:
        half_h.append((o["size_m"][2] if o["kind"] == "box" else o["height_m"]) / 2)
    substeps = max(1, int(round(1.0 / (float(ep["fps"]) * model.opt.timestep))))
    T = len(joints)
    rgb = np.zeros((T, h, w, 3), np.uint8)
    robot = np.zeros((T, h, w), np.uint8)
    reached = np.zeros((T, len(names)))
    poses = np.zeros((T, len(objects), 4))
    contacts = np.zeros((T, len(objects)), np.uint8)
    stable, reason = True, ""
    table_z = float(ep["table"]["z_m"])
    for t in range(T):
        if t > 0:
            for s in range(substeps):
                a = (s + 1) / substeps
                data.ctrl[:] = (1 - a) * joints[t - 1] + a * joints[t]
                mujoco.mj_step(model, data)
                for ci in range(data.ncon):
                    con = data.contact[ci]
                    for g, other in ((con.geom1, con.geom2), (con.geom2, con.geom1)):
                        if g in object_geoms and robot_geoms[other]:
                            contacts[t, object_geoms[g]] = 1
        if not np.all(np.isfinite(data.qpos)):
            stable, reason = False, f"frame {t}: the state is not finite (NaN or inf)"
            break
        # The reached joints within their limits (the solver's soft limits
        # let a joint pass them by a hair).
        reached[t] = np.clip(data.qpos[qadr], lo, hi)
        for i, b in enumerate(objects):
            pos = data.xpos[b]
            m = data.xmat[b].reshape(3, 3)
            poses[t, i] = [pos[0], pos[1], pos[2] - half_h[i], math.atan2(m[1, 0], m[0, 0])]
            if pos[2] < table_z - 0.05 and stable:
                stable, reason = False, f"frame {t}: object {i} is {table_z - pos[2]:.3f} m below the table top"
        renderer.update_scene(data, camera="c")
        rgb[t] = renderer.render()
        seg.update_scene(data, camera="c")
        ids = seg.render()
        geom = np.where(ids[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), ids[..., 0], -1)
        robot[t] = (geom >= 0) & robot_geoms[np.clip(geom, 0, model.ngeom - 1)]
    os.makedirs(out, exist_ok=True)
    np.save(os.path.join(out, "rgb.npy"), rgb)
    np.save(os.path.join(out, "robot.npy"), robot)
    np.save(os.path.join(out, "joints.npy"), reached)
    np.save(os.path.join(out, "objects.npy"), poses)
    np.save(os.path.join(out, "contacts.npy"), contacts)
    with open(os.path.join(out, "report.json"), "w", encoding="utf-8") as f:
        json.dump({"stable": stable, "reason": reason, "mujoco": mujoco.__version__,
                   "substeps": substeps}, f)


if __name__ == "__main__":
    main()
