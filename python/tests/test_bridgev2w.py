"""Tests of the Python package against the command line (the same Rust
code reached another way) and closed forms. Run by
crates/cli/tests/python_package.rs after `pip install ./python`:

  python python/tests/test_bridgev2w.py BRIDGEV2W_BINARY WORKDIR
"""

import json
import pathlib
import subprocess
import sys

import numpy as np

import bridgev2w as bw

BIN, WORK = sys.argv[1], pathlib.Path(sys.argv[2])


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
    # The shipped demo model, from its folder.
    demo = bw.WorldModel.from_pretrained(pathlib.Path(__file__).resolve().parents[2] / "assets" / "demo-model")
    assert demo.resolution == (64, 96) and demo.clip_frames == 9, demo
    v = demo.predict(np.zeros((64, 96, 3), np.uint8), np.zeros((9, 64, 96)), steps=1)
    assert v.shape == (9, 64, 96, 3)
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


def test_bad_input_is_a_python_exception_naming_it():
    robot, cam = bw.Robot("franka"), camera()
    cases = [
        (lambda: bw.render_masks(robot, cam, joints=np.zeros((2, 3))), ValueError, "joints"),
        (lambda: bw.render_masks(robot, cam, joints=np.full((1, len(robot.joint_names)), np.nan)), ValueError, "NaN"),
        (lambda: bw.render_masks(robot, cam), ValueError, "joints= and actions="),
        (lambda: bw.render_masks(robot, cam, joints=np.full((1, 8), 0.5)), ValueError, "outside its limits"),
        (lambda: robot.solve_ik(np.zeros((2, 6))), ValueError, "actions"),
        (lambda: bw.Camera.from_json(WORK / "missing.json"), FileNotFoundError, "missing.json"),
        (lambda: bw.Camera(K=np.eye(2), world_from_camera=np.eye(4), size=(4, 4)), ValueError, "K"),
        (lambda: bw.Robot("no-such-robot"), bw.Error, "no-such-robot"),
        (lambda: bw.Robot.from_urdf(WORK / "missing.urdf"), FileNotFoundError, "missing.urdf"),
        (lambda: bw.metrics.psnr(np.zeros((4, 4, 3)), np.zeros((4, 4, 3))), ValueError, "uint8"),
        (lambda: bw.metrics.mask_iou(np.zeros(3), np.zeros(4)), ValueError, "same shape"),
    ]
    for call, kind, needle in cases:
        try:
            call()
        except kind as e:
            assert needle in str(e), f"{kind.__name__} without {needle!r}: {e}"
        else:
            raise AssertionError(f"no {kind.__name__} for {needle!r}")


if __name__ == "__main__":
    tests = [v for k, v in sorted(globals().items()) if k.startswith("test_")]
    for t in tests:
        t()
        print(f"ok {t.__name__}")
    print(f"{len(tests)} passed")
