"""``bw.convert``: raw DROID / AgiBot World episodes to a training dataset,
as ``bridgev2w convert`` (docs/guide/data.md); ``bw.read_episode``: an
episode of such a dataset (frames, states, actions, camera, masks) back."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Optional, Sequence, Union

import numpy as np

from . import Camera, Robot, _core, _float, _int, _path

_DEFAULT_ROBOT = {"droid": "franka-robotiq", "agibot": "agibot-g1", "ctrl-world": "franka-robotiq"}


@dataclass(frozen=True)
class ConvertReport:
    """What :func:`convert` did."""

    out: str
    #: Raw episodes read.
    episodes: int
    #: LeRobot episodes written (one per camera of each episode).
    views_written: int
    #: ``(item, error)`` of each episode or camera skipped with ``skip_bad``.
    skipped: list = field(default_factory=list)
    #: Camera episodes whose masks are empty in every frame (check the calibration).
    empty_mask_views: list = field(default_factory=list)
    #: Per arm, the link the written actions are poses of (the flange).
    ee_frames: list = field(default_factory=list)
    #: The whole conversion report (``out/conversion_report.json``): ``notes``
    #: lists everything done to the data beyond copying it (frames aligned,
    #: intrinsics scaled, grippers clamped, joints past their limits, ...).
    report: dict = field(default_factory=dict)


def _robot(robot, default: str) -> Robot:
    """``robot`` as a :class:`Robot`: itself, a built-in name or a URDF path
    (``default``, a built-in name, when None)."""
    if robot is None:
        return Robot(default)
    if isinstance(robot, (str, os.PathLike)):
        name = os.fspath(robot)
        return Robot(name) if name in _core.builtin_robots().replace(",", " ").split() else Robot.from_urdf(name)
    if not isinstance(robot, Robot):
        raise ValueError(f"robot: expected a bridgev2w.Robot, a built-in name or a URDF path, got {robot!r}")
    return robot


def _names(name, value):
    if value is None:
        return None
    if isinstance(value, str):
        value = [v.strip() for v in value.split(",") if v.strip()]
    if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
        raise ValueError(f"{name}: expected a list of names (or a comma-separated string), got {value!r}")
    return list(value)


def convert(src, out, *, format: str, robot: Union[Robot, str, None] = None,
            joint_names: Union[Sequence[str], str, None] = None, width: int = 96, height: int = 64,
            fps: Optional[int] = None, intrinsics=None, calibration=None, missing_calibration: str = "recorded",
            cameras: Union[Sequence[str], str, None] = None, gripper_source: str = "auto",
            gripper_range=(35.0, 120.0), split: str = "train",
            skip_bad: bool = False, limit: Optional[int] = None, camera_json=None,
            include: Union[Sequence[str], str, None] = None, split_rules: Sequence[str] = ()) -> ConvertReport:
    """Converts raw episodes under ``src`` into a LeRobot v3.0 training
    dataset at ``out`` (must not exist; written to a temporary folder beside it, then
    renamed): every camera of every episode one episode, frames resized to
    ``width`` x ``height`` (even), ``calc`` masks rendered from the recorded
    joints, as ``bridgev2w convert``. Returns a :class:`ConvertReport`.

    ``format``: ``"droid"`` (DROID raw episodes; needs ``intrinsics``, DROID's
    published ``intrinsics.json`` or a JSON file of intrinsics per camera
    serial, and takes ``calibration``, one or a list of extrinsics files
    such as DROID's ``cam2base_extrinsic_superset.json``, earlier first;
    ``missing_calibration`` ``"recorded"`` or ``"error"`` for cameras none
    calibrates; ``cameras`` by role, default ``ext1, ext2``) or ``"agibot"``
    (AgiBot World; ``cameras`` default ``head``; ``gripper_source``
    ``"auto"``, ``"action"`` or ``"state"``, ``gripper_range`` the (open,
    closed) ``state/effector/position`` readings). ``robot``: a :class:`Robot`, a built-in name
    or a URDF path (default ``franka-robotiq`` for DROID, ``agibot-g1`` for AgiBot
    World); ``joint_names`` the robot's names for the recorded joint columns.
    ``"ctrl-world"``: DROID episodes of the Ctrl-World layout
    (``annotation/<split>/<id>.json``, ``videos/<split>/<id>/{0,1,2}.mp4``),
    with ``camera_json`` a dict ``{"ext1": camera.json, "ext2": ...}`` (what
    :func:`bridgev2w.calibrate` writes), ``include`` the episodes
    (``collection/split/id``) and ``split_rules`` as ``--split-rule``
    (``"EPISODE[:ROLE]=SPLIT"``, ``-`` for not converted).
    ``fps`` defaults to 15 (DROID), 30 (AgiBot World) or 5 (ctrl-world); ``split`` is
    recorded for every episode; ``skip_bad`` records failing episodes in
    ``out/skipped.json`` and goes on; ``limit`` converts at most that many
    episodes. The GIL is released while it runs.

    A missing ``src``, ``intrinsics`` or ``calibration`` is a
    ``FileNotFoundError``, an existing ``out`` a ``FileExistsError``, a bad
    argument a ``ValueError`` naming it, an unreadable episode a
    ``bridgev2w.Error`` naming the file and field."""
    if format not in _DEFAULT_ROBOT:
        raise ValueError(f"format: {format!r}, expected 'droid', 'agibot' or 'ctrl-world'")
    if camera_json is None:
        camera_json = {}
    if not isinstance(camera_json, dict):
        raise ValueError(f"camera_json: expected a dict of role -> camera JSON path, got {camera_json!r}")
    if format != "ctrl-world" and (camera_json or include is not None or split_rules):
        raise ValueError("camera_json, include, split_rules: apply to format='ctrl-world'")
    if isinstance(split_rules, str) or not all(isinstance(r, str) for r in split_rules):
        raise ValueError(f"split_rules: expected a list of 'EPISODE[:ROLE]=SPLIT' strings, got {split_rules!r}")
    robot = _robot(robot, _DEFAULT_ROBOT[format])
    if not isinstance(gripper_range, (list, tuple)) or len(gripper_range) != 2:
        raise ValueError(f"gripper_range: expected (open, closed) readings, got {gripper_range!r}")
    grip = (_float("gripper_range[0]", gripper_range[0]), _float("gripper_range[1]", gripper_range[1]))
    if not isinstance(split, str) or not split:
        raise ValueError(f"split: expected a split name, got {split!r}")
    if calibration is None:
        calibration = []
    elif isinstance(calibration, (str, os.PathLike)):
        calibration = [calibration]
    calibration = [_path(f"calibration[{i}]", c) for i, c in enumerate(calibration)]
    d = _core.convert(
        format, _path("src", src), _path("out", out), robot._r, _names("joint_names", joint_names),
        _int("width", width, 2, 4096, even=True), _int("height", height, 2, 4096, even=True),
        None if fps is None else _int("fps", fps, 1, 2 ** 32 - 1),
        _path("intrinsics", intrinsics, optional=True), calibration, str(missing_calibration),
        _names("cameras", cameras), str(gripper_source), grip, split, bool(skip_bad),
        None if limit is None else _int("limit", limit, 1),
        [(str(r), _path(f"camera_json[{r!r}]", p)) for r, p in camera_json.items()],
        _names("include", include), list(split_rules))
    d["report"] = json.loads(d.pop("report_json"))
    return ConvertReport(**d)


@dataclass(frozen=True)
class Episode:
    """One episode of a LeRobot dataset, as :func:`read_episode` reads it."""

    #: uint8 ``[T, H, W, 3]``: the decoded video ``key``.
    frames: np.ndarray
    #: float32 ``[T, n]``: ``observation.state`` (the robot's joints in what synth and convert write).
    states: np.ndarray
    #: float32 ``[T, m]``: ``action`` (end-effector poses, 7 per arm).
    actions: np.ndarray
    #: The camera of ``key`` from ``meta/calibration/`` (None when the dataset has none).
    camera: Optional[Camera]
    #: uint8 ``[T, H, W]`` from ``masks/episode_N.npy`` (None when the dataset has none).
    masks: Optional[np.ndarray]
    tasks: list
    key: str
    split: Optional[str]


def read_episode(root, episode: int = 0, *, key: Optional[str] = None) -> Episode:
    """Episode ``episode`` of the LeRobot v3.0/v2.1 dataset at ``root`` (what
    :func:`bridgev2w.synth.generate` and :func:`convert` write, or LeRobot's
    own ``LeRobotDataset.create``): its frames of video ``key`` (default the
    first), states, actions, calibrated camera and masks, read by the same
    Rust reader ``bridgev2w train`` uses, with the GIL released. A missing
    dataset is a ``FileNotFoundError``, an unknown ``key`` a ``ValueError``,
    an unreadable file or a missing episode a ``bridgev2w.Error``."""
    d = _core.read_episode(_path("root", root), _int("episode", episode, 0), key)
    t, h, w = d["shape"]
    masks = d["masks"]
    return Episode(
        frames=np.frombuffer(d["frames"], dtype=np.uint8).reshape(t, h, w, 3),
        states=np.array(d["states"], dtype=np.float32).reshape(t, -1),
        actions=np.array(d["actions"], dtype=np.float32).reshape(t, -1),
        camera=None if d["camera"] is None else Camera(_core_camera=d["camera"]),
        masks=None if masks is None else np.frombuffer(masks, dtype=np.uint8).reshape(t, h, w),
        tasks=d["tasks"], key=d["key"], split=d["split"])
