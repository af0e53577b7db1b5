"""``bw.evaluate_policies``: policies as Python functions, evaluated by
world-model rollouts beside the scripted and served ones, as
``bridgev2w eval-policy-rollout`` (docs/guide/planning.md)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Mapping, Optional, Sequence

import numpy as np

from . import _core, _float, _int, _path


@dataclass(frozen=True)
class PolicyEvaluation:
    """Success rates per policy in the world model and in the synthetic world."""

    #: Policy names, in order: scripted, served, then the functions.
    policies: list
    #: World-model success rate per policy.
    predicted: list
    #: Synthetic-world success rate per policy.
    real: list
    #: Mean maximum rank violation of the predicted rates (lower is better).
    mmrv: float
    #: Pearson r of the predicted against the real rates.
    pearson: float
    #: Mean world-model goal progress per policy (None with a label judge).
    progress: Optional[list] = None
    #: ``(name, error)`` of each policy whose evaluation stopped (a function
    #: that raised, with its traceback and step; a server that failed).
    failed: list = field(default_factory=list)
    #: World-model minus synthetic-world success rate per policy.
    overestimate: list = field(default_factory=list)
    #: The calibrated judge (``calibrate_judge``): ``floor``, ``ratio``,
    #: ``episodes``, ``quantile``, ``expert_ratios``; None for the fixed one.
    calibration: Optional[dict] = None
    #: The table ``bridgev2w eval-policy-rollout`` prints.
    markdown: str = ""


def _wrap(name: str, fn: Callable):
    """The callable the core calls: numpy in, rows of 7 floats out."""

    def call(image: bytes, height: int, width: int, joints, ee, step: int):
        obs = {
            "image": np.frombuffer(image, dtype=np.uint8).reshape(height, width, 3),
            "joints": np.asarray(joints, dtype=np.float64),
            "ee": np.asarray(ee, dtype=np.float64),
            "step": step,
        }
        out = np.asarray(fn(obs))
        if out.dtype.kind not in "fiu":
            raise ValueError(f"{name} returned dtype {out.dtype}: expected numbers")
        out = out.astype(np.float64)
        if out.ndim == 1:
            out = out[None]
        if out.ndim != 2 or out.shape[1] != 7 or out.shape[0] == 0:
            raise ValueError(
                f"{name} returned shape {out.shape}: expected [steps, 7] "
                "([x, y, z, roll, pitch, yaw, gripper] per step)")
        bad = np.argwhere(~np.isfinite(out))
        if len(bad):
            r, c = bad[0]
            raise ValueError(f"{name} returned {out[r, c]} at row {r}, column {c}: expected finite numbers")
        return out.tolist()

    return call


def evaluate_policies(policies: Mapping[str, Callable], *, task: str = "pick_place", trials: int = 10,
                      model: str = "perfect", weights=None, offsets_mm: Sequence[float] = (),
                      served: Sequence[str] = (), served_config=None, episode_frames: int = 25,
                      chunk: int = 8, ratio: float = 0.5, calibrate_judge: int = 0,
                      calibration_quantile: float = 0.8, split: str = "test",
                      seed: int = 0) -> PolicyEvaluation:
    """Evaluates each function of ``policies`` (name -> function) by
    rollouts in the world model ``model`` (``"perfect"``, ``"random"`` or a
    model folder with ``weights``) and in the synthetic world, beside the
    scripted policies of ``offsets_mm`` and the ``served`` ones
    (``"[NAME=]ws://HOST:PORT"``, mapped by ``served_config``), as
    ``bridgev2w eval-policy-rollout``.

    A function gets a dict ``{"image": uint8 [H, W, 3], "joints": float64
    [dof], "ee": float64 [x, y, z, roll, pitch, yaw, gripper], "step": int}``
    (the last frame, the model's prediction in the model) and returns the
    next actions, ``[steps, 7]`` absolute end-effector poses and gripper
    closure in the robot's base frame. A function that raises, or returns
    another shape or non-finite values, stops its own evaluation: it is
    listed in ``failed`` with the traceback and the step, and the other
    policies' results are kept.

    ``calibrate_judge=N`` calibrates the goal-distance judge on the model's
    own rollouts of the expert's actions in N train-split episodes (their
    ``calibration_quantile`` of ``d_last / d_start`` is a floor ``f``;
    success is ``d_last / d_start <= f + ratio (1 - f)``), as
    ``eval-policy-rollout --calibrate-judge``; ``calibration`` then holds
    the floor and the ratio."""
    if not isinstance(policies, Mapping):
        raise ValueError(f"policies: expected a dict of name -> function, got {type(policies).__name__}")
    for name, fn in policies.items():
        if not isinstance(name, str) or not name:
            raise ValueError(f"policies: expected non-empty string names, got {name!r}")
        if not callable(fn):
            raise ValueError(f"policies[{name!r}]: expected a function, got {type(fn).__name__}")
    wrapped = [(name, _wrap(name, fn)) for name, fn in policies.items()]
    d = _core.evaluate_policies(
        wrapped, str(task), _int("trials", trials, 1), str(model), _path("weights", weights, optional=True),
        [_float(f"offsets_mm[{i}]", v) for i, v in enumerate(offsets_mm)], [str(s) for s in served],
        _path("served_config", served_config, optional=True), _int("episode_frames", episode_frames, 2),
        _int("chunk", chunk, 1), _float("ratio", ratio), _int("calibrate_judge", calibrate_judge, 0),
        _float("calibration_quantile", calibration_quantile), str(split), _int("seed", seed, 0))
    return PolicyEvaluation(**d)
