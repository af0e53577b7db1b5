"""The W&B export of a training run (bridgev2w.wandb_export), in W&B's
offline mode: a 2-step `bridgev2w train` of the tiny model writes its
TensorBoard events; the export replays them into an offline W&B run, whose
records (W&B's LevelDB-log file of protocol buffers) are read back here and
compared with the run's metrics.jsonl. Run by crates/cli/tests/python_package.rs
(BRIDGEV2W_BIN as in test_bridgev2w.py).
"""

import collections
import json
import os
import pathlib
import subprocess
import sys

import pytest

import bridgev2w.wandb_export as wx

BIN = os.environ["BRIDGEV2W_BIN"]

TRAIN_TOML = """
[model]
backbone = "random:tiny"
lora_rank = 4
lora_alpha = 4.0
controlnet_layers = 1
[data]
dataset = "{data}"
[train]
max_steps = 2
checkpoint_every = 1
preview_steps = 2
warmup_steps = 1
lr = 1e-4
"""

BLOCK = 32768  # LevelDB log blocks


def wandb_records(path):
    """The records of a `.wandb` file: a 7-byte header (":W&B", magic, version),
    then LevelDB log blocks of 32 KiB holding chunks (crc32c, length u16, type
    1 full / 2 first / 3 middle / 4 last) of serialized `Record` messages."""
    from wandb.proto import wandb_internal_pb2 as pb

    data = pathlib.Path(path).read_bytes()
    assert data[:4] == b":W&B", f"{path}: not a W&B log"
    pos, pending, out = 7, b"", []
    while pos + 7 <= len(data):
        left = BLOCK - pos % BLOCK
        if left < 7:
            pos += left
            continue
        n = int.from_bytes(data[pos + 4:pos + 6], "little")
        kind = data[pos + 6]
        if kind == 0:  # zero padding to the block's end
            pos += left
            continue
        chunk = data[pos + 7:pos + 7 + n]
        pos += 7 + n
        if kind in (1, 2):
            pending = chunk
        else:
            pending += chunk
        if kind in (1, 4):
            r = pb.Record()
            r.ParseFromString(pending)
            out.append(r)
    return out


def history(records):
    """`[{key: value}]` of the history records, keys joined with '/'."""
    rows = []
    for r in records:
        if r.WhichOneof("record_type") == "history":
            rows.append({(i.key or "/".join(i.nested_key)): json.loads(i.value_json) for i in r.history.item})
    return rows


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("wandb-export", numbered=True)
    data, run = d / "data", d / "run"
    subprocess.run([BIN, "synth", "--out", str(data), "--episodes-per-split", "2", "--frames", "9",
                    "--width", "96", "--height", "64"], check=True, capture_output=True)
    cfg = d / "train.toml"
    cfg.write_text(TRAIN_TOML.format(data=data))
    subprocess.run([BIN, "train", str(cfg), "--quiet", "--out", str(run)], check=True, capture_output=True)
    return run


def test_offline_export_replays_every_metric_and_preview(run_dir):
    assert not wx._wandb_service_running()
    local = wx.export_run(run_dir, project="bridgev2w-test", mode="offline", dir=run_dir.parent / "wb")
    # The export started W&B's service, so it stopped it: the `.wandb` file
    # below is complete, however slowly the service wrote it.
    assert not wx._wandb_service_running()
    files = list(local.glob("run-*.wandb"))
    assert len(files) == 1, f"{local}: {list(local.iterdir())}"
    records = wandb_records(files[0])
    rows = history(records)
    metrics = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    # What was read from TensorBoard, then what W&B wrote (told apart on failure).
    events = wx.read_events(run_dir)
    assert sorted(events.scalars) == [m["step"] for m in metrics], (events.steps, metrics)
    kinds = collections.Counter(r.WhichOneof("record_type") for r in records)
    scalar_rows = [r for r in rows if "train/loss" in r]
    assert [r["_step"] for r in scalar_rows] == [m["step"] for m in metrics], (kinds, rows)
    for row, m in zip(scalar_rows, metrics):
        for key in ("loss", "diffusion", "dynamics", "lr", "grad_norm", "secs"):
            # float32 in the TensorBoard log
            assert row[f"train/{key}"] == pytest.approx(m[key], rel=1e-6, abs=1e-12), (key, row, m)
    # A preview image at every checkpoint (checkpoint_every = 1), logged at
    # the checkpoint's step count: after steps 0 and 1, steps 1 and 2.
    tag = "preview/truth_over_prediction"
    images = {r["_step"]: {k[len(tag) + 1:]: v for k, v in r.items() if k.startswith(tag + "/")} for r in rows}
    images = {step: img for step, img in images.items() if img}
    assert sorted(images) == [1, 2], rows
    for img in images.values():
        assert img["_type"] == "image-file" and img["format"] == "png", img
        assert (local / "files" / img["path"]).is_file(), img
        assert img["width"] > 0 and img["height"] > 0, img
    # The run's config.toml is the W&B config.
    runs = [r.run for r in wandb_records(files[0]) if r.WhichOneof("record_type") == "run"]
    assert len(runs) == 1 and runs[0].project == "bridgev2w-test" and runs[0].display_name == "run", runs
    keys = {u.key for u in runs[0].config.update}
    assert {"model", "data", "train"} <= keys, keys


def test_a_callers_own_wandb_run_keeps_running_through_an_export(run_dir, tmp_path):
    import wandb

    (tmp_path / "mine").mkdir()
    mine = wandb.init(project="mine", mode="offline", dir=str(tmp_path / "mine"), reinit="create_new")
    try:
        assert wx._wandb_service_running()
        local = wx.export_run(run_dir, project="bridgev2w-test", mode="offline", dir=tmp_path / "wb")
        assert wx._wandb_service_running()
        mine.log({"after_export": 1.5}, step=0)
    finally:
        mine.finish()
        wandb.teardown()
    exported = history(wandb_records(next(local.glob("run-*.wandb"))))
    assert [r["_step"] for r in exported if "train/loss" in r] == [0, 1], exported
    own = history(wandb_records(next(pathlib.Path(mine.dir).parent.glob("run-*.wandb"))))
    assert [r.get("after_export") for r in own] == [1.5], own


def test_the_command_line_and_its_errors(run_dir, tmp_path):
    py = sys.executable
    out = subprocess.run([py, "-m", "bridgev2w.wandb_export", str(run_dir), "--offline", "--dir", str(tmp_path)],
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "exported" in out.stdout and "wandb sync" in out.stdout, out.stdout
    assert list((tmp_path / "wandb").glob("offline-run-*/run-*.wandb"))
    missing = subprocess.run([py, "-m", "bridgev2w.wandb_export", str(tmp_path / "nope"), "--offline"],
                             capture_output=True, text=True)
    assert missing.returncode == 2 and "no such run folder" in missing.stderr, missing.stderr
    with pytest.raises(ValueError, match="no TensorBoard event files"):
        wx.export_run(tmp_path, mode="offline")
    with pytest.raises(ValueError, match="mode: 'later'"):
        wx.export_run(run_dir, mode="later")
