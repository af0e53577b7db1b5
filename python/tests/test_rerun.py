"""Tests of bridgev2w.rerun: each of its three recordings written from
small generated inputs (a synthetic dataset, `random:tiny` and `bridgev2w
predict`) through ``python -m bridgev2w.rerun`` and the functions, reloaded
with the Rerun SDK's own reader (``rerun.chunk.RrdReader``) and checked:
entity paths, frames on the ``frame`` timeline, one mesh per link, the
logged images against their sources, the link poses against the masks; and
bad input as the expected exception. Run with pytest by
crates/cli/tests/python_package.rs after ``pip install ./python``:

  BRIDGEV2W_BIN=... BRIDGEV2W_TEST_WORK=DIR python -m pytest python/tests/test_rerun.py

The tests run in file order (later ones read what earlier ones wrote).
"""

import contextlib
import io
import json
import os
import pathlib
import subprocess
import sys
from typing import NamedTuple

import numpy as np
import pytest

import bridgev2w as bw
from bridgev2w import rerun as bwr
from bridgev2w.rerun.__main__ import main

BIN = os.environ["BRIDGEV2W_BIN"]
WORK = pathlib.Path(os.environ["BRIDGEV2W_TEST_WORK"]) / "rerun"
FRAMES = 9  # the frames of the synthetic episodes and of random:tiny's clips


def load(path):
    """A recording read back: entity path -> {"static": components,
    "temporal": components, "frames": the frame indexes of its rows}."""
    from rerun.chunk import RrdReader

    reader = RrdReader(str(path))
    assert len(reader.recordings()) == 1
    out = {}
    for c in reader.stream():
        batch = c.to_record_batch()
        e = out.setdefault(c.entity_path, {"static": set(), "temporal": set(), "frames": [], "batches": []})
        components = {n for n in batch.schema.names if ":" in n}
        if c.is_static:
            e["static"] |= components
        else:
            assert c.timeline_names == ["frame"], (c.entity_path, c.timeline_names)
            e["temporal"] |= components
            e["frames"] += batch.column("frame").to_pylist()
        e["batches"].append(batch)
    return out


def images(entity, component="Image:buffer"):
    """The images of an entity by frame, as flat uint8 arrays."""
    rows = {}
    for b in entity["batches"]:
        if component in b.schema.names:
            for t, buf in zip(b.column("frame").to_pylist(), b.column(component).to_pylist()):
                rows[t] = np.asarray(buf[0], dtype=np.uint8)
    return [rows[t] for t in sorted(rows)]


class Ran(NamedTuple):
    returncode: int
    stdout: str
    stderr: str


def run(*args, check=True, subprocess_=False):
    """``python -m bridgev2w.rerun ARGS``: its main() in this process (a new
    interpreter costs seconds of imports), or with ``subprocess_`` the real command."""
    args = [str(a) for a in args]
    if subprocess_:
        p = subprocess.run([sys.executable, "-m", "bridgev2w.rerun", *args], capture_output=True, text=True)
    else:
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main(args)
        p = Ran(code, out.getvalue(), err.getvalue())
    if check:
        assert p.returncode == 0, p.stderr
    return p


@pytest.fixture(scope="module")
def data():
    """A tiny synthetic dataset (one pick-and-place, one unseen-camera reach)
    and episode 0's camera, joints, actions, first frame and video as files."""
    WORK.mkdir(parents=True, exist_ok=True)
    root = WORK / "data"
    if not root.exists():
        bw.synth.generate(root, episodes_per_split=(1, 0, 1, 0), frames=FRAMES, tasks=("pick_place", "reach"),
                          seed=1)
        ep = bw.read_episode(root, 0)
        (WORK / "camera.json").write_text(ep.camera.to_json())
        (WORK / "joints.json").write_text(json.dumps(ep.states.tolist()))
        np.save(WORK / "actions.npy", ep.actions.astype(np.float64))
        np.save(WORK / "truth.npy", ep.frames)
        from PIL import Image

        Image.fromarray(ep.frames[0]).save(WORK / "first.png")
    return root


def check_robot(rec, robot, frames):
    """One static Mesh3D per link of the robot, posed on every frame."""
    meshes = robot.link_meshes()
    links = {p for p, e in rec.items() if p.startswith("/world/robot/")}
    assert links == {f"/world/robot/{m.name}" for m in meshes}
    assert len(links) == len(robot.link_labels()) == len(meshes)
    for p in links:
        assert {"Mesh3D:vertex_positions", "Mesh3D:triangle_indices"} <= rec[p]["static"], p
        assert "Transform3D:translation" in rec[p]["temporal"] and sorted(rec[p]["frames"]) == list(range(frames))


def test_masks_recording_holds_the_robot_camera_masks_and_joints(data):
    out = WORK / "masks.rrd"
    p = run("masks", "--robot", "franka", "--camera", WORK / "camera.json", "--joints", WORK / "joints.json",
            "--rerun", out, subprocess_=True)
    assert f"wrote {out}: {FRAMES} frames" in p.stdout
    rec = load(out)
    robot, cam = bw.Robot("franka"), bw.Camera.from_json(WORK / "camera.json")
    check_robot(rec, robot, FRAMES)
    assert "Pinhole:image_from_camera" in rec["/world/camera/image"]["static"]
    assert "Transform3D:translation" in rec["/world/camera"]["static"]
    masks = rec["/world/camera/image/masks"]
    assert sorted(masks["frames"]) == list(range(FRAMES)) and "SegmentationImage:buffer" in masks["temporal"]
    joints = {p for p in rec if p.startswith("/joints/")}
    assert joints == {f"/joints/{n}" for n in robot.joint_names}
    assert all(sorted(rec[p]["frames"]) == list(range(FRAMES)) for p in joints)
    assert not any(p.startswith("/actions") for p in rec)
    # The annotation context names every link by its mask label.
    context = rec["/"]["batches"][0].column("AnnotationContext:context").to_pylist()[0][0]
    assert {c["class_id"]: c["class_description"]["info"]["label"] for c in context} == {
        0: "background", **robot.link_labels()}
    # The segmentation images are the labels render_masks gives (uint16, little-endian bytes).
    q = np.array(json.loads((WORK / "joints.json").read_text()))
    labels = bw.render_masks(robot, cam, joints=q, labels=True)
    logged = images(masks, "SegmentationImage:buffer")
    assert all(np.array_equal(lg.view("<u2"), lab.ravel()) for lg, lab in zip(logged, labels))


def test_link_poses_place_the_meshes_on_the_masks(data):
    """The meshes at the poses of Robot.link_poses, seen through the camera's
    K and world_from_camera, land on the pixels render_masks labels robot."""
    robot, cam = bw.Robot("franka"), bw.Camera.from_json(WORK / "camera.json")
    q = np.array(json.loads((WORK / "joints.json").read_text()))
    poses = robot.link_poses(q)
    assert poses.shape == (FRAMES, len(robot.link_meshes()), 4, 4) and poses.dtype == np.float64
    assert np.allclose(robot.link_poses(q[3]), poses[3])
    masks = bw.render_masks(robot, cam, joints=q)
    camera_from_world = np.linalg.inv(cam.world_from_camera)
    w, h = cam.size
    hits = total = 0
    for t in range(FRAMES):
        for m, pose in zip(robot.link_meshes(), poses[t]):
            p = (camera_from_world @ pose)[:3] @ np.c_[m.vertices, np.ones(len(m.vertices))].T
            uv = (cam.K @ p)[:2] / p[2]
            u, v = np.rint(uv).astype(int)
            inside = (p[2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
            hits += int(masks[t][v[inside], u[inside]].sum())
            total += int(inside.sum())
    assert total > 1000 and hits / total > 0.95, (hits, total)
    # The camera's parts back, as given.
    d = bw.Camera(K=cam.K, world_from_camera=cam.world_from_camera, size=cam.size, dist=[0.1, 0, 0, 0])
    assert cam.dist is None and np.allclose(d.dist, [0.1, 0, 0, 0, 0])
    assert np.allclose(d.K, cam.K) and np.allclose(d.world_from_camera, cam.world_from_camera)


def test_masks_recording_from_actions_and_its_series(data):
    out = WORK / "masks-actions.rrd"
    rec = bwr.record_masks(out, "franka", WORK / "camera.json", actions=WORK / "actions.npy")
    assert rec.frames == FRAMES and rec.out == str(out)
    back = load(out)
    assert {p for p in back if p.startswith("/actions/")} == {f"/actions/{n}" for n in bwr.ACTION_NAMES}
    assert set(rec.entities) >= {p.lstrip("/") for p in back if p.startswith("/world")}
    check_robot(back, bw.Robot("franka"), FRAMES)
    assert bwr.action_names(14)[7:9] == ["arm1/x", "arm1/y"]


def test_predict_recording_shows_the_prediction_beside_the_truth(data):
    # The masks and the prediction as `bridgev2w masks` and `bridgev2w predict` write them.
    subprocess.run([BIN, "masks", "--robot", "franka", "--camera", WORK / "camera.json", "--joints",
                    WORK / "joints.json", "--width", "96", "--height", "64", "--out", WORK / "masks-out", "--no-png"],
                   check=True, capture_output=True)
    subprocess.run([BIN, "predict", "--model", "random:tiny", "--image", WORK / "first.png", "--masks",
                    WORK / "masks-out/masks.npy", "--steps", "2", "--device", "cpu", "--out", WORK / "pred"],
                   check=True, capture_output=True)
    out = WORK / "prediction.rrd"
    run("predict", "--video", WORK / "pred", "--masks", WORK / "masks-out/labels.npy", "--robot", "franka",
        "--truth", WORK / "truth.npy", "--image", WORK / "first.png", "--rerun", out)
    rec = load(out)
    for p in ("/video/predicted", "/video/true", "/video/masks"):
        assert sorted(rec[p]["frames"]) == list(range(FRAMES)), p
    assert "Image:buffer" in rec["/video/first_frame"]["static"]
    predicted = np.load(WORK / "pred/video.npy")
    assert all(np.array_equal(a, b.ravel()) for a, b in zip(images(rec["/video/predicted"]), predicted))
    truth = np.load(WORK / "truth.npy")
    assert all(np.array_equal(a, b.ravel()) for a, b in zip(images(rec["/video/true"]), truth))
    from rerun.chunk import RrdReader

    assert len(RrdReader(str(out)).blueprints()) == 1, "the side-by-side layout"
    # Predicting here (--model) gives the same video as `bridgev2w predict` (to 1 of 255).
    out2 = WORK / "prediction-model.rrd"
    run("predict", "--model", "random:tiny", "--image", WORK / "first.png", "--masks", WORK / "masks-out/masks.npy",
        "--steps", "2", "--device", "cpu", "--rerun", out2)
    rec2 = load(out2)
    assert "/video/true" not in rec2
    ours = np.stack(images(rec2["/video/predicted"])).astype(int)
    assert np.abs(ours - predicted.reshape(FRAMES, -1).astype(int)).max() <= 1


def test_view_recording_of_a_dataset_episode(data):
    out = WORK / "episode.rrd"
    p = run("view", data, "--episode", 1, "--rerun", out)
    assert f"{FRAMES} frames" in p.stdout
    rec = load(out)
    robot, ep = bw.Robot("franka"), bw.read_episode(data, 1)
    check_robot(rec, robot, FRAMES)
    for e in ("/world/camera/image/rgb", "/world/camera/image/masks"):
        assert sorted(rec[e]["frames"]) == list(range(FRAMES)), e
    assert all(np.array_equal(a, b.ravel()) for a, b in zip(images(rec["/world/camera/image/rgb"]), ep.frames))
    assert len([p for p in rec if p.startswith("/joints/")]) == len(robot.joint_names)
    assert len([p for p in rec if p.startswith("/actions/")]) == ep.actions.shape[1]
    # The rendered link labels cover the pixels of the dataset's own masks.
    labels = np.stack(images(rec["/world/camera/image/masks"], "SegmentationImage:buffer")).view("<u2")
    assert np.array_equal(labels.reshape(ep.masks.shape) != 0, ep.masks != 0)


def test_bad_input_is_an_error_naming_it(data):
    cam = WORK / "camera.json"
    # An existing recording is kept unless --overwrite; nothing is left behind.
    out = WORK / "masks.rrd"
    before = out.read_bytes()
    p = run("masks", "--robot", "franka", "--camera", cam, "--joints", WORK / "joints.json", "--rerun", out,
            check=False)
    assert p.returncode == 1 and f"{out}: already exists" in p.stderr and out.read_bytes() == before
    with pytest.raises(FileExistsError, match="already exists"):
        bwr.record_episode(out, data, 0)
    run("masks", "--robot", "franka", "--camera", cam, "--joints", WORK / "joints.json", "--rerun", out,
        "--overwrite")
    assert sorted(x.name for x in WORK.iterdir() if ".tmp" in x.name) == []
    # Inputs: named, with what was expected.
    bad = WORK / "bad.rrd"
    with pytest.raises(ValueError, match=r"joints: expected 8 values per row"):
        bwr.record_masks(bad, "franka", cam, joints=np.zeros((3, 7)))
    # Joints past their limits are recorded as given, with a warning naming them.
    with pytest.warns(UserWarning, match=r"panda_joint4.*outside its limits"):
        (WORK / "far.json").write_text(json.dumps([[0, 0, 0, 1.0, 0, 0, 0, 0]]))
        bwr.record_masks(WORK / "far.rrd", "franka", cam, joints=WORK / "far.json")
    with pytest.raises(FileNotFoundError, match="nope.json"):
        bwr.record_masks(bad, "franka", WORK / "nope.json", joints=WORK / "joints.json")
    with pytest.raises(ValueError, match="exactly one of joints= and actions="):
        bwr.record_masks(bad, "franka", cam)
    with pytest.raises(ValueError, match=r"out: .*expected a file name ending in \.rrd"):
        bwr.record_masks(WORK / "bad.mp4", "franka", cam, joints=WORK / "joints.json")
    video = np.load(WORK / "pred/video.npy")
    with pytest.raises(ValueError, match=r"truth: expected uint8 \[9, 64, 96, 3\]"):
        bwr.record_prediction(bad, video, masks=np.load(WORK / "masks-out/masks.npy"), truth=video[:5])
    with pytest.raises(ValueError, match=r"masks: expected \[9, 64, 96\]"):
        bwr.record_prediction(bad, video, masks=np.zeros((9, 32, 48), np.uint8))
    with pytest.raises(bw.Error, match="episode"):
        bwr.record_episode(bad, data, 7)
    with pytest.raises(ValueError, match="observation.state has 8 values per frame but robot"):
        bwr.record_episode(bad, data, 0, robot="dual-arm")
    with pytest.raises(ValueError, match="joints: expected 8 values per row"):
        bw.Robot("franka").link_poses(np.zeros((2, 3)))
    p = run("predict", "--video", WORK / "pred", "--masks", WORK / "nope.npy", "--rerun", bad, check=False)
    assert p.returncode == 1 and "--masks" in p.stderr and "nope.npy: no such .npy file" in p.stderr
    p = run("predict", "--model", "random:tiny", "--masks", WORK / "masks-out/masks.npy", "--rerun", bad,
            check=False)
    assert p.returncode == 1 and "--image" in p.stderr
    assert not bad.exists() and sorted(x.name for x in WORK.iterdir() if ".tmp" in x.name) == []


def test_without_the_rerun_sdk_the_error_says_how_to_get_it(data, monkeypatch):
    monkeypatch.setitem(sys.modules, "rerun", None)  # `import rerun` fails
    with pytest.raises(ImportError, match=r"rerun-sdk==0\.41\.0.*\./run setup"):
        bwr.record_episode(WORK / "x.rrd", data, 0)
    p = run("view", data, "--rerun", WORK / "x.rrd", check=False)
    assert p.returncode == 1 and "rerun-sdk" in p.stderr
    assert not (WORK / "x.rrd").exists()
