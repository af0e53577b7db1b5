"""Tests of the Python package against the command line (the same Rust
code reached another way) and closed forms. Run with pytest by
crates/cli/tests/python_package.rs after `pip install ./python`:

  BRIDGEV2W_BIN=... BRIDGEV2W_TEST_WORK=DIR BRIDGEV2W_TEST_RAW=DIR \
    python -m pytest python/tests/test_bridgev2w.py

BRIDGEV2W_BIN: the `bridgev2w` binary; BRIDGEV2W_TEST_WORK: an empty
folder; BRIDGEV2W_TEST_RAW: the raw DROID/AgiBot episodes of
scripts/fixtures/write_raw_episodes.py with their videos (written by the
Rust test). The tests run in file order (later ones read what earlier ones
wrote).
"""

import json
import os
import pathlib
import subprocess
import threading
import time

import numpy as np

import bridgev2w as bw

BIN = os.environ["BRIDGEV2W_BIN"]
WORK = pathlib.Path(os.environ["BRIDGEV2W_TEST_WORK"])
RAW = pathlib.Path(os.environ["BRIDGEV2W_TEST_RAW"])


def cli_masks(tmp, robot, cam, *, joints=None, actions=None, depth=False):
    """`bridgev2w masks` of the same inputs: (masks, labels, depth or None)."""
    cam_path = tmp / "cam.json"
    cam_path.write_text(cam.to_json())
    args = [BIN, "masks", "--robot", robot, "--camera", str(cam_path),
            "--width", str(cam.size[0]), "--height", str(cam.size[1]),
            "--out", str(tmp / "out"), "--no-png"]
    if joints is not None:
        (tmp / "q.json").write_text(json.dumps(np.asarray(joints).tolist()))
        args += ["--joints", str(tmp / "q.json")]
    else:
        (tmp / "a.json").write_text(json.dumps(np.asarray(actions).tolist()))
        args += ["--actions", str(tmp / "a.json")]
    if depth:
        args.append("--depth")
    subprocess.run(args, check=True, capture_output=True)
    out = tmp / "out"
    return (np.load(out / "masks.npy"), np.load(out / "labels.npy"),
            np.load(out / "depth.npy") if depth else None)


def camera():
    # 1.2 m in front of the robot, looking back at it (OpenCV axes).
    pose = np.array([[0.0, 0.0, -1.0, 1.6], [1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.5], [0, 0, 0, 1]])
    K = np.array([[120.0, 0, 79.5], [0, 120.0, 59.5], [0, 0, 1]])
    return bw.Camera(K=K, world_from_camera=pose, size=(160, 120))


def test_masks_from_joints_match_the_cli():
    robot, cam = bw.Robot("franka"), camera()
    t = np.arange(4)[:, None]
    q = robot.home[None, :] + 0.2 * np.sin(0.5 * t + np.arange(len(robot.joint_names)))
    q[:, -1] = 0.02  # the finger joint, within [0, 0.04] m
    masks = bw.render_masks(robot, cam, joints=q)
    labels, depth = bw.render_masks(robot, cam, joints=q, labels=True, depth=True)
    assert masks.dtype == np.uint8 and masks.shape == (4, 120, 160), masks.shape
    assert labels.dtype == np.uint16 and depth.dtype == np.float32
    assert masks.sum() > 500, "the robot is in view"
    tmp = WORK / "joints"
    tmp.mkdir()
    m, lab, d = cli_masks(tmp, "franka", cam, joints=q, depth=True)
    assert np.array_equal(masks, m), "masks differ from bridgev2w masks"
    assert np.array_equal(labels, lab), "labels differ"
    assert np.array_equal(np.isinf(depth), np.isinf(d)) and np.allclose(depth[np.isfinite(depth)], d[np.isfinite(d)])
    assert set(np.unique(labels)) - {0} <= set(robot.link_labels())


def test_ik_and_masks_from_actions_match_the_cli():
    robot, cam = bw.Robot("franka"), camera()
    a = np.array([[0.32 + 0.01 * t, -0.02, 0.46, np.pi, 0.0, 0.08, 0.2 * t] for t in range(4)])
    q, res = robot.solve_ik(a)
    assert q.shape == (4, len(robot.joint_names)) and len(res) == 4
    assert all(r.reached and r.position_error_m < 1e-3 for r in res), res
    masks = bw.render_masks(robot, cam, actions=a)
    tmp = WORK / "actions"
    tmp.mkdir()
    m, _, _ = cli_masks(tmp, "franka", cam, actions=a)
    assert np.array_equal(masks, m), "masks from actions differ from bridgev2w masks --actions"
    # Out of reach: an error, or with allow_residual a residual that says so.
    far = a.copy()
    far[:, 0] = 3.0
    try:
        robot.solve_ik(far)
        raise AssertionError("an unreachable target passed")
    except bw.Error as e:
        assert "frame 0" in str(e), e
    _, res = robot.solve_ik(far, allow_residual=True)
    assert not res[0].reached and res[0].position_error_m > 1.0


def test_a_urdf_robot_gives_the_clis_masks_joints_and_ik_residuals():
    """A URDF robot (the Franka's URDF file, not the built-in one), actions
    with an unreachable frame rendered with allow_residual: masks, IK joints
    and residuals equal `bridgev2w masks --robot URDF --allow-ik-residual`."""
    urdf = pathlib.Path(__file__).resolve().parents[2] / "crates/embodiment/robots/franka/franka.urdf"
    robot = bw.Robot.from_urdf(urdf, ee_links=["panda_hand_tcp"], gripper_joints=["panda_finger_joint1"])
    cam = camera()
    a = np.array([[0.30 + 0.02 * t, 0.05, 0.45, np.pi, 0.0, 0.1 * t, 0.5] for t in range(4)])
    a[2, 0] = 2.5  # out of reach
    q, res = robot.solve_ik(a, allow_residual=True)
    masks = bw.render_masks(robot, cam, actions=a, allow_residual=True)
    tmp = WORK / "urdf"
    tmp.mkdir()
    cam_path = tmp / "cam.json"
    cam_path.write_text(cam.to_json())
    (tmp / "a.json").write_text(json.dumps(a.tolist()))
    subprocess.run([BIN, "masks", "--robot", str(urdf), "--ee-link", "panda_hand_tcp",
                    "--gripper-joint", "panda_finger_joint1", "--camera", str(cam_path),
                    "--width", "160", "--height", "120", "--actions", str(tmp / "a.json"),
                    "--allow-ik-residual", "--out", str(tmp / "out"), "--no-png"],
                   check=True, capture_output=True)
    out = tmp / "out"
    assert masks.sum() > 500, "the robot is in view"
    assert np.array_equal(masks, np.load(out / "masks.npy")), "masks differ from the CLI's"
    assert np.array_equal(q, np.load(out / "joints.npy")), "IK joints differ from the CLI's"
    report = json.loads((out / "ik.json").read_text())
    assert report["frames_not_reached"] == [r.frame for r in res if not r.reached] == [2], report
    cli = [(r["frame"], r["position_error_m"], r["rotation_error_rad"], r["reached"])
           for r in report["residuals"]]
    assert cli == [(r.frame, r.position_error_m, r.rotation_error_rad, r.reached) for r in res], (cli, res)


def test_lerobot_transform_adds_each_cameras_mask():
    robot, cam = bw.Robot("franka"), camera()
    q = robot.home.copy()
    q[-1] = 0.02
    masks = bw.lerobot.EmbodimentMasks(robot, {"observation.images.main": cam})
    # A numpy item with the camera's image at half size: the mask follows the image.
    item = {"observation.state": q, "observation.images.main": np.zeros((60, 80, 3), np.uint8)}
    out = masks(item)
    m = out["observation.images.main.mask"]
    assert m.shape == (60, 80) and m.dtype == np.uint8
    assert np.array_equal(m, bw.render_masks(robot, cam.rescaled(80, 60), joints=q[None])[0])
    # A torch item (LeRobotDataset's): a window of states, a [C, H, W] image.
    import torch

    window = torch.tensor(np.stack([q, q]), dtype=torch.float32)
    out = masks({"observation.state": window, "observation.images.main": torch.zeros(3, 120, 160)})
    t = out["observation.images.main.mask"]
    assert isinstance(t, torch.Tensor) and tuple(t.shape) == (2, 120, 160)
    assert np.array_equal(t.numpy()[0], bw.render_masks(robot, cam, joints=q[None].astype(np.float32))[0])
    try:
        masks({"action": q})
        raise AssertionError("an item without a state passed")
    except ValueError as e:
        assert "observation.state" in str(e), e


def test_world_model_predicts_as_the_cli_does():
    # `bridgev2w predict` initialises a random preset from its --seed.
    wm = bw.WorldModel.from_pretrained("random:tiny", seed=3)
    (h, w), t = wm.resolution, wm.clip_frames
    rng = np.random.default_rng(1)
    first = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    masks = np.zeros((t, h, w), np.uint8)
    masks[:, h // 4: h // 2, w // 4: w // 2] = 1
    video = wm.predict(first, masks, steps=2, seed=3)
    assert video.dtype == np.uint8 and video.shape == (t, h, w, 3), video.shape
    tmp = WORK / "predict"
    tmp.mkdir()
    import PIL.Image

    PIL.Image.fromarray(first).save(tmp / "first.png")
    np.save(tmp / "masks.npy", masks)
    subprocess.run([BIN, "predict", "--model", "random:tiny", "--image", str(tmp / "first.png"),
                    "--masks", str(tmp / "masks.npy"), "--steps", "2", "--seed", "3",
                    "--out", str(tmp / "out")], check=True, capture_output=True)
    cli = np.load(tmp / "out" / "video.npy")
    diff = np.abs(cli.astype(int) - video.astype(int))
    assert diff.max() <= 1 and diff.mean() < 0.01, (diff.max(), diff.mean())
    # The VAE in the tiles asked for, as `predict --vae-tile`: the same video
    # as the CLI's, another than whole frames give.
    tiled = bw.WorldModel.from_pretrained("random:tiny", seed=3, vae_tile="48x40").predict(first, masks, steps=2, seed=3)
    subprocess.run([BIN, "predict", "--model", "random:tiny", "--image", str(tmp / "first.png"),
                    "--masks", str(tmp / "masks.npy"), "--steps", "2", "--seed", "3", "--vae-tile", "48x40",
                    "--out", str(tmp / "out-tiled")], check=True, capture_output=True)
    diff = np.abs(np.load(tmp / "out-tiled" / "video.npy").astype(int) - tiled.astype(int))
    assert diff.max() <= 1 and diff.mean() < 0.01, (diff.max(), diff.mean())
    assert (tiled != video).any(), "the tiles must be used"
    # predict_files: the CLI's library call, the same files.
    r = wm.predict_files(tmp / "first.png", tmp / "masks.npy", tmp / "out-py", steps=2, seed=3)
    assert r["frames"] == t and r["clips"] == [(None, str(tmp / "masks.npy"))], r
    assert sorted(files(tmp / "out-py")) == sorted(files(tmp / "out"))
    diff = np.abs(np.load(tmp / "out-py" / "video.npy").astype(int) - cli.astype(int))
    assert diff.max() <= 1 and diff.mean() < 0.01, (diff.max(), diff.mean())
    try:
        wm.predict_files(tmp / "first.png", tmp / "masks.npy", tmp / "out-py", steps=2)
        raise AssertionError("an existing output was replaced")
    except bw.Error as e:
        assert "already exists" in str(e), e
    try:
        wm.predict_files(tmp / "first.png", tmp / "absent.npy", tmp / "out-x")
        raise AssertionError("a missing mask file passed")
    except FileNotFoundError as e:
        assert "absent.npy" in str(e), e
    # Link labels pass through as labels: a binary-coded model sees robot vs
    # background, so labels give the video their silhouette gives.
    labels = masks * 7
    labels[:, h // 4: h // 3] = 3
    labels[:, h // 4: h // 3, : w // 4] = 0
    assert (wm.predict(first, labels, steps=2, seed=3) == wm.predict(first, labels != 0, steps=2, seed=3)).all()
    for bad in (masks.astype(np.int32) * 300, masks.astype(np.int16) - 1):
        try:
            wm.predict(first, bad)
            raise AssertionError("labels outside 0..255 passed")
        except ValueError as e:
            assert "0..255" in str(e), e
    # The shipped demo model, from its folder.
    demo = bw.WorldModel.from_pretrained(pathlib.Path(__file__).resolve().parents[2] / "assets" / "demo-model")
    assert demo.resolution == (64, 96) and demo.clip_frames == 9, demo
    # It reads link-coded masks: labels pass, binary masks are refused by name.
    lab = np.zeros((9, 64, 96), np.uint8)
    lab[:, 20:40, 30:50] = 3
    v = demo.predict(np.zeros((64, 96, 3), np.uint8), lab, steps=1)
    assert v.shape == (9, 64, 96, 3)
    refused = None
    try:
        demo.predict(np.zeros((64, 96, 3), np.uint8), lab != 0, steps=1)
    except Exception as e:  # the model's own error (bridgev2w's exception type)
        refused = str(e)
    assert refused is not None and "link-coded" in refused, refused
    try:
        wm.predict(first[:, :-1], masks)
        raise AssertionError("a wrong first frame passed")
    except ValueError as e:
        assert "first_frame" in str(e), e
    try:
        bw.WorldModel.from_pretrained(WORK / "no-model-here")
        raise AssertionError("a missing model folder passed")
    except FileNotFoundError as e:
        assert "no-model-here" in str(e), e


def test_metrics_match_closed_forms():
    rng = np.random.default_rng(0)
    gt = rng.integers(0, 256, (3, 24, 32, 3), dtype=np.uint8)
    noise = rng.integers(-20, 21, gt.shape)
    pred = np.clip(gt.astype(int) + noise, 0, 255).astype(np.uint8)
    mse = ((pred.astype(float) - gt) ** 2 / 255.0 ** 2).mean(axis=(1, 2, 3))
    want = np.mean(10 * np.log10(1.0 / mse))
    assert abs(bw.metrics.psnr(pred, gt) - want) < 1e-6, (bw.metrics.psnr(pred, gt), want)
    assert abs(bw.metrics.ssim(gt, gt) - 1.0) < 1e-9
    assert 0.0 < bw.metrics.ssim(pred, gt) < 1.0
    a, b = rng.random((40, 50)) > 0.5, rng.random((40, 50)) > 0.3
    assert abs(bw.metrics.mask_iou(a, b) - (a & b).sum() / (a | b).sum()) < 1e-12


def files(root):
    """{relative path: bytes} of every file under root."""
    root = pathlib.Path(root)
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def same_tree(a, b):
    fa, fb = files(a), files(b)
    assert sorted(fa) == sorted(fb), (sorted(set(fa) ^ set(fb)))
    differ = [k for k in fa if fa[k] != fb[k]]
    assert not differ, f"files differ between {a} and {b}: {differ}"
    return len(fa)


def test_synth_generate_writes_what_the_cli_writes():
    out = WORK / "synth-py"
    s = bw.synth.generate(out, episodes_per_split=(2, 1, 0, 1), frames=5, width=32, height=24, seed=4,
                          tasks=["reach", "push"])
    assert s.episodes == 4 and s.total_frames == 20, s
    assert s.episodes_per_split == {"train": 2, "test": 1, "unseen_scene": 1}, s.episodes_per_split
    assert s.episodes_per_task == {"reach": 2, "push": 2}, s.episodes_per_task
    assert pathlib.Path(s.out) == out
    subprocess.run([BIN, "synth", "--out", str(WORK / "synth-cli"), "--episodes-per-split", "2,1,0,1",
                    "--frames", "5", "--width", "32", "--height", "24", "--seed", "4", "--tasks", "reach,push"],
                   check=True, capture_output=True)
    n = same_tree(out, WORK / "synth-cli")
    assert n > 8, n
    # Read back: the masks it wrote are what render_masks gives for the
    # episode's camera and joints (stored as float32: to a few edge pixels).
    ep = bw.read_episode(out, 3)
    assert ep.frames.shape == (5, 24, 32, 3) and ep.frames.dtype == np.uint8, ep.frames.shape
    assert ep.states.shape == (5, 8) and ep.actions.shape == (5, 7) and ep.split == "unseen_scene", ep
    assert np.array_equal(ep.masks, np.load(out / "masks/episode_000003.npy"))
    assert ep.camera.size == (32, 24) and ep.key == "observation.images.main"
    masks = bw.render_masks(bw.Robot("franka"), ep.camera, joints=ep.states)
    assert bw.metrics.mask_iou(masks, ep.masks) > 0.9, bw.metrics.mask_iou(masks, ep.masks)
    try:
        bw.synth.generate(out, episodes_per_split=1, frames=5, width=32, height=24)
        raise AssertionError("an existing out passed")
    except FileExistsError as e:
        assert "synth-py" in str(e), e
    # Perturbed demonstrations: the CLI's bytes again, the counts reported.
    p = bw.synth.generate(WORK / "synth-py-perturbed", episodes_per_split=(3, 1, 0, 0), frames=5, width=32,
                          height=24, seed=4, tasks=["reach", "push"], perturbed_fraction=1.0, perturb_mm=40)
    assert p.perturbed == 3 and 0 <= p.perturbed_failed <= 3, p
    subprocess.run([BIN, "synth", "--out", str(WORK / "synth-cli-perturbed"), "--episodes-per-split", "3,1,0,0",
                    "--frames", "5", "--width", "32", "--height", "24", "--seed", "4", "--tasks", "reach,push",
                    "--perturbed-fraction", "1", "--perturb-mm", "40"], check=True, capture_output=True)
    assert same_tree(WORK / "synth-py-perturbed", WORK / "synth-cli-perturbed") > 8
    import pytest
    with pytest.raises(ValueError, match="perturbed-fraction"):
        bw.synth.generate(WORK / "synth-py-bad", perturbed_fraction=2.0)


def test_read_episode_checks_shapes_against_the_declared_features():
    out = WORK / "synth-shapes"
    bw.synth.generate(out, episodes_per_split=(1, 0, 0, 0), frames=3, width=32, height=24, seed=1)
    info_path = out / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    key = "observation.images.main"
    n = info["features"]["observation.state"]["shape"][0]

    def refused(needles):
        try:
            bw.read_episode(out, 0)
        except bw.Error as e:
            assert all(x in str(e) for x in needles), (needles, e)
        else:
            raise AssertionError(f"read despite {needles}")

    good = json.dumps(info)
    info["features"]["observation.state"]["shape"] = [n + 1]
    info_path.write_text(json.dumps(info))
    refused(["observation.state", f"declares shape [{n + 1}]", "file-000.parquet"])
    info = json.loads(good)
    info["features"][key]["shape"] = [24, 30, 3]
    info_path.write_text(json.dumps(info))
    refused([key, "declares [24, 30, 3]", ".mp4"])
    info_path.write_text(good)
    assert bw.read_episode(out, 0).masks.shape == (3, 24, 32)
    np.save(out / "masks" / "episode_000000.npy", np.zeros((2, 24, 32), np.uint8))
    refused(["episode_000000.npy", "masks", "shape [2, 24, 32]", "expected [3, 24, 32]"])


def test_convert_writes_what_the_cli_writes():
    droid = RAW / "droid"
    intr = RAW / "droid_intrinsics.json"
    r = bw.convert(droid, WORK / "droid-py", format="droid", intrinsics=intr, width=32, height=24)
    assert (r.episodes, r.views_written, r.skipped) == (1, 2, []), r
    assert r.ee_frames == ["panda_link8"] and isinstance(r.report["notes"], list), r
    subprocess.run([BIN, "convert", "--format", "droid", str(droid), "--out", str(WORK / "droid-cli"),
                    "--intrinsics", str(intr), "--width", "32", "--height", "24"], check=True,
                   capture_output=True)
    same_tree(WORK / "droid-py", WORK / "droid-cli")
    ep = bw.read_episode(WORK / "droid-py", 1)
    assert ep.frames.shape[1:] == (24, 32, 3) and ep.states.shape[1] == 8, (ep.frames.shape, ep.states.shape)
    # AgiBot World onto a Robot object, one camera.
    g1 = bw.Robot("agibot-g1")
    r = bw.convert(RAW / "agibot", WORK / "g1-py", format="agibot", robot=g1, width=32, height=24,
                   cameras="head")
    assert r.episodes == 1 and r.views_written == 1, r
    subprocess.run([BIN, "convert", "--format", "agibot", str(RAW / "agibot"), "--out", str(WORK / "g1-cli"),
                    "--width", "32", "--height", "24", "--cameras", "head"], check=True, capture_output=True)
    same_tree(WORK / "g1-py", WORK / "g1-cli")
    # A bad episode: an error naming it, or skipped and reported.
    try:
        bw.convert(RAW / "droid_bad", WORK / "bad", format="droid", intrinsics=intr, width=32, height=24)
        raise AssertionError("a bad episode passed")
    except bw.Error as e:
        assert "trajectory_length" in str(e) or "NaN" in str(e), e
    assert not (WORK / "bad").exists(), "nothing half-written"
    import shutil

    shutil.copytree(droid, WORK / "mixed" / "good")
    shutil.copytree(RAW / "droid_bad", WORK / "mixed" / "bad")
    r = bw.convert(WORK / "mixed", WORK / "bad", format="droid", intrinsics=intr, width=32, height=24,
                   skip_bad=True)
    assert (r.episodes, r.views_written, len(r.skipped)) == (1, 2, 2), r
    assert (WORK / "bad" / "skipped.json").is_file()


def test_calibrate_finds_a_camera_and_writes_its_folder():
    """bw.calibrate on a real DROID episode (skipped where the shared real
    data is absent): a known focal length kept, the files written, an
    existing out refused, bad arguments named."""
    import pytest

    root = pathlib.Path(__file__).resolve().parents[2] / ".." / "shared" / "realdata" / "droid" / "droid_new_setup"
    if not root.is_dir():
        pytest.skip(f"{root} is absent (the shared real-data folder)")
    video = root / "videos" / "val" / "0007" / "0.mp4"
    joints = root / "annotation" / "val" / "0007.json"
    out = WORK / "calibration"
    marks = pathlib.Path(__file__).resolve().parents[2] / "crates" / "data" / "tests" / "data" / "droid_marks.json"
    c = bw.calibrate(video, joints, out, focal_px=133.0, fy_over_fx=192 / 180, analysis_width=80,
                     max_evaluations=30, walk_evaluations=0, marks=marks)
    # The hand marks of this video (6 in the file) are measured in pixels.
    assert len(c.marks) == 1 and c.marks[0][3] == 6 and 0 <= c.marks[0][1] <= c.marks[0][2], c.marks
    assert isinstance(c.camera, bw.Camera) and c.camera.size == (320, 192), c
    assert abs(c.camera.K[0, 0] - 133.0) < 1e-9, c.camera.K
    assert 0.0 <= c.held_out_iou <= 1.0 and len(c.episodes) == 1 and c.episodes[0][3], c
    assert c.reliable == (not c.flags) and "held-out IoU" in c.summary, c
    for f in ["camera.json", "residuals.json"]:
        assert (out / f).is_file(), f
    assert bw.Camera.from_json(out / "camera.json").size == (320, 192)
    with pytest.raises(bw.Error, match="exists"):
        bw.calibrate(video, joints, out, focal_px=133.0, analysis_width=80, max_evaluations=30)
    # Its camera converts the rig's episodes (the Ctrl-World layout), as the CLI does.
    rig = root.parent
    args = dict(format="ctrl-world", width=32, height=24, camera_json={"ext1": out / "camera.json"},
                include=["droid_new_setup/val/0007", "droid_new_setup/val/0011"],
                split_rules=["droid_new_setup/val/0011=test"])
    r = bw.convert(rig, WORK / "cw-py", **args)
    assert (r.episodes, r.views_written, r.skipped) == (2, 2, []), r
    assert bw.read_episode(WORK / "cw-py", 1).split == "test"
    subprocess.run([BIN, "convert", "--format", "ctrl-world", str(rig), "--out", str(WORK / "cw-cli"),
                    "--width", "32", "--height", "24", "--camera", f"ext1={out / 'camera.json'}",
                    "--include", ",".join(args["include"]), "--split-rule", args["split_rules"][0]],
                   check=True, capture_output=True)
    same_tree(WORK / "cw-py", WORK / "cw-cli")
    with pytest.raises(ValueError, match="wrist"):
        bw.convert(rig, WORK / "cw-bad", format="ctrl-world", camera_json={"wrist": out / "camera.json"})
    with pytest.raises(ValueError, match="check_joints"):
        bw.calibrate(video, joints, WORK / "c2", check_videos=[video])
    with pytest.raises(FileNotFoundError, match="absent.mp4"):
        bw.calibrate(root / "absent.mp4", joints, WORK / "c3")
    with pytest.raises(FileNotFoundError, match="absent-marks.json"):
        bw.calibrate(video, joints, WORK / "c4", marks=WORK / "absent-marks.json")
    with pytest.raises(ValueError, match=r"walk_evaluations: -1, expected an integer in \[0, 100000\]"):
        bw.calibrate(video, joints, WORK / "c5", walk_evaluations=-1)
    with pytest.raises(ValueError, match=r"background_weight: -1.0, expected a finite value >= 0"):
        bw.calibrate(video, joints, WORK / "c5", background_weight=-1.0)
    with pytest.raises(ValueError, match=r"appearance_weight: -2.5, expected a finite value >= 0"):
        bw.calibrate(video, joints, WORK / "c5", appearance_weight=-2.5)
    with pytest.raises(ValueError, match=r"appearance_weight: expected a finite number, got nan"):
        bw.calibrate(video, joints, WORK / "c5", appearance_weight=float("nan"))
    with pytest.raises(ValueError, match=r"static_changes: .*leaveout.*expected one of score, leave-out"):
        bw.calibrate(video, joints, WORK / "c6", static_changes="leaveout")


def test_batches_equal_their_single_items():
    robot, cam = bw.Robot("franka"), camera()
    t = np.arange(3)[:, None, None]
    dof = len(robot.joint_names)
    q = robot.home[None, None, :] + 0.15 * np.sin(0.7 * t + 0.3 * np.arange(4)[None, :, None] + np.arange(dof))
    q[..., -1] = 0.02
    masks = bw.render_masks(robot, cam, joints=q)  # [B=3, T=4, H, W]
    assert masks.shape == (3, 4, 120, 160) and masks.dtype == np.uint8
    for b in range(3):
        assert np.array_equal(masks[b], bw.render_masks(robot, cam, joints=q[b])), b
    # One camera per sequence.
    other = cam.rescaled(160, 120)
    labels, depth = bw.render_masks(robot, [cam, other, cam], joints=q, labels=True, depth=True)
    assert labels.shape == depth.shape == (3, 4, 120, 160) and np.array_equal(labels > 0, masks)
    # IK of a batch of action sequences, in parallel: as one at a time.
    a = np.array([[[0.32 + 0.01 * t + 0.02 * b, -0.02, 0.46, np.pi, 0.0, 0.08, 0.2 * t] for t in range(3)]
                  for b in range(2)])
    qb, res = robot.solve_ik(a)
    assert qb.shape == (2, 3, dof) and len(res) == 2 and len(res[1]) == 3
    for b in range(2):
        q1, r1 = robot.solve_ik(a[b])
        assert np.array_equal(q1, qb[b]) and r1 == res[b]
    mb = bw.render_masks(robot, cam, actions=a)
    assert np.array_equal(mb[1], bw.render_masks(robot, cam, actions=a[1]))


def test_world_model_batches_and_torch_tensors():
    import torch

    wm = bw.WorldModel.from_pretrained("random:tiny", seed=3)
    (h, w), t = wm.resolution, wm.clip_frames
    rng = np.random.default_rng(2)
    first = rng.integers(0, 256, (2, h, w, 3), dtype=np.uint8)
    masks = np.zeros((2, t, h, w), np.uint8)
    masks[0, :, : h // 2] = 1
    masks[1, :, :, w // 2:] = 1
    videos = wm.predict(first, masks, steps=2, seed=5)
    assert videos.shape == (2, t, h, w, 3) and videos.dtype == np.uint8
    for b in range(2):
        one = wm.predict(first[b], masks[b], steps=2, seed=5)
        diff = np.abs(one.astype(int) - videos[b].astype(int))
        assert diff.max() <= 1 and diff.mean() < 0.01, (b, diff.max(), diff.mean())
    # One first frame shared by a batch of masks.
    shared = wm.predict(first[0], masks, steps=2, seed=5)
    assert shared.shape == (2, t, h, w, 3)
    assert np.abs(shared[0].astype(int) - videos[0].astype(int)).max() <= 1
    # torch in, torch out (the same numbers).
    tv = wm.predict(torch.from_numpy(first[1]), torch.from_numpy(masks[1]).bool(), steps=2, seed=5)
    assert isinstance(tv, torch.Tensor) and tv.dtype == torch.uint8 and tuple(tv.shape) == (t, h, w, 3)
    assert np.abs(tv.numpy().astype(int) - videos[1].astype(int)).max() <= 1


def test_the_gil_is_released_while_predicting_and_rendering():
    # A prediction in a thread: the main thread keeps running Python meanwhile.
    wm = bw.WorldModel.from_pretrained("random:tiny", seed=3)
    (h, w), t = wm.resolution, wm.clip_frames
    first = np.zeros((h, w, 3), np.uint8)
    masks = np.ones((t, h, w), np.uint8)
    span = {}

    def predict():
        span["start"] = time.perf_counter()
        wm.predict(first, masks, steps=3, seed=0)
        span["end"] = time.perf_counter()

    worker = threading.Thread(target=predict)
    ticks = []
    worker.start()
    while worker.is_alive():
        ticks.append(time.perf_counter())
        time.sleep(0.002)
    worker.join()
    inside = [x for x in ticks if span["start"] < x < span["end"]]
    took = span["end"] - span["start"]
    # With the GIL held for the whole call, no tick could fall inside it.
    assert took > 0.05 and len(inside) >= 10, (took, len(inside))
    gaps = np.diff([span["start"], *inside, span["end"]])
    assert gaps.max() < max(0.5 * took, 0.05), (took, gaps.max())

    # Two threads rendering at once: their calls overlap in time (with the GIL
    # held, one would wait for the other to finish).
    robot, cam = bw.Robot("franka"), camera().rescaled(480, 360)
    q = np.repeat(robot.home[None], 48, axis=0)
    q[:, 0] = np.linspace(-1, 1, 48)
    q[:, -1] = 0.02
    spans = [None, None]
    barrier = threading.Barrier(2)

    def render(i):
        barrier.wait()
        s = time.perf_counter()
        bw.render_masks(robot, cam, joints=q, depth=True)
        spans[i] = (s, time.perf_counter())

    threads = [threading.Thread(target=render, args=(i,)) for i in range(2)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    (s0, e0), (s1, e1) = spans
    overlap = min(e0, e1) - max(s0, s1)
    assert overlap > 0.5 * min(e0 - s0, e1 - s1), (spans, overlap)


def test_joints_past_their_limits_are_rendered_and_warned_about():
    import warnings

    robot, cam = bw.Robot("franka"), camera()
    q = np.full((1, 8), 0.5)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        m = bw.render_masks(robot, cam, joints=q)
    assert m.shape[0] == 1
    text = " ".join(str(w.message) for w in caught)
    assert "panda_joint4" in text and "outside its limits" in text and "not clamped" in text, text
    assert robot._r.limit_violations(q.tolist())[0][0] == "panda_joint4"


def test_flange_actions_and_moving_cameras():
    robot = bw.Robot("franka-robotiq")
    # DROID-style flange poses as TCP poses and back (closed form: the
    # Robotiq TCP is 0.1581549775 m along the flange's z axis, its URDF origin).
    flange = np.array([[0.5, 0.0, 0.3, np.pi, 0.0, 0.0, 0.4]])
    tcp = robot.convert_action_links(flange, ["panda_link8"], ["robotiq_tcp"])
    assert np.allclose(tcp[0, :3], [0.5, 0.0, 0.3 - 0.1581549775], atol=1e-9), tcp
    assert tcp[0, 6] == 0.4
    back = robot.convert_action_links(tcp, ["robotiq_tcp"], ["panda_link8"])
    assert np.allclose(back[0, :3], flange[0, :3], atol=1e-9)
    # A camera moving per frame renders each frame from its own pose.
    cam = camera()
    q = np.array([robot.home, robot.home])
    fixed = bw.render_masks(robot, cam, joints=q[:1], labels=True)
    moving = cam.with_poses([cam.world_from_camera, cam.world_from_camera])
    assert moving.kind == "per_frame"
    m = bw.render_masks(robot, moving, joints=q, labels=True)
    assert (m[0] == fixed[0]).all() and (m[1] == fixed[0]).all()
    # Mounted on the base link at the camera's pose: the fixed camera.
    mounted = cam.mounted("panda_link0", cam.world_from_camera)
    assert (bw.render_masks(robot, mounted, joints=q[:1], labels=True) == fixed).all()
    try:
        bw.render_masks(robot, cam.mounted("no_such_link"), joints=q[:1])
        raise AssertionError("an unknown mount link passed")
    except ValueError as e:
        assert "no_such_link" in str(e), e


def test_python_functions_are_evaluated_as_policies():
    import pytest

    seen = {}

    def stay(obs):
        seen["obs"] = (obs["image"].shape, obs["image"].dtype, obs["joints"].shape, obs["ee"].shape)
        return np.repeat(obs["ee"][None], 4, axis=0)

    def broken(obs):
        if obs["step"] == 1:
            raise RuntimeError("policy bug on purpose")
        return obs["ee"]

    def wide(obs):
        return np.zeros((3, 8))

    r = bw.evaluate_policies({"stay": stay, "broken": broken, "wide": wide}, task="reach", trials=2,
                             episode_frames=9, offsets_mm=[0, 50])
    assert r.policies == ["scripted(offset 0 mm)", "scripted(offset 50 mm)", "stay"], r
    assert seen["obs"] == ((64, 96, 3), np.uint8, (8,), (7,)), seen
    assert r.real[0] == 1.0 and r.real[2] == 0.0 and r.predicted[2] == 0.0, r
    assert "| stay |" in r.markdown
    failed = dict(r.failed)
    assert failed.keys() == {"broken", "wide"}, r.failed
    assert "policy broken, step 1" in failed["broken"] and "policy bug on purpose" in failed["broken"]
    assert "Traceback" in failed["broken"] and "in broken" in failed["broken"], failed["broken"]
    assert "returned shape (3, 8)" in failed["wide"] and "step 0" in failed["wide"], failed["wide"]
    assert r.calibration is None
    assert r.overestimate == [p - q for p, q in zip(r.predicted, r.real)], r.overestimate
    # The judge calibrated on the perfect model's expert rollouts: a floor
    # of 0, so the fixed judge's rates.
    c = bw.evaluate_policies({"stay": stay}, task="reach", trials=2, episode_frames=9, offsets_mm=[0, 50],
                             calibrate_judge=2)
    assert c.calibration["floor"] == 0.0 and c.calibration["ratio"] == 0.5, c.calibration
    assert c.calibration["episodes"] == 2 and len(c.calibration["expert_ratios"]) == 2, c.calibration
    assert c.predicted == r.predicted and c.real == r.real, (c, r)
    with pytest.raises(ValueError, match=r"policies\['x'\]: expected a function"):
        bw.evaluate_policies({"x": 3})
    with pytest.raises(ValueError, match="task"):
        bw.evaluate_policies({"stay": stay}, task="fly", offsets_mm=[0])
    with pytest.raises(ValueError, match="two policies"):
        bw.evaluate_policies({"stay": stay}, task="reach")


def test_bad_input_is_a_python_exception_naming_it():
    robot, cam = bw.Robot("franka"), camera()
    wm = bw.WorldModel.from_pretrained("random:tiny")
    cases = [
        (lambda: bw.render_masks(robot, cam, joints=np.zeros((2, 3))), ValueError, "joints"),
        (lambda: bw.render_masks(robot, cam, joints=np.full((1, len(robot.joint_names)), np.nan)), ValueError, "NaN"),
        (lambda: bw.render_masks(robot, cam), ValueError, "joints= and actions="),
        (lambda: robot.solve_ik(np.zeros((2, 6))), ValueError, "actions"),
        (lambda: bw.Camera.from_json(WORK / "missing.json"), FileNotFoundError, "missing.json"),
        (lambda: bw.Camera(K=np.eye(2), world_from_camera=np.eye(4), size=(4, 4)), ValueError, "K"),
        (lambda: bw.Robot("no-such-robot"), bw.Error, "no-such-robot"),
        (lambda: bw.Robot.from_urdf(WORK / "missing.urdf"), FileNotFoundError, "missing.urdf"),
        (lambda: bw.metrics.psnr(np.zeros((4, 4, 3)), np.zeros((4, 4, 3))), ValueError, "uint8"),
        (lambda: bw.metrics.mask_iou(np.zeros(3), np.zeros(4)), ValueError, "same shape"),
        # Batches.
        (lambda: bw.render_masks(robot, [cam, cam], joints=np.zeros((3, 2, 8))), ValueError, "camera"),
        (lambda: bw.render_masks(robot, [cam, cam.rescaled(80, 60)], joints=np.tile(robot.home, (2, 1, 1))),
         ValueError, "one size"),
        (lambda: bw.render_masks(robot, "cam.json", joints=robot.home[None]), ValueError, "camera"),
        (lambda: bw.render_masks(robot, cam, joints=np.zeros((1, 1, 1, 8))), ValueError, "joints"),
        (lambda: bw.render_masks(robot, cam, joints=np.array([["a"] * 8])), ValueError, "joints"),
        (lambda: robot.solve_ik(np.zeros((2, 0, 7))), ValueError, "actions"),
        # The world model (random:tiny: 9 frames of 64x96).
        (lambda: wm.predict(np.zeros((64, 96, 3)), np.zeros((9, 64, 96), np.uint8)), ValueError, "first_frame"),
        (lambda: wm.predict(np.zeros((64, 96, 3), np.uint8), np.zeros((8, 64, 96), np.uint8)), ValueError, "masks"),
        (lambda: wm.predict(np.zeros((64, 96, 3), np.uint8), np.full((9, 64, 96), 0.5)), ValueError, "masks"),
        (lambda: wm.predict(np.zeros((2, 64, 96, 3), np.uint8), np.zeros((3, 9, 64, 96), np.uint8)),
         ValueError, "batches"),
        (lambda: wm.predict(np.zeros((64, 96, 3), np.uint8), np.zeros((9, 64, 96), np.uint8), steps=0),
         ValueError, "steps"),
        (lambda: wm.predict(np.zeros((64, 96, 3), np.uint8), np.zeros((9, 64, 96), np.uint8), guidance="x"),
         ValueError, "guidance"),
        (lambda: bw.WorldModel.from_pretrained("random:tiny", device="tpu"), ValueError, "device"),
        (lambda: bw.WorldModel.from_pretrained("random:tiny", vae_tile="144"), ValueError, "vae_tile"),
        (lambda: bw.WorldModel.from_pretrained("random:tiny", vae_tile="64x96"), ValueError, "would not join"),
        # synth.
        (lambda: bw.synth.generate(WORK / "s1", frames=1), ValueError, "frames"),
        (lambda: bw.synth.generate(WORK / "s1", width=33), ValueError, "width"),
        (lambda: bw.synth.generate(WORK / "s1", height=16.0), ValueError, "height"),
        (lambda: bw.synth.generate(WORK / "s1", episodes_per_split=(1, 2)), ValueError, "episodes_per_split"),
        (lambda: bw.synth.generate(WORK / "s1", episodes_per_split=0), ValueError, "episodes_per_split"),
        (lambda: bw.synth.generate(WORK / "s1", tasks="reach,fly"), ValueError, "tasks"),
        (lambda: bw.synth.generate(WORK / "s1", fps=0), ValueError, "fps"),
        (lambda: bw.synth.generate(WORK / "s1", robot="no-such-robot", episodes_per_split=1), bw.Error,
         "no-such-robot"),
        (lambda: bw.synth.generate(None), ValueError, "out"),
        # convert.
        (lambda: bw.convert(WORK / "no-raw", WORK / "c1", format="agibot"), FileNotFoundError, "no-raw"),
        (lambda: bw.convert(RAW / "droid", WORK / "c1", format="droid", intrinsics=WORK / "no-intr.json"),
         FileNotFoundError, "no-intr.json"),
        (lambda: bw.convert(RAW / "droid", WORK / "c1", format="droid"), ValueError, "intrinsics"),
        (lambda: bw.convert(RAW / "droid", WORK / "c1", format="rlds"), ValueError, "format"),
        (lambda: bw.convert(RAW / "agibot", WORK / "c1", format="agibot", width=31), ValueError, "width"),
        (lambda: bw.convert(RAW / "agibot", WORK / "c1", format="agibot", gripper_range="abc"), ValueError,
         "gripper_range"),
        (lambda: bw.convert(RAW / "agibot", WORK / "c1", format="agibot", cameras=[1]), ValueError, "cameras"),
        # Duplicate or no cameras: the library's check, shared with the CLI.
        (lambda: bw.convert(RAW / "agibot", WORK / "c1", format="agibot", cameras="head,head"), ValueError,
         '"head" is named twice'),
        (lambda: bw.convert(RAW / "droid", WORK / "c1", format="droid", intrinsics=RAW / "droid_intrinsics.json",
                            cameras=["ext1", "ext2", "ext1"]), ValueError, '"ext1" is named twice'),
        (lambda: bw.convert(RAW / "agibot", WORK / "c1", format="agibot", cameras=" , "), ValueError,
         "at least one camera"),
        (lambda: bw.convert(RAW / "agibot", WORK / "c1", format="agibot", robot=WORK / "no.urdf"),
         FileNotFoundError, "no.urdf"),
        (lambda: bw.convert(RAW / "agibot", RAW / "droid", format="agibot"), FileExistsError, "droid"),
        (lambda: bw.convert(RAW / "droid", WORK / "c1", format="agibot"), FileNotFoundError, "proprio_stats"),
        (lambda: bw.read_episode(WORK / "no-dataset"), FileNotFoundError, "no-dataset"),
        (lambda: bw.read_episode(WORK / "synth-py", 99), bw.Error, "99"),
        (lambda: bw.read_episode(WORK / "synth-py", 0, key="observation.images.top"), ValueError, "key"),
        (lambda: bw.read_episode(WORK / "synth-py", -1), ValueError, "episode"),
    ]
    # Sizes beyond their maximum or the machine (issue 69, item 3): an
    # exception naming them, before anything of that size is allocated.
    cases += [
        (lambda: cam.rescaled(100_000, 60), ValueError, "width=100000"),
        (lambda: bw.render_masks(robot, cam.rescaled(16384, 16384), joints=np.tile(robot.home, (10_000, 1))),
         ValueError, "rendering 10000 frames of 16384x16384 pixels needs at least"),
        (lambda: wm.predict(np.broadcast_to(np.zeros((64, 96, 3), np.uint8), (5000, 64, 96, 3)),
                            np.zeros((9, 64, 96), np.uint8)), ValueError, "first_frame: a batch of 5000"),
        (lambda: wm.predict(np.zeros((64, 96, 3), np.uint8),
                            np.broadcast_to(np.zeros((9, 64, 96), np.uint8), (4097, 9, 64, 96))),
         ValueError, "masks: a batch of 4097"),
        (lambda: wm.predict(np.zeros((64, 96, 3), np.uint8), np.zeros((9, 64, 96), np.uint8), steps=10 ** 12),
         ValueError, "steps"),
    ]
    for call, kind, needle in cases:
        try:
            call()
        except kind as e:
            assert needle in str(e), f"{kind.__name__} without {needle!r}: {e}"
        else:
            raise AssertionError(f"no {kind.__name__} for {needle!r}")
