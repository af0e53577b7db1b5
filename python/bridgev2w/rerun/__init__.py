"""Rerun recordings (``.rrd``) of a robot's masks, of a prediction, and of a
dataset episode, for the Rerun viewer (``rerun OUT.rrd``); docs/guide/rerun.md.

    import bridgev2w.rerun as bwr
    bwr.record_masks("masks.rrd", bw.Robot("franka"), camera, actions=a)
    bwr.record_prediction("prediction.rrd", video, masks=labels, truth=gt)
    bwr.record_episode("episode.rrd", "data", 0)

or from a shell, ``python -m bridgev2w.rerun masks|predict|view ...``
(``--help`` on each). Everything is logged on one sequence timeline,
``frame``:

- ``world/robot/<link>``: each link's visual mesh (``Mesh3D``, static, in
  the link frame, in the link's label colour) posed per frame by a
  ``Transform3D`` (``world_from_link``; "world" is the robot's base frame);
- ``world/camera``: the camera's pose (``Transform3D``, static) and under it
  ``world/camera/image`` its ``Pinhole`` (OpenCV axes) with the image
  (``.../rgb``) and the link masks (``.../masks``, a ``SegmentationImage``
  whose classes the ``AnnotationContext`` at the root names by link);
- ``video/predicted``, ``video/true``, ``video/masks``: a prediction, the
  true video and the masks, shown side by side by the recording's blueprint;
- ``joints/<joint>`` and ``actions/<value>``: time series (``Scalars``).

A recording is written to ``OUT.tmp-PID`` and renamed to ``OUT`` when
complete; an existing ``OUT`` is kept unless ``overwrite``. ``rerun``
(PyPI ``rerun-sdk``, which ``./run setup`` installs into the project venv)
is imported when a recording is written, not with this module.
"""

from __future__ import annotations

import contextlib
import json
import os
from typing import NamedTuple, Optional, Union

import numpy as np

from .. import Camera, Robot, _array, _float_array, _int, _path, builtin_robots, read_episode, read_trajectory, \
    render_masks

#: The one timeline of every recording: the frame index.
TIMELINE = "frame"
#: Names of the values of one arm's end-effector action.
ACTION_NAMES = ("x", "y", "z", "roll", "pitch", "yaw", "gripper")


def _rerun():
    """The ``rerun`` module, or an ImportError saying where it comes from."""
    try:
        import rerun
        import rerun.blueprint  # noqa: F401
    except ImportError as e:
        raise ImportError(
            f"bridgev2w.rerun needs the Rerun SDK (PyPI rerun-sdk==0.41.0): {e}. ./run setup installs it "
            "into the project venv .venv (scripts/requirements-lock.txt); elsewhere: pip install "
            "rerun-sdk==0.41.0") from None
    return rerun


class Recording(NamedTuple):
    """What a ``record_*`` function wrote."""

    out: str
    #: Frames on the ``frame`` timeline.
    frames: int
    #: The entity paths logged, sorted.
    entities: list


def _out_path(out, overwrite):
    out = _path("out", out)
    if not out.endswith(".rrd"):
        raise ValueError(f"out: {out!r}, expected a file name ending in .rrd")
    if os.path.isdir(out):
        raise FileExistsError(f"{out}: is a folder; expected a .rrd file name")
    if os.path.exists(out) and not overwrite:
        raise FileExistsError(f"{out}: already exists; choose another out or overwrite it "
                              "(overwrite=True, --overwrite)")
    parent = os.path.dirname(os.path.abspath(out))
    if not os.path.isdir(parent):
        raise FileNotFoundError(f"{parent}: no such folder for out {out}")
    return out


class _Writer:
    """A recording stream saved to ``OUT.tmp-PID``: ``log``/``columns`` add to
    it, :meth:`commit` renames it to ``OUT``; the entities are remembered."""

    def __init__(self, rr, out, blueprint):
        self.rr, self.out = rr, out
        self.tmp = f"{out}.tmp-{os.getpid()}"
        self.entities = set()
        self.rec = rr.RecordingStream("bridgev2w")
        # One timeline, the frame index: no wall-clock log_time.
        rr.set_log_time_enabled(False, recording=self.rec)
        self.rec.save(self.tmp, default_blueprint=blueprint)

    def log(self, path, *archetypes, static=False):
        self.entities.add(path)
        self.rec.log(path, *archetypes, static=static)

    def columns(self, path, columns, frames):
        """Logs ``columns`` (an archetype's ``.columns(...)``) at frames 0..frames-1."""
        self.entities.add(path)
        self.rec.send_columns(path, indexes=[self.rr.TimeColumn(TIMELINE, sequence=np.arange(frames))],
                              columns=columns)

    def frame(self, t):
        self.rec.set_time(TIMELINE, sequence=int(t))

    def close(self):
        self.rec.flush()
        self.rec.disconnect()

    def commit(self, frames, overwrite):
        """Renames the finished file to ``OUT`` (a hard link when ``OUT``
        must not exist: one that appeared meanwhile is not replaced)."""
        self.close()
        if overwrite:
            os.replace(self.tmp, self.out)
        else:
            try:
                os.link(self.tmp, self.out)
            except FileExistsError:
                raise FileExistsError(f"{self.out}: already exists (written meanwhile); choose another out or "
                                      "overwrite it (overwrite=True, --overwrite)") from None
            os.remove(self.tmp)
        return Recording(self.out, int(frames), sorted(self.entities))


@contextlib.contextmanager
def _writing(out, blueprint):
    """A :class:`_Writer` for ``out``; the temporary file goes if anything fails."""
    rr = _rerun()
    w = _Writer(rr, out, blueprint(rr.blueprint) if callable(blueprint) else blueprint)
    try:
        yield w
    except BaseException:
        with contextlib.suppress(Exception):
            w.close()
        with contextlib.suppress(OSError):
            os.remove(w.tmp)
        raise


def _entity(name):
    """A link or joint name as one entity-path part."""
    return _rerun().escape_entity_path_part(name)


def _annotations(w, robot: Optional[Robot]):
    """The classes of the segmentation images, at the root: 0, the
    background, transparent; each link's label, name and colour (``robot``),
    or 1 = "robot" for binary masks."""
    rr = w.rr
    info = [rr.AnnotationInfo(id=0, label="background", color=(0, 0, 0, 0))]  # transparent
    if robot is None:
        info.append(rr.AnnotationInfo(id=1, label="robot", color=(255, 80, 40)))
    else:
        info += [rr.AnnotationInfo(id=m.label, label=m.name, color=m.color) for m in robot.link_meshes()]
    w.log("/", rr.AnnotationContext([rr.ClassDescription(info=i) for i in info]), static=True)


def _vertex_normals(vertices, triangles):
    """Area-weighted vertex normals (for shading; zero for unused vertices)."""
    v = vertices.astype(np.float64)
    tri = triangles.astype(np.int64)
    face = np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, tri[:, k], face)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return (n / np.where(length > 0, length, 1.0)).astype(np.float32)


def _log_robot(w, robot: Robot, joints: np.ndarray, *, root: str = "world/robot"):
    """The robot's link meshes (static) posed by forward kinematics at every
    frame of ``joints`` ``[T, dof]``: one ``Mesh3D`` per link, its
    ``Transform3D`` per frame."""
    rr = w.rr
    poses = robot.link_poses(joints)
    for i, m in enumerate(robot.link_meshes()):
        path = f"{root}/{_entity(m.name)}"
        w.log(path, rr.Mesh3D(vertex_positions=m.vertices, triangle_indices=m.triangles,
                              vertex_normals=_vertex_normals(m.vertices, m.triangles), albedo_factor=m.color),
              static=True)
        w.columns(path, rr.Transform3D.columns(translation=poses[:, i, :3, 3], mat3x3=poses[:, i, :3, :3]),
                  len(joints))


def _log_camera(w, camera: Camera, *, root: str = "world/camera"):
    """The camera's pose (``root``) and pinhole (``root/image``), static. The
    principal point moves by half a pixel: Rerun puts pixel centres at
    ``+0.5``, the project's cameras at integers. The pinhole has no
    distortion: a distorted camera's image is shown as recorded."""
    rr = w.rr
    pose = camera.world_from_camera
    w.log(root, rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]), static=True)
    K = camera.K.copy()
    K[0, 2] += 0.5
    K[1, 2] += 0.5
    w.log(f"{root}/image", rr.Pinhole(image_from_camera=K, resolution=list(camera.size),
                                      camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.15),
          static=True)


def _log_images(w, path, frames, *, segmentation=False):
    """``frames`` (uint8 ``[T, H, W, 3]``, or labels ``[T, H, W]`` with
    ``segmentation``) as one image per frame at ``path``."""
    rr = w.rr
    for t, f in enumerate(frames):
        w.frame(t)
        w.log(path, rr.SegmentationImage(f) if segmentation else rr.Image(f))


def _log_series(w, root, values, names):
    """``values`` ``[T, n]`` as ``n`` scalar series ``root/<name>``."""
    for j, name in enumerate(names):
        w.columns(f"{root}/{_entity(name)}", w.rr.Scalars.columns(scalars=values[:, j]), len(values))


def action_names(dim: int) -> list[str]:
    """Names of the values of ``dim``-wide end-effector actions: ``x`` ..
    ``gripper`` for one arm, ``arm0/x`` .. for several (7 per arm)."""
    if dim % 7:
        return [f"a{i}" for i in range(dim)]
    if dim == 7:
        return list(ACTION_NAMES)
    return [f"arm{i // 7}/{ACTION_NAMES[i % 7]}" for i in range(dim)]


def _eye(robot: Robot, q0, camera: Optional[Camera]):
    """Where the 3D view looks from: ahead, to the right of and above the
    robot at ``q0`` (and the camera), far enough to see them whole."""
    points = [m.vertices @ pose[:3, :3].T + pose[:3, 3] for m, pose in zip(robot.link_meshes(),
                                                                             robot.link_poses(q0))]
    if camera is not None:
        points.append(camera.world_from_camera[None, :3, 3])
    points = np.concatenate(points)
    lo, hi = points.min(axis=0), points.max(axis=0)
    center, radius = (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 0.1)
    direction = np.array([1.0, -1.25, 0.8]) / np.linalg.norm([1.0, -1.25, 0.8])
    return (center + 1.9 * radius * direction).tolist(), center.tolist()


def _world_blueprint(rrb, eye, *, rgb=True, actions=True):
    """3D world | camera image over the time series."""
    right = [rrb.Spatial2DView(origin="world/camera/image", name="camera" if rgb else "masks"),
             rrb.TimeSeriesView(origin="joints", name="joints")]
    if actions:
        right.append(rrb.TimeSeriesView(origin="actions", name="actions"))
    world = rrb.Spatial3DView(origin="world", name="robot",
                              eye_controls=rrb.EyeControls3D(position=eye[0], look_target=eye[1], eye_up=(0, 0, 1)))
    return rrb.Blueprint(rrb.Horizontal(world, rrb.Vertical(*right), column_shares=[3, 2]), collapse_panels=True)


def _robot(robot, mesh_paths=(), ee_links=(), gripper_joints=()) -> Robot:
    """A :class:`Robot`, a built-in name or a URDF path."""
    if isinstance(robot, Robot):
        return robot
    if isinstance(robot, (str, os.PathLike)):
        name = os.fspath(robot)
        if name in builtin_robots().replace(",", " ").split():
            return Robot(name)
        return Robot.from_urdf(name, mesh_paths=mesh_paths, ee_links=ee_links, gripper_joints=gripper_joints)
    raise ValueError(f"robot: expected a bridgev2w.Robot, a built-in name ({builtin_robots()}) or a URDF path, "
                     f"got {robot!r}")


def record_masks(out, robot: Union[Robot, str], camera: Union[Camera, str], *, joints=None, actions=None,
                 allow_residual: bool = False, overwrite: bool = False) -> Recording:
    """A recording of what ``bridgev2w masks`` renders: the robot's links
    posed per frame, the camera and its per-link masks (the segmentation
    image), the joints and the actions as time series. ``robot``: a
    :class:`bridgev2w.Robot`, a built-in name or a URDF path; ``camera``: a
    :class:`bridgev2w.Camera` or its JSON file; ``joints`` ``[T, dof]`` or
    end-effector ``actions`` ``[T, action_dim]`` (solved by IK first; arrays
    or files as ``bridgev2w masks --joints/--actions`` read them)."""
    out = _out_path(out, overwrite)
    robot = _robot(robot)
    if not isinstance(camera, Camera):
        camera = Camera.from_json(_path("camera", camera))
    if (joints is None) == (actions is None):
        raise ValueError("record_masks: give exactly one of joints= and actions=")
    source = actions if actions is not None else joints
    try:
        if actions is not None:
            a = read_trajectory(actions) if isinstance(actions, (str, os.PathLike)) else actions
            a = _float_array("actions", a, 2, robot.action_dim)
            q, _ = robot.solve_ik(a, allow_residual=allow_residual)
        else:
            q = read_trajectory(joints) if isinstance(joints, (str, os.PathLike)) else joints
            q = _float_array("joints", q, 2, len(robot.joint_names))
            a = None
        labels = render_masks(robot, camera, joints=q, labels=True)
    except ValueError as e:  # name the file the values came from
        if isinstance(source, (str, os.PathLike)) and os.fspath(source) not in str(e):
            raise ValueError(f"{os.fspath(source)}: {e}") from None
        raise
    eye = _eye(robot, q[0], camera)
    with _writing(out, lambda rrb: _world_blueprint(rrb, eye, rgb=False, actions=a is not None)) as w:
        w.log("world", w.rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        _annotations(w, robot)
        _log_robot(w, robot, q)
        _log_camera(w, camera)
        _log_images(w, "world/camera/image/masks", labels, segmentation=True)
        _log_series(w, "joints", q, robot.joint_names)
        if a is not None:
            _log_series(w, "actions", a, action_names(a.shape[1]))
        return w.commit(len(q), overwrite)


def _video(name, value, shape=None):
    """uint8 ``[T, H, W, 3]`` (of ``shape`` when given)."""
    v = _array(name, value)
    if v.dtype != np.uint8 or v.ndim != 4 or v.shape[-1] != 3 or (shape is not None and v.shape != shape):
        want = f"[{', '.join(map(str, shape))}]" if shape is not None else "[T, H, W, 3]"
        raise ValueError(f"{name}: expected uint8 {want}, got {v.dtype} {tuple(v.shape)}")
    return v


def _segmentation(name, value, shape):
    """Masks ``[T, H, W]`` as segmentation classes and whether they are link
    labels: uint16 labels as they are, binary uint8/bool masks (0/1 or
    0/255) as 1 = robot."""
    m = _array(name, value)
    if m.shape != shape:
        raise ValueError(f"{name}: expected [{', '.join(map(str, shape))}] (the video's frames), "
                         f"got shape {tuple(m.shape)}")
    if m.dtype == np.uint16:
        return m, True
    if m.dtype.kind not in "bu":
        raise ValueError(f"{name}: expected uint8 or bool masks or uint16 link labels, got dtype {m.dtype}")
    return (m != 0).astype(np.uint16), False


def record_prediction(out, video, *, masks, truth=None, first_frame=None, robot: Optional[Robot] = None,
                      overwrite: bool = False) -> Recording:
    """A recording of a prediction: ``video`` (uint8 ``[T, H, W, 3]``, as
    :meth:`bridgev2w.WorldModel.predict` or ``bridgev2w predict`` give it) and
    the true video ``truth`` (same shape, optional) side by side with the
    ``masks`` (``[T, H, W]``: binary, or the link labels of
    ``render_masks(..., labels=True)`` named by ``robot``'s links), and the
    ``first_frame`` it started from (optional, static)."""
    out = _out_path(out, overwrite)
    v = _video("video", video)
    t, h, w_ = v.shape[:3]
    segmentation, labelled = _segmentation("masks", masks, (t, h, w_))
    gt = None if truth is None else _video("truth", truth, v.shape)
    first = None if first_frame is None else _video("first_frame", _array("first_frame", first_frame)[None],
                                                   (1, h, w_, 3))[0]
    robot = None if robot is None else _robot(robot)

    def blueprint(rrb):
        views = [rrb.Spatial2DView(origin="video/predicted", name="predicted")]
        if gt is not None:
            views.append(rrb.Spatial2DView(origin="video/true", name="true"))
        views.append(rrb.Spatial2DView(origin="video/masks", name="masks"))
        return rrb.Blueprint(rrb.Horizontal(*views), collapse_panels=True)

    with _writing(out, blueprint) as w:
        if not labelled or robot is not None:  # link labels without a robot: Rerun's own colours
            _annotations(w, robot if labelled else None)
        if first is not None:
            w.log("video/first_frame", w.rr.Image(first), static=True)
        _log_images(w, "video/predicted", v)
        if gt is not None:
            _log_images(w, "video/true", gt)
        _log_images(w, "video/masks", segmentation, segmentation=True)
        return w.commit(t, overwrite)


def _dataset_robot(root):
    """The built-in robot a dataset names in ``meta/info.json`` (``robot_type``), or None."""
    try:
        with open(os.path.join(root, "meta", "info.json")) as f:
            name = json.load(f).get("robot_type")
    except (OSError, ValueError, AttributeError):
        return None
    return name if isinstance(name, str) and name in builtin_robots().replace(",", " ").split() else None


def record_episode(out, dataset, episode: int = 0, *, robot: Union[Robot, str, None] = None,
                   key: Optional[str] = None, overwrite: bool = False) -> Recording:
    """A recording of episode ``episode`` of a converted or synthetic dataset
    (read with :func:`bridgev2w.read_episode`): the robot's links posed by
    the recorded joints (``observation.state``), the calibrated camera with
    video ``key`` (default the first) and the per-link masks rendered from
    the joints, the joints and the actions as time series. ``robot``
    defaults to the dataset's ``robot_type`` when that is a built-in robot.
    An episode without a camera gets its video and stored masks under
    ``video/`` instead."""
    out = _out_path(out, overwrite)
    dataset = _path("dataset", dataset)
    ep = read_episode(dataset, _int("episode", episode, 0), key=key)
    if robot is None:
        robot = _dataset_robot(dataset)
        if robot is None:
            raise ValueError(f"robot: {dataset}/meta/info.json names no built-in robot (robot_type); "
                             f"give robot= (--robot) a built-in name ({builtin_robots()}) or a URDF path")
    robot = _robot(robot)
    q = ep.states.astype(np.float64)
    dof = len(robot.joint_names)
    if q.shape[1] != dof:
        raise ValueError(f"{dataset}: episode {episode}'s observation.state has {q.shape[1]} values per frame "
                         f"but robot {robot.name!r} has {dof} joints ({', '.join(robot.joint_names)}); "
                         "give the dataset's robot (robot=, --robot)")
    t, h, w_ = ep.frames.shape[:3]
    camera = ep.camera
    if camera is not None and camera.size != (w_, h):
        camera = camera.rescaled(w_, h)
    labels = render_masks(robot, camera, joints=q, labels=True) if camera is not None else None
    a = ep.actions.astype(np.float64)

    eye = _eye(robot, q[0], camera)

    def blueprint(rrb):
        if camera is not None:
            return _world_blueprint(rrb, eye, rgb=True, actions=True)
        return rrb.Blueprint(rrb.Horizontal(rrb.Spatial3DView(origin="world", name="robot"),
                                            rrb.Spatial2DView(origin="video", name="camera"),
                                            rrb.Vertical(rrb.TimeSeriesView(origin="joints"),
                                                         rrb.TimeSeriesView(origin="actions"))),
                             collapse_panels=True)

    with _writing(out, blueprint) as w:
        w.log("world", w.rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        _annotations(w, robot if camera is not None else None)
        _log_robot(w, robot, q)
        if camera is not None:
            _log_camera(w, camera)
            _log_images(w, "world/camera/image/rgb", ep.frames)
            _log_images(w, "world/camera/image/masks", labels, segmentation=True)
        else:
            _log_images(w, "video/rgb", ep.frames)
            if ep.masks is not None:
                _log_images(w, "video/masks", ep.masks.astype(np.uint16), segmentation=True)
        _log_series(w, "joints", q, robot.joint_names)
        _log_series(w, "actions", a, action_names(a.shape[1]))
        return w.commit(t, overwrite)
