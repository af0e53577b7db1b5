"""Weights & Biases export of a training run's TensorBoard events.

``bridgev2w train`` writes its metrics twice: ``metrics.jsonl`` and TensorBoard
event files under ``OUT/tensorboard`` (every loss term, the learning rate, the
gradient norm and the step time as ``train/<name>`` scalars, and the preview
images ``preview/truth_over_prediction`` at every checkpoint). This module
replays those events into a W&B run, one ``log`` per step, with the run's
``config.toml`` as the W&B config:

    import bridgev2w.wandb_export as wx
    path = wx.export_run("runs/proof/bridgev2w", project="bridgev2w", mode="offline")

    python -m bridgev2w.wandb_export runs/proof/bridgev2w --project bridgev2w --offline

``mode="offline"`` writes the W&B run under ``dir`` (default: the run folder)
for a later ``wandb sync``; ``mode="online"`` uploads it (needs ``wandb login``).
The events are read by TensorBoard's own ``EventAccumulator``, so a resumed run
(a new event file whose steps restart from its checkpoint) is replayed the
way TensorBoard shows it: the steps the resume repeated are kept once.
"""

from __future__ import annotations

import argparse
import io
import os
import sys
import tomllib
from pathlib import Path
from typing import NamedTuple

__all__ = ["export_run", "read_events", "RunEvents"]

MODES = ("offline", "online", "disabled")


class RunEvents(NamedTuple):
    """A run's events by step: ``scalars[step][tag]`` and ``images[step][tag]`` (PNG bytes)."""

    scalars: dict[int, dict[str, float]]
    images: dict[int, dict[str, bytes]]

    @property
    def steps(self) -> list[int]:
        return sorted(set(self.scalars) | set(self.images))


def _events_dir(run: Path) -> Path:
    if not run.is_dir():
        raise FileNotFoundError(f"{run}: no such run folder (expected the `out` of `bridgev2w train`)")
    tb = run / "tensorboard"
    files = sorted(tb.glob("events.out.tfevents.*")) if tb.is_dir() else []
    if not files:
        raise ValueError(
            f"{tb}: no TensorBoard event files (events.out.tfevents.*); "
            "expected a run written by `bridgev2w train`"
        )
    return tb


def read_events(run: str | os.PathLike) -> RunEvents:
    """Every scalar and image event of the run folder ``run``, by step."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    tb = _events_dir(Path(run))
    acc = EventAccumulator(str(tb), size_guidance={"scalars": 0, "images": 0})
    acc.Reload()
    tags = acc.Tags()
    scalars: dict[int, dict[str, float]] = {}
    images: dict[int, dict[str, bytes]] = {}
    for tag in tags.get("scalars", []):
        for e in acc.Scalars(tag):
            scalars.setdefault(int(e.step), {})[tag] = float(e.value)
    for tag in tags.get("images", []):
        for e in acc.Images(tag):
            images.setdefault(int(e.step), {})[tag] = bytes(e.encoded_image_string)
    return RunEvents(scalars, images)


def _config(run: Path) -> dict:
    path = run / "config.toml"
    if not path.is_file():
        return {}
    try:
        return tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: not a TOML config ({e})") from None


def export_run(
    run: str | os.PathLike,
    *,
    project: str = "bridgev2w",
    name: str | None = None,
    entity: str | None = None,
    mode: str = "offline",
    dir: str | os.PathLike | None = None,
    events: RunEvents | None = None,
) -> Path:
    """Replays the run folder ``run``'s TensorBoard events into one W&B run.

    Returns the W&B run's local folder (``DIR/wandb/offline-run-*`` in offline
    mode). ``name`` defaults to the run folder's name, ``dir`` to the run folder;
    ``events``: the run's events when already read (``read_events(run)``).
    The offline run's ``.wandb`` file is complete on return, except in a
    process that already runs W&B (runs of its own, ``wandb.setup()``): W&B's
    service, which writes it, is then the caller's, and the file is complete
    once that service ends (``wandb.teardown()`` or the process's exit).
    """
    if mode not in MODES:
        raise ValueError(f"mode: {mode!r}: expected one of {', '.join(MODES)}")
    run = Path(run)
    if events is None:
        events = read_events(run)
    config = _config(run)
    try:
        import wandb
    except ImportError:
        raise ImportError(
            "bridgev2w.wandb_export needs the `wandb` package (installed into .venv by `./run setup`; "
            "elsewhere `pip install wandb`)"
        ) from None
    from PIL import Image

    out = Path(dir) if dir is not None else run
    out.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("WANDB_SILENT", "true")
    owns_service = not _wandb_service_running()
    wb = wandb.init(
        project=project,
        entity=entity,
        name=name or run.resolve().name,
        dir=str(out),
        mode=mode,
        config=config,
        job_type="train",
        reinit="create_new",
    )
    try:
        for step in events.steps:
            row: dict = dict(events.scalars.get(step, {}))
            for tag, png in events.images.get(step, {}).items():
                row[tag] = wandb.Image(Image.open(io.BytesIO(png)).convert("RGB"), caption=f"step {step}")
            wb.log(row, step=step)
        local = Path(wb.dir).parent
    finally:
        wb.finish()
        # finish() returns once the run's exit record is handled, but W&B's
        # service closes the run's transaction log (the offline `.wandb`
        # file) afterwards, on its own time: on a busy machine the file can
        # still be unwritten when finish() returns. Stopping the service waits
        # for it; done only when this call started it, so that a process
        # with its own W&B runs keeps them.
        if owns_service:
            wandb.teardown()
    return local


def _wandb_service_running() -> bool:
    """Whether this process already has W&B's service (a run of its own, or
    an earlier ``wandb.setup()``); unknown (another wandb version's layout)
    counts as running, so that nothing of the caller's is stopped."""
    try:
        from wandb.sdk import wandb_setup
    except ImportError:
        return True
    if not hasattr(wandb_setup, "_singleton"):
        return True
    setup = wandb_setup._singleton
    if setup is None or getattr(setup, "_pid", os.getpid()) != os.getpid():
        return False
    return getattr(setup, "_connection", True) is not None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m bridgev2w.wandb_export",
        description="Replay a `bridgev2w train` run's TensorBoard events into Weights & Biases.",
    )
    p.add_argument("run", help="the run folder (`out` of the training config)")
    p.add_argument("--project", default="bridgev2w")
    p.add_argument("--name", help="the W&B run's name (default: the run folder's name)")
    p.add_argument("--entity", help="the W&B entity (team or user)")
    p.add_argument("--dir", help="where W&B writes its local files (default: the run folder)")
    p.add_argument("--offline", action="store_true", help="write an offline run for a later `wandb sync`")
    a = p.parse_args(argv)
    try:
        events = read_events(a.run)
        local = export_run(
            a.run, project=a.project, name=a.name, entity=a.entity,
            mode="offline" if a.offline else "online", dir=a.dir, events=events,
        )
    except (FileNotFoundError, ValueError, ImportError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"exported {len(events.steps)} step(s) of {a.run} to {local}")
    if a.offline:
        print(f"upload it with: wandb sync {local}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
