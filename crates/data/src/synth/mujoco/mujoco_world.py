"""The synthetic world's scenes simulated and rendered by MuJoCo (issue 72).

Run by `bridgev2w synth --engine mujoco` (embedded in the binary, written to
a temporary folder with the robot's description and run with the MuJoCo
venv's Python) as a session over stdin and stdout (`--serve`; the protocol
in `serve`, the Rust side in `session.rs`).

An episode (the JSON of a reset, written by the Rust side):
  urdf            path of the robot's URDF (meshes beside it, in meshes/)
  joint_names     the actuated joints, the columns of `joints`
  mimic           optional {joint: [source, multiplier, offset]}; default: the URDF's <mimic> tags
  joints          [T][n] joint positions; the first row is the start
  fps             frames per second (physics steps per frame = 1 / (fps x 2 ms))
  camera          fx, fy, cx, cy, width, height, world_from_camera (4x4)
  table           z_m, x_m [lo, hi], y_m [lo, hi], colors [[r,g,b] x2], texture_png (optional)
  background      [[r,g,b] x2]: the sky's gradient
  backdrop_rgb    optional: raw sRGB8 [height, width, 3] file, drawn where a pixel's ray meets no geom
  to_light_world  unit vector towards the light
  objects         [{kind: box|cylinder, size_m | radius_m+height_m, color, position_m (bottom centre), yaw_rad}]

The robot is position-controlled (a position actuator per actuated joint,
its gravity compensated), mimic joints follow by equality constraints; the
objects are free bodies with MuJoCo's contact and friction; the table is
static. Each frame reports the joints the arm reached (within their
limits), the objects' poses (bottom centre and yaw), which objects a robot
geom touched, and when rendered the RGB frame and MuJoCo's segmentation of
the robot's geoms. An unstable frame (a non-finite state, an object through
the table) ends the reply with "stable": false and the reason. Exit code 2
for bad input or a missing MuJoCo/OpenGL, with the reason on stderr.
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


def urdf_spec(mujoco, urdf: str, balance_inertia: bool = True):
    """The URDF as MuJoCo's importer reads it: visual geoms kept, every link a
    body, meshes by file name from the description's meshes/ folder."""
    folder = os.path.dirname(os.path.abspath(urdf))
    text = open(urdf, encoding="utf-8").read()
    ext = (
        f'<mujoco><compiler meshdir="{folder}/meshes" strippath="true" '
        'discardvisual="false" fusestatic="false"'
        + (' balanceinertia="true"' if balance_inertia else "")
        + "/></mujoco>"
    )
    text, n = re.subn(r"(<robot[^>]*>)", lambda m: m.group(1) + ext, text, count=1)
    if n != 1:
        fail(f"{urdf}: no <robot> element")
    with tempfile.NamedTemporaryFile("w", suffix=".urdf", delete=False) as f:
        f.write(text)
        tmp = f.name
    try:
        return mujoco.MjSpec.from_file(tmp)
    except Exception as e:  # the importer's own message names the element
        fail(f"{urdf}: MuJoCo cannot load it: {e}")
    finally:
        os.unlink(tmp)


def add_camera(mujoco, spec, camera: dict, name: str = "c"):
    """A camera JSON's camera in `spec`: OpenCV axes (x right, y down, z
    forward) turned into MuJoCo's (looking along -z, y up), the vertical
    field of view from fy. Square pixels and a centred principal point are
    required (MuJoCo's camera is a field of view). Returns (width, height)."""
    w, h = int(camera["width"]), int(camera["height"])
    for key, centre in (("cx", (w - 1) / 2), ("cy", (h - 1) / 2)):
        if abs(float(camera[key]) - centre) > 1e-6:
            fail(f"camera {key} {camera[key]}: expected the image centre {centre} (MuJoCo's camera is a field of view)")
    if abs(float(camera["fx"]) - float(camera["fy"])) > 1e-6:
        fail(f"camera fx {camera['fx']}, fy {camera['fy']}: expected square pixels")
    world_from_camera = np.asarray(camera["world_from_camera"], float)
    rotation = world_from_camera[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, rotation.flatten())
    c = spec.worldbody.add_camera(name=name, pos=world_from_camera[:3, 3], quat=quat)
    c.fovy = float(np.degrees(2 * np.arctan((h / 2) / float(camera["fy"]))))
    return w, h


def build(mujoco, ep: dict):
    urdf = ep["urdf"]
    ep.setdefault("mimic", urdf_mimics(urdf))
    spec = urdf_spec(mujoco, urdf)
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
    w, h = add_camera(mujoco, spec, ep["camera"])
    spec.visual.global_.offwidth = max(w, 640)
    spec.visual.global_.offheight = max(h, 480)
    try:
        model = spec.compile()
    except Exception as e:
        fail(f"the scene does not compile: {e}")
    return model, (w, h)


class Sim:
    """One scene: reset at the plan's first joints, then stepped frame by frame."""

    def __init__(self, mujoco, ep: dict):
        self.mj = mujoco
        model, (w, h) = build(mujoco, ep)
        self.model, self.w, self.h = model, w, h
        self.data = mujoco.MjData(model)
        try:
            self.renderer = mujoco.Renderer(model, h, w)
            self.seg = mujoco.Renderer(model, h, w)
        except Exception as e:
            fail(f"MuJoCo cannot render offscreen ({e}): set MUJOCO_GL=egl (Mesa's libEGL, Debian's libegl1 libegl-mesa0 libgl1-mesa-dri) or MUJOCO_GL=osmesa (libosmesa6)")
        self.seg.enable_segmentation_rendering()
        names = ep["joint_names"]
        self.names = names
        jid = lambda n: mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n)
        self.qadr = [model.jnt_qposadr[jid(n)] for n in names]
        jids = [jid(n) for n in names]
        limited = np.array([bool(model.jnt_limited[j]) for j in jids])
        self.lo = np.where(limited, [model.jnt_range[j][0] for j in jids], -np.inf)
        self.hi = np.where(limited, [model.jnt_range[j][1] for j in jids], np.inf)
        self.mimic = ep.get("mimic", {})
        self.madr = {j: model.jnt_qposadr[jid(j)] for j in self.mimic}
        self.objects = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f"object{i}") for i in range(len(ep["objects"]))]
        # The robot's geoms: those of bodies other than the world and the objects.
        self.robot_geoms = np.array([model.geom_bodyid[g] != 0 and model.geom_bodyid[g] not in self.objects
                                     for g in range(model.ngeom)])
        self.object_geoms = {model.body_geomadr[b]: i for i, b in enumerate(self.objects)}
        self.half_h = [(o["size_m"][2] if o["kind"] == "box" else o["height_m"]) / 2 for o in ep["objects"]]
        self.substeps = max(1, int(round(1.0 / (float(ep["fps"]) * model.opt.timestep))))
        self.table_z = float(ep["table"]["z_m"])
        self.backdrop = None
        if ep.get("backdrop_rgb"):
            raw = np.fromfile(ep["backdrop_rgb"], dtype=np.uint8)
            if raw.size != h * w * 3:
                fail(f"{ep['backdrop_rgb']}: {raw.size} bytes, expected {h} x {w} x 3 (the camera's size)")
            self.backdrop = raw.reshape(h, w, 3)
        self.frame_index = 0
        # Start at the first joints, at rest, and let the objects settle.
        first = np.asarray(ep["joints"][0], float)
        if first.shape != (len(names),):
            fail(f"joints: rows of {first.shape}, expected {len(names)} values ({', '.join(names)})")
        self.data.qpos[self.qadr] = first
        for j, (source, k, offset) in self.mimic.items():
            self.data.qpos[self.madr[j]] = k * first[names.index(source)] + offset
        self.data.ctrl[:] = first
        self.target = first
        mujoco.mj_forward(model, self.data)
        for _ in range(100):
            mujoco.mj_step(model, self.data)

    def step(self, target) -> np.ndarray:
        """One frame towards the joints `target`: the robot's touches per object."""
        mujoco, model, data = self.mj, self.model, self.data
        target = np.asarray(target, float)
        if target.shape != (len(self.names),):
            fail(f"joints: a row of {target.shape}, expected {len(self.names)} values")
        touched = np.zeros(len(self.objects), np.uint8)
        for s in range(self.substeps):
            a = (s + 1) / self.substeps
            data.ctrl[:] = (1 - a) * self.target + a * target
            mujoco.mj_step(model, data)
            for ci in range(data.ncon):
                con = data.contact[ci]
                for g, other in ((con.geom1, con.geom2), (con.geom2, con.geom1)):
                    if g in self.object_geoms and self.robot_geoms[other]:
                        touched[self.object_geoms[g]] = 1
        self.target = target
        self.frame_index += 1
        return touched

    def save(self):
        """The whole simulation state (physics, the controller's target, the frame count)."""
        mj = self.mj
        spec = int(mj.mjtState.mjSTATE_INTEGRATION)
        buf = np.zeros(mj.mj_stateSize(self.model, spec))
        mj.mj_getState(self.model, self.data, buf, spec)
        return buf, self.target.copy(), self.frame_index

    def restore(self, saved) -> None:
        mj = self.mj
        buf, target, frame_index = saved
        mj.mj_setState(self.model, self.data, buf, int(mj.mjtState.mjSTATE_INTEGRATION))
        mj.mj_forward(self.model, self.data)
        self.target, self.frame_index = target.copy(), frame_index

    def state(self):
        """(reached joints, object poses [K, 4], why it is unstable or "")."""
        data = self.data
        t = self.frame_index
        if not np.all(np.isfinite(data.qpos)):
            return None, None, f"frame {t}: the state is not finite (NaN or inf)"
        # The reached joints within their limits (the solver's soft limits
        # let a joint pass them by a hair).
        reached = np.clip(data.qpos[self.qadr], self.lo, self.hi)
        poses = np.zeros((len(self.objects), 4))
        reason = ""
        for i, b in enumerate(self.objects):
            pos = data.xpos[b]
            m = data.xmat[b].reshape(3, 3)
            poses[i] = [pos[0], pos[1], pos[2] - self.half_h[i], math.atan2(m[1, 0], m[0, 0])]
            if pos[2] < self.table_z - 0.05 and not reason:
                reason = f"frame {t}: object {i} is {self.table_z - pos[2]:.3f} m below the table top"
        return reached, poses, reason

    def render(self):
        """(RGB [H, W, 3] uint8, robot pixels [H, W] uint8)."""
        self.renderer.update_scene(self.data, camera="c")
        rgb = self.renderer.render()
        self.seg.update_scene(self.data, camera="c")
        ids = self.seg.render()
        geom = np.where(ids[..., 1] == int(self.mj.mjtObj.mjOBJ_GEOM), ids[..., 0], -1)
        robot = ((geom >= 0) & self.robot_geoms[np.clip(geom, 0, self.model.ngeom - 1)]).astype(np.uint8)
        if self.backdrop is not None:
            # The built-in world's backdrop where the ray meets nothing (the
            # skybox, its gradient, shows only through edge pixels).
            rgb = np.where((ids[..., 0] < 0)[..., None], self.backdrop, rgb)
        return rgb, robot


def import_mujoco():
    try:
        import mujoco
    except ImportError as e:
        fail(f"cannot import mujoco ({e}): run scripts/setup-mujoco-venv.sh (it makes .venv-mujoco)")
    return mujoco


def serve() -> None:
    """A session over stdin/stdout, one JSON object a line each way:
    {"cmd": "reset", "episode": EPISODE} (its `joints` holds at least the
    first row) and {"cmd": "step", "joints": [[...], ...], "render": "last"
    | "all" | "none"} answer {"frames": [{"joints", "objects", "touched",
    "rgb" and "robot" (base64 of the raw uint8 arrays, when rendered)}],
    "stable", "reason"}; a reset answers its start frame, rendered.
    {"cmd": "save", "slot": NAME} keeps the current state; {"cmd":
    "rollouts", "slot": NAME, "candidates": [ROWS, ...], "render": "last" |
    "none"} steps each candidate's rows from that state and answers its last
    frame (or {"unstable": reason}), the scene left at the saved state;
    {"cmd": "restore", "slot": NAME} goes back to it. Anything else MuJoCo
    prints goes to stderr."""
    import base64

    mujoco = import_mujoco()
    reply = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)
    sim = None
    saved = {}

    def record(q, p, touched, rendered):
        r = {"joints": q.tolist(), "objects": p.tolist(), "touched": touched.tolist()}
        if rendered:
            rgb, robot = sim.render()
            r["rgb"] = base64.b64encode(rgb.tobytes()).decode()
            r["robot"] = base64.b64encode(robot.tobytes()).decode()
        return r

    for line in sys.stdin:
        if not line.strip():
            continue
        msg = json.loads(line)
        frames, reason = [], ""
        if msg.get("cmd") == "reset":
            sim, saved = Sim(mujoco, msg["episode"]), {}
            q, p, reason = sim.state()
            if not reason:
                frames.append(record(q, p, np.zeros(len(sim.objects), np.uint8), True))
        elif msg.get("cmd") == "step" and sim is not None:
            rows = msg["joints"]
            render = msg.get("render", "last")
            for i, row in enumerate(rows):
                touched = sim.step(row)
                q, p, reason = sim.state()
                if reason:
                    break
                last = i == len(rows) - 1
                frames.append(record(q, p, touched, render == "all" or (render == "last" and last)))
        elif msg.get("cmd") == "save" and sim is not None:
            # The current state kept under a name; answers the current frame, unrendered.
            saved[msg["slot"]] = sim.save()
            q, p, reason = sim.state()
            if not reason:
                frames.append(record(q, p, np.zeros(len(sim.objects), np.uint8), False))
        elif msg.get("cmd") == "rollouts" and sim is not None:
            # From a saved state, each candidate's joint rows stepped and its
            # last frame answered (rendered as `render` says: last or none);
            # the scene is left at the saved state.
            start = saved.get(msg["slot"])
            if start is None:
                fail(f"rollouts from slot {msg['slot']!r}: nothing saved there (save first)")
            for rows in msg["candidates"]:
                sim.restore(start)
                touched = np.zeros(len(sim.objects), np.uint8)
                reason_c = ""
                for row in rows:
                    touched |= sim.step(row)
                q, p, reason_c = sim.state()
                if reason_c:
                    # An unstable candidate: its frame says so, the others go on.
                    frames.append({"unstable": reason_c})
                    continue
                frames.append(record(q, p, touched, msg.get("render", "last") == "last"))
            sim.restore(start)
        elif msg.get("cmd") == "restore" and sim is not None:
            start = saved.get(msg["slot"])
            if start is None:
                fail(f"restore slot {msg['slot']!r}: nothing saved there (save first)")
            sim.restore(start)
            q, p, reason = sim.state()
            if not reason:
                frames.append(record(q, p, np.zeros(len(sim.objects), np.uint8), False))
        elif msg.get("cmd") == "close":
            break
        else:
            fail(f"unknown or early command {msg.get('cmd')!r} (expected reset, then step, save, rollouts, restore or close)")
        reply.write(json.dumps({"frames": frames, "stable": not reason, "reason": reason,
                                "mujoco": mujoco.__version__, "substeps": sim.substeps}) + "\n")
        reply.flush()


def main() -> None:
    if sys.argv[1:] != ["--serve"]:
        fail("usage: mujoco_world.py --serve (a session over stdin and stdout)")
    serve()


if __name__ == "__main__":
    main()
