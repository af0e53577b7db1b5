"""The synthetic tabletop dataset of ``bridgev2w synth``, from Python.

    import bridgev2w as bw
    summary = bw.synth.generate("data", episodes_per_split=(4, 1, 1, 1), frames=17,
                                tasks=("reach", "push", "pick_place", "play"))

writes the same bytes as ``bridgev2w synth --out data --episodes-per-split
4,1,1,1 --frames 17 --tasks reach,push,pick_place,play`` (LeRobot v3.0: videos,
states, actions, per-episode cameras and masks; see docs/guide/data.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence, Union

from . import _core
from . import _float, _int, _path

#: The tasks the generator scripts.
TASKS = ("reach", "push", "pick_place", "play")
#: The splits, in the order of ``episodes_per_split``.
SPLITS = ("train", "test", "unseen_camera", "unseen_scene")


@dataclass(frozen=True)
class SynthSummary:
    """What :func:`generate` wrote."""

    out: str
    episodes: int
    total_frames: int
    episodes_per_split: dict = field(default_factory=dict)
    episodes_per_task: dict = field(default_factory=dict)
    #: Object-moving contacts (push and grasp frames) over all episodes.
    contact_events: int = 0
    #: Perturbed demonstrations in the train split (``perturbed_fraction``).
    perturbed: int = 0
    #: Of those, the ones that fail the task.
    perturbed_failed: int = 0


def generate(out, *, robot: str = "franka", episodes_per_split: Union[int, Sequence[int]] = (8, 2, 2, 2),
             frames: int = 25, width: int = 96, height: int = 64, fps: int = 10, seed: int = 0,
             tasks: Union[str, Sequence[str]] = ("reach", "push", "pick_place"),
             perturbed_fraction: float = 0.0, perturb_mm: float = 30.0) -> SynthSummary:
    """Writes a synthetic tabletop dataset (LeRobot v3.0) to ``out``, which
    must not exist (written to a temporary folder beside it, then renamed), and returns its
    :class:`SynthSummary`. The arguments and defaults are ``bridgev2w
    synth``'s: a built-in ``robot``; ``episodes_per_split``, one number for
    all of :data:`SPLITS` or four; ``frames`` per episode (2..10000);
    ``width`` and ``height`` even, 16..4096 pixels; ``fps``; ``seed`` (same
    seed, same bytes); ``tasks`` from :data:`TASKS`, assigned round-robin (a
    list or a comma-separated string; repeat one to weigh it);
    ``perturbed_fraction`` of the train split's goal-task episodes get one
    normal offset of ``perturb_mm`` per axis on every action's position, so
    that some fail (``--perturbed-fraction``, ``--perturb-mm``). Episodes are
    rendered in parallel on the Rust thread pool with the GIL released.
    ``out`` existing is a ``FileExistsError``, a bad argument a
    ``ValueError`` naming it, anything else a ``bridgev2w.Error``."""
    if not isinstance(robot, str):
        raise ValueError(f"robot: expected a built-in robot's name ({_core.builtin_robots()}), got {robot!r}")
    if isinstance(episodes_per_split, (list, tuple)):
        counts = [_int(f"episodes_per_split[{i}]", n, 0, 100_000) for i, n in enumerate(episodes_per_split)]
        if len(counts) != 4:
            raise ValueError(f"episodes_per_split: expected one number or four ({', '.join(SPLITS)}), "
                             f"got {len(counts)}")
    else:
        counts = [_int("episodes_per_split", episodes_per_split, 0, 100_000)] * 4
    if isinstance(tasks, str):
        tasks = [t.strip() for t in tasks.split(",")]
    if not isinstance(tasks, (list, tuple)) or not tasks or not all(isinstance(t, str) for t in tasks):
        raise ValueError(f"tasks: expected a non-empty list of task names ({', '.join(TASKS)}), got {tasks!r}")
    for t in tasks:
        if t not in TASKS:
            raise ValueError(f"tasks: unknown task {t!r}, expected one of {', '.join(TASKS)}")
    d = _core.synth_generate(
        _path("out", out), robot, counts, _int("frames", frames, 2, 10_000),
        _int("width", width, 16, 4096, even=True), _int("height", height, 16, 4096, even=True),
        _int("fps", fps, 1, 2 ** 32 - 1), _int("seed", seed, 0, 2 ** 64 - 1), list(tasks),
        _float("perturbed_fraction", perturbed_fraction), _float("perturb_mm", perturb_mm))
    return SynthSummary(**d)
