"""``python -m bridgev2w.rerun``: the command line of :mod:`bridgev2w.rerun`.

    python -m bridgev2w.rerun masks --robot franka --camera cam.json --actions actions.json --rerun masks.rrd
    python -m bridgev2w.rerun predict --model assets/demo-model --image first.png --masks labels.npy \\
        --truth truth.npy --robot franka --rerun prediction.rrd
    python -m bridgev2w.rerun predict --video pred --masks labels.npy --rerun prediction.rrd
    python -m bridgev2w.rerun view data --episode 0 --rerun episode.rrd

The inputs are those of ``bridgev2w masks`` and ``bridgev2w predict`` (a
prediction is either made here, ``--model``, or read from the folder
``bridgev2w predict`` writes, ``--video``); the output is one ``.rrd`` file.
"""

from __future__ import annotations

import argparse
import glob
import os
import sys

import numpy as np

from .. import Camera, Error, Robot, WorldModel
from .. import rerun as bwr


def _robot(a) -> Robot:
    return bwr._robot(a.robot, mesh_paths=a.mesh_path, ee_links=a.ee_link, gripper_joints=a.gripper_joint)


def _npy(flag, path):
    """An array from a ``.npy`` file, errors naming the flag and the file."""
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{flag} {path}: no such .npy file")
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise ValueError(f"{flag} {path}: not a readable .npy array ({e})") from None


def _png(flag, path):
    """uint8 ``[H, W, 3]`` from a PNG/JPEG file."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"))
    except FileNotFoundError:
        raise FileNotFoundError(f"{flag} {path}: no such image file") from None
    except (OSError, UnidentifiedImageError) as e:
        raise ValueError(f"{flag} {path}: not a readable image ({e})") from None


def _video(flag, path):
    """uint8 ``[T, H, W, 3]`` from a ``.npy`` file, a folder holding
    ``video.npy`` (what ``bridgev2w predict`` writes), or a folder of PNG frames."""
    if os.path.isdir(path):
        if os.path.isfile(os.path.join(path, "clips.json")):
            raise ValueError(f"{flag} {path}: holds several clips (clips.json); give one clip's folder, "
                             f"e.g. {os.path.join(path, 'NAME')}")
        if os.path.isfile(os.path.join(path, "video.npy")):
            return _npy(flag, os.path.join(path, "video.npy"))
        frames = sorted(glob.glob(os.path.join(path, "*.png")))
        if not frames:
            raise FileNotFoundError(f"{flag} {path}: no video.npy and no PNG frames in this folder")
        return np.stack([_png(flag, f) for f in frames])
    return _npy(flag, path)


def _first_frame(path, resolution):
    """The first frame (PNG/JPEG or ``.npy``), resized to ``resolution`` ``(H, W)``
    if needed (with a note, as ``bridgev2w predict``)."""
    img = _npy("--image", path) if path.endswith(".npy") else _png("--image", path)
    h, w = resolution
    if img.ndim == 3 and img.dtype == np.uint8 and img.shape[:2] != (h, w) and img.shape[2] == 3:
        from PIL import Image

        print(f"note: resizing {path} from {img.shape[1]}x{img.shape[0]} to the model's {w}x{h} (WxH)",
              file=sys.stderr)
        img = np.asarray(Image.fromarray(img).resize((w, h), Image.BILINEAR))
    return img


def masks(a):
    robot = _robot(a)
    camera = Camera.from_json(a.camera)
    if (a.width is None) != (a.height is None):
        raise ValueError("--width and --height: give both (the camera is rescaled) or neither (its own size)")
    if a.width is not None:
        camera = camera.rescaled(a.width, a.height)
    return bwr.record_masks(a.rerun, robot, camera, joints=a.joints, actions=a.actions,
                            allow_residual=a.allow_ik_residual, overwrite=a.overwrite)


def predict(a):
    bwr._out_path(a.rerun, a.overwrite)  # before minutes of prediction
    masks = _npy("--masks", a.masks)
    robot = _robot(a) if a.robot is not None else None
    truth = None if a.truth is None else _video("--truth", a.truth)
    if a.model is not None:
        if a.image is None:
            raise ValueError("--image: the first frame is needed to predict with --model")
        wm = WorldModel.from_pretrained(a.model, weights=a.weights, device=a.device, precision=a.precision,
                                        seed=a.seed)
        first = _first_frame(a.image, wm.resolution)
        video = wm.predict(first, masks, steps=a.steps, seed=a.seed, guidance=a.guidance)
    else:
        video = _video("--video", a.video)
        first = None if a.image is None else _first_frame(a.image, video.shape[1:3])
    return bwr.record_prediction(a.rerun, video, masks=masks, truth=truth, first_frame=first, robot=robot,
                                 overwrite=a.overwrite)


def view(a):
    robot = _robot(a) if a.robot is not None else None
    return bwr.record_episode(a.rerun, a.dataset, a.episode, robot=robot, key=a.key, overwrite=a.overwrite)


def _robot_args(p, required):
    p.add_argument("--robot", required=required,
                   help="built-in robot (bridgev2w.builtin_robots()) or a URDF file")
    p.add_argument("--mesh-path", action="append", default=[], metavar="DIR",
                   help="folder searched for package:// and relative mesh paths (repeatable)")
    p.add_argument("--ee-link", action="append", default=[], metavar="LINK",
                   help="end-effector link for --actions with a URDF file (one per arm, in action order)")
    p.add_argument("--gripper-joint", action="append", default=[], metavar="JOINT",
                   help="gripper joint of each arm (URDF files; the order of --ee-link)")


def _out_args(p):
    p.add_argument("--rerun", required=True, metavar="OUT.rrd",
                   help="the recording (written to OUT.rrd.tmp-PID, then renamed)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing OUT.rrd")


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m bridgev2w.rerun",
                                 description="Rerun recordings (.rrd) of masks, predictions and dataset episodes; "
                                             "open one with `rerun OUT.rrd`.")
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("masks", help="a robot's links, camera and link masks for joints or actions "
                                     "(the inputs of `bridgev2w masks`)")
    _robot_args(p, required=True)
    p.add_argument("--camera", required=True,
                   help="camera JSON (fx, fy, cx, cy, width, height, world_from_camera or extrinsics_xyz_rpy)")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--joints", help="joint positions per frame (JSON, CSV or .npy), in the robot's joint order")
    g.add_argument("--actions", help="end-effector actions per frame (7 per arm: x y z roll pitch yaw gripper)")
    p.add_argument("--width", type=int, help="render at this width (with --height; default: the camera's)")
    p.add_argument("--height", type=int, help="render at this height (with --width)")
    p.add_argument("--allow-ik-residual", action="store_true",
                   help="render frames whose IK target is out of reach instead of failing")
    _out_args(p)
    p.set_defaults(run=masks)

    p = sub.add_parser("predict", help="a predicted video beside the true one and the masks "
                                       "(the inputs of `bridgev2w predict`, or its output folder)")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--model", help="predict here: a model folder (as assets/demo-model), a diffusers folder "
                                   "with --weights, or random:PRESET")
    g.add_argument("--video", help="a prediction already made: the output folder of `bridgev2w predict` "
                                   "(its video.npy), or a uint8 [T, H, W, 3] .npy")
    p.add_argument("--weights", help="BridgeV2W weights for a diffusers --model")
    p.add_argument("--image", help="the first frame (PNG/JPEG or .npy); needed with --model")
    p.add_argument("--masks", required=True,
                   help="masks .npy [T, H, W]: masks.npy (binary) or labels.npy (link labels) of `bridgev2w masks`")
    p.add_argument("--truth", help="the true video: a uint8 [T, H, W, 3] .npy or a folder of PNG frames")
    _robot_args(p, required=False)
    p.add_argument("--steps", type=int, default=50, help="denoising steps (as bridgev2w predict)")
    p.add_argument("--guidance", type=float, default=6.0, help="classifier-free guidance scale (1 = off)")
    p.add_argument("--seed", type=int, default=42, help="noise seed (and a random: model's)")
    p.add_argument("--device", default="auto", help="cpu, cuda, cuda:N or auto")
    p.add_argument("--precision", default="f32", help="f32 or bf16")
    _out_args(p)
    p.set_defaults(run=predict)

    p = sub.add_parser("view", help="an episode of a converted or synthetic dataset")
    p.add_argument("dataset", help="a LeRobot dataset folder (bridgev2w synth or convert)")
    p.add_argument("--episode", type=int, default=0, help="the episode index (default 0)")
    p.add_argument("--key", help="the video (default the first)")
    _robot_args(p, required=False)
    _out_args(p)
    p.set_defaults(run=view)
    return ap


def main(argv=None) -> int:
    a = parser().parse_args(argv)
    try:
        rec = a.run(a)
    except (ValueError, OSError, Error, ImportError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(f"wrote {rec.out}: {rec.frames} frames, {len(rec.entities)} entities (rerun {rec.out} opens it)")
    return 0


if __name__ == "__main__":  # python -m bridgev2w.rerun
    sys.exit(main())
