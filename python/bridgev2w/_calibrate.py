"""``bw.calibrate``: a fixed camera's calibration from the robot's own motion
in its video, as ``bridgev2w calibrate`` (docs/guide/calibrate.md)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Optional, Sequence, Union

from . import Camera, Robot, _core, _float, _int, _path
from ._data import _robot


@dataclass(frozen=True)
class Calibration:
    """What :func:`calibrate` found and wrote."""

    #: The output folder (``camera.json``, ``residuals.json``, ``overlay/``).
    out: str
    #: The camera, at the video's size.
    camera: Camera
    #: IoU of the rendered robot against the robot pixels found in the
    #: video, on the fitted episodes' held-out frames.
    held_out_iou: float
    #: The same on the frames fitted.
    fit_iou: float
    #: False when a flag was raised (a low held-out IoU, an ambiguous fit).
    reliable: bool
    #: ``(code, message)`` per flag (``low_held_out_iou``, ``ambiguous``,
    #: ``marks_disagree``).
    flags: list = field(default_factory=list)
    #: ``(name, held_out_iou, held_out_frames, fitted)`` per episode, the
    #: fitted ones first, then the checked ones.
    episodes: list = field(default_factory=list)
    #: ``(name, median_px, max_px, marks)`` per episode with hand marks:
    #: the tool point's reprojection error at the video's size.
    marks: list = field(default_factory=list)
    #: What ``bridgev2w calibrate`` prints.
    summary: str = ""


def _paths(name, value):
    if isinstance(value, (str, os.PathLike)):
        value = [value]
    if not isinstance(value, (list, tuple)):
        raise ValueError(f"{name}: expected a path or a list of paths, got {value!r}")
    return [_path(f"{name}[{i}]", v) for i, v in enumerate(value)]


def _weight(name, value) -> float:
    v = _float(name, value)
    if v < 0:
        raise ValueError(f"{name}: {value!r}, expected a finite value >= 0")
    return v


def calibrate(videos, joints, out, *, robot: Union[Robot, str, None] = None,
              check_videos: Sequence = (), check_joints: Sequence = (),
              focal_px: Optional[float] = None, fy_over_fx: float = 1.0, analysis_width: int = 320,
              max_evaluations: int = 250, walk_evaluations: int = 120, marks=None,
              static_changes: str = "score", background_weight: float = 10.0,
              appearance_weight: float = 1.0, overwrite: bool = False) -> Calibration:
    """Finds the fixed camera of ``videos`` (one MP4 or a list, one per
    episode) from the robot's joints in each (``joints``, in the same order:
    trajectory files, or DROID annotation JSONs of the Ctrl-World layout),
    checks it on ``check_videos`` / ``check_joints`` (not fitted), and writes
    ``camera.json``, ``residuals.json`` and overlay GIFs to ``out``, as
    ``bridgev2w calibrate``. ``robot`` defaults to ``franka-robotiq``;
    ``focal_px`` is a known fx at the video's size (then only the pose is
    fitted); ``fy_over_fx`` 1.0667 for DROID's 320x192 videos (stretched
    from 320x180). ``marks``: a JSON file of hand-marked tool-point pixels
    (see the calibrate guide): each marked episode's reprojection error is
    reported in ``marks``; on fitted episodes 4 or more marks start and pull
    the fit. ``walk_evaluations``: the evaluations of each re-fit of the
    search's walk along the orbit and dolly-zoom valleys (0 skips the walk,
    about half the time). ``static_changes``: ``"score"`` every found pixel,
    or ``"leave-out"`` the found pixels that keep their colour over the
    frames around them (a moved object at rest, an exposure drift) of the
    score. ``background_weight``: the weight of the background's consistency
    beside the silhouette in the full-grid refinement (0: the silhouette
    alone; see the calibrate guide); ``appearance_weight``: the weight of how
    well the rendered robot splits the frames' colours, in the middle- and
    full-grid refinements (0: left out). The GIL is released while it runs (minutes).

    Missing files are a ``FileNotFoundError``, bad arguments a ``ValueError``
    naming them, an existing ``out`` without ``overwrite`` or a video the
    calibration refuses (a moving camera, a robot that hardly moves, too few
    frames with robot pixels) a ``bridgev2w.Error`` with the measured reason.
    A camera that does not match the video well is returned with
    ``reliable`` False and its flags."""
    robot = _robot(robot, "franka-robotiq")
    d = _core.calibrate(
        robot._r, _paths("videos", videos), _paths("joints", joints), _path("out", out),
        _paths("check_videos", list(check_videos)), _paths("check_joints", list(check_joints)),
        None if focal_px is None else _float("focal_px", focal_px),
        _float("fy_over_fx", fy_over_fx), _int("analysis_width", analysis_width, 16, 4096),
        _int("max_evaluations", max_evaluations, 10, 100000),
        _int("walk_evaluations", walk_evaluations, 0, 100000),
        None if marks is None else _path("marks", marks), str(static_changes),
        _weight("background_weight", background_weight),
        _weight("appearance_weight", appearance_weight), bool(overwrite))
    d["camera"] = Camera(_core_camera=d["camera"])
    return Calibration(**d)
