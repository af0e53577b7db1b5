"""BridgeV2W from Python: pixel-aligned embodiment masks from robot actions
(any URDF, inverse kinematics, calibrated cameras), the action-conditioned
world model, the data commands and the video metrics of the paper, over the
project's Rust core (``bridgev2w._core``).

    import bridgev2w as bw
    robot = bw.Robot("franka")                       # or bw.Robot.from_urdf(...)
    cam = bw.Camera.from_json("cam.json")            # or bw.Camera(K=..., world_from_camera=..., size=(w, h))
    masks = bw.render_masks(robot, cam, joints=q)    # uint8 [T, H, W]; q [B, T, dof] gives [B, T, H, W]
    q, residuals = robot.solve_ik(actions)           # [T, dof], one residual per frame and arm
    wm = bw.WorldModel.from_pretrained("assets/demo-model")
    video = wm.predict(first_frame, masks, steps=20, seed=0)   # uint8 [T, H, W, 3] (numpy or torch)
    bw.synth.generate("data", episodes_per_split=(4, 1, 1, 1))
    bw.convert("raw/droid", "data/droid", format="droid", intrinsics="zed.json")
    ep = bw.read_episode("data", 0)                  # frames, states, actions, camera, masks
    bw.metrics.psnr(pred, gt)
    # Rerun recordings (.rrd) of masks, predictions and episodes: bridgev2w.rerun
    # (python -m bridgev2w.rerun masks|predict|view ...; docs/guide/rerun.md)

Arrays are numpy arrays (the world model also takes and returns torch
tensors); a wrong dtype or shape is a ``ValueError`` naming the argument and
what was expected, a missing file a ``FileNotFoundError``, anything else the
library refuses a ``bridgev2w.Error``. Rendering, IK, prediction and the
data commands release the GIL; batches run on the Rust thread pool.
"""

from __future__ import annotations

import json
import numbers
import os
import warnings
from typing import NamedTuple, Optional, Sequence, Union

import numpy as np

try:  # libtorch first, from the torch the native module was built against
    import torch  # noqa: F401
except ImportError:  # the module's rpath names the build's libtorch
    pass

from . import _core, metrics  # noqa: E402
from ._core import Error  # noqa: E402

__all__ = ["Robot", "Camera", "Residual", "render_masks", "WorldModel", "metrics", "lerobot", "synth",
           "convert", "ConvertReport", "read_episode", "Episode", "calibrate", "Calibration", "evaluate_policies", "PolicyEvaluation", "Error",
           "builtin_robots"]


def _is_tensor(x) -> bool:
    return type(x).__module__.startswith("torch") and hasattr(x, "detach")


def _array(name, value):
    """``value`` as a numpy array (a torch tensor through its CPU copy, zero-copy on the CPU)."""
    if _is_tensor(value):
        return value.detach().cpu().numpy()
    try:
        return np.asarray(value)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name}: expected an array, got {type(value).__name__} ({e})") from None


def _float_array(name, value, ndims, last=None):
    """A float64 array of ``ndims`` (an int or a tuple of allowed ones) dimensions."""
    a = _array(name, value)
    if a.dtype.kind not in "fiu":
        raise ValueError(f"{name}: expected a numeric array, got dtype {a.dtype}")
    ndims = (ndims,) if isinstance(ndims, int) else tuple(ndims)
    if a.ndim not in ndims:
        want = " or ".join(str(n) for n in ndims)
        raise ValueError(f"{name}: expected {want} dimensions, got shape {a.shape}")
    if last is not None and a.shape[-1] != last:
        raise ValueError(f"{name}: expected {last} values per row, got shape {a.shape}")
    if a.size == 0:
        raise ValueError(f"{name}: expected at least one frame, got shape {a.shape}")
    a = a.astype(np.float64)
    if not np.isfinite(a).all():
        raise ValueError(f"{name}: holds NaN or infinite values")
    return a


def _int(name, value, lo, hi=None, even=False):
    """An int within [lo, hi] (and even), else a ValueError naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name}: expected an integer, got {value!r}")
    value = int(value)
    if value < lo or (hi is not None and value > hi) or (even and value % 2):
        rng = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise ValueError(f"{name}: {value}, expected an {'even ' if even else ''}integer {rng}")
    return value


def _float(name, value):
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not np.isfinite(value):
        raise ValueError(f"{name}: expected a finite number, got {value!r}")
    return float(value)


def _path(name, value, optional=False):
    if value is None and optional:
        return None
    if not isinstance(value, (str, os.PathLike)):
        raise ValueError(f"{name}: expected a path (str or os.PathLike), got {type(value).__name__}")
    return os.fspath(value)


class Residual(NamedTuple):
    """What the IK left of one arm's target in one frame."""

    frame: int
    arm: str
    position_error_m: float
    rotation_error_rad: float
    reached: bool


class LinkMesh(NamedTuple):
    """A link's visual geometry, as :meth:`Robot.link_meshes` gives it."""

    name: str
    #: The value ``render_masks(..., labels=True)`` writes for this link.
    label: int
    #: RGB8: the label's colour in the overlays of ``bridgev2w masks``.
    color: tuple
    #: float32 ``[N, 3]``: metres, in the link frame.
    vertices: np.ndarray
    #: uint32 ``[M, 3]``: vertex indices.
    triangles: np.ndarray


class Robot:
    """A robot: a built-in one by name (``franka``, ``dual-arm``, ``agibot-g1``, ``franka-robotiq``), or a URDF
    with :meth:`from_urdf`."""

    def __init__(self, name: str = "franka", *, _core_robot=None):
        if _core_robot is None and not isinstance(name, str):
            raise ValueError(f"name: expected a built-in robot's name ({builtin_robots()}), got {name!r}")
        self._r = _core_robot if _core_robot is not None else _core.Robot(name)

    @classmethod
    def from_urdf(cls, path, mesh_paths: Sequence[str] = (), ee_links: Sequence[str] = (),
                  gripper_joints: Sequence[str] = ()) -> "Robot":
        """A robot from a URDF file; ``mesh_paths`` are searched for
        ``package://`` and relative meshes; ``ee_links`` (one per arm, in
        action order) and ``gripper_joints`` enable end-effector actions."""
        if isinstance(mesh_paths, (str, os.PathLike)):
            mesh_paths = [mesh_paths]
        return cls(_core_robot=_core.Robot.from_urdf(
            _path("path", path), [_path("mesh_paths", p) for p in mesh_paths], list(ee_links),
            list(gripper_joints)))

    @property
    def name(self) -> str:
        return self._r.name

    @property
    def joint_names(self) -> list[str]:
        """The actuated joints, in the order of joint arrays."""
        return self._r.joint_names

    @property
    def action_dim(self) -> int:
        """Values per frame of end-effector actions: 7 per arm
        (x, y, z, roll, pitch, yaw in the base frame, gripper 0 open .. 1 closed)."""
        return self._r.action_dim

    @property
    def home(self) -> np.ndarray:
        return np.array(self._r.home)

    def link_labels(self) -> dict[int, str]:
        """The link of each label value that ``render_masks(..., labels=True)`` writes."""
        return dict(self._r.link_labels())

    def link_meshes(self) -> list["LinkMesh"]:
        """The visual mesh of every link with geometry (the links of
        :meth:`link_labels`, in that order) as a :class:`LinkMesh`: vertices
        float32 ``[N, 3]`` in metres in the link frame, triangles uint32 ``[M, 3]``."""
        out = []
        for name, label, color, v, t in self._r.link_meshes():
            out.append(LinkMesh(name, int(label), tuple(color), np.frombuffer(v, dtype="<f4").reshape(-1, 3),
                                np.frombuffer(t, dtype="<u4").reshape(-1, 3)))
        return out

    def link_poses(self, joints) -> np.ndarray:
        """Forward kinematics: ``world_from_link`` float64 ``[T, L, 4, 4]``
        ("world" is the robot's base frame) of the ``L`` links of
        :meth:`link_meshes`, in that order, for ``joints`` ``[T, dof]`` (a
        single frame ``[dof]`` gives ``[L, 4, 4]``), checked as
        :func:`render_masks` checks them (finite, within the joint limits)."""
        q = _float_array("joints", joints, (1, 2), len(self.joint_names))
        single = q.ndim == 1
        q = q[None] if single else q
        poses = np.frombuffer(self._r.link_poses(q.tolist()), dtype="<f8").reshape(len(q), -1, 4, 4)
        return poses[0] if single else poses

    def convert_action_links(self, actions, from_links, to_links):
        """End-effector ``actions`` ``[T, action_dim]`` given as poses of
        ``from_links`` (one link name per arm) re-expressed as poses of
        ``to_links``: e.g. recorded flange poses (DROID's ``panda_link8``,
        AgiBot World's ``arm_l_link7``/``arm_r_link7``) as the TCP poses this
        robot's actions use by default, or back. The links of each arm must be
        rigidly attached to each other; grippers are copied."""
        a = _float_array("actions", actions, (2,), self.action_dim)
        out = self._r.convert_action_links(a.tolist(), list(from_links), list(to_links))
        return np.array(out, dtype=np.float64).reshape(a.shape)

    def solve_ik(self, actions, *, allow_residual: bool = False):
        """Joint positions ``[T, dof]`` for end-effector ``actions``
        ``[T, action_dim]`` (each frame warm-started from the previous one),
        and a :class:`Residual` per frame and arm. A batch of sequences
        ``[B, T, action_dim]`` gives ``[B, T, dof]`` and a list of residual
        lists, the sequences solved in parallel on the Rust thread pool. An
        unreachable target is a ``bridgev2w.Error`` unless ``allow_residual``."""
        a = _float_array("actions", actions, (2, 3), self.action_dim)
        single = a.ndim == 2
        seqs = a[None] if single else a
        out = self._r.solve_ik(seqs.tolist(), bool(allow_residual))
        q = np.array([q for q, _ in out], dtype=np.float64).reshape(len(seqs), seqs.shape[1], -1)
        res = [[Residual(*r) for r in rs] for _, rs in out]
        return (q[0], res[0]) if single else (q, res)

    def __repr__(self) -> str:
        return repr(self._r)


class Camera:
    """A calibrated camera: pinhole intrinsics ``K``, optional OpenCV
    distortion ``dist`` (k1, k2, p1, p2, k3), the pose ``world_from_camera``
    (4x4, OpenCV axes: x right, y down, z forward) and ``size`` (width, height)."""

    def __init__(self, K=None, world_from_camera=None, size=None, dist=None, *, _core_camera=None):
        if _core_camera is not None:
            self._c = _core_camera
            return
        if K is None or world_from_camera is None or size is None:
            raise ValueError("Camera: give K, world_from_camera and size (or use Camera.from_json)")
        k = _float_array("K", K, 2)
        if k.shape != (3, 3):
            raise ValueError(f"K: expected a 3x3 matrix, got shape {k.shape}")
        pose = _float_array("world_from_camera", world_from_camera, 2)
        if pose.shape != (4, 4):
            raise ValueError(f"world_from_camera: expected a 4x4 matrix, got shape {pose.shape}")
        if not isinstance(size, (tuple, list)) or len(size) != 2:
            raise ValueError(f"size: expected (width, height), got {size!r}")
        width, height = _int("size[0] (width)", size[0], 1), _int("size[1] (height)", size[1], 1)
        spec = {
            "fx": k[0, 0], "fy": k[1, 1], "cx": k[0, 2], "cy": k[1, 2],
            "width": width, "height": height,
            "world_from_camera": pose.tolist(),
        }
        if dist is not None:
            d = _float_array("dist", dist, 1)
            if d.shape[0] not in (4, 5):
                raise ValueError(f"dist: expected 4 or 5 coefficients (k1, k2, p1, p2[, k3]), got {d.shape[0]}")
            names = ["k1", "k2", "p1", "p2", "k3"]
            spec["distortion"] = {n: float(v) for n, v in zip(names, d)}
        self._c = _core.Camera.from_json_str(json.dumps(spec), "Camera(...)")

    @classmethod
    def from_json(cls, path) -> "Camera":
        """A camera from the JSON file ``bridgev2w masks --camera`` reads."""
        return cls(_core_camera=_core.Camera.from_json(_path("path", path)))

    def to_json(self) -> str:
        return self._c.to_json()

    def rescaled(self, width: int, height: int) -> "Camera":
        """This camera with its intrinsics scaled to ``width`` x ``height``."""
        return Camera(_core_camera=self._c.rescaled(_int("width", width, 1), _int("height", height, 1)))

    def with_poses(self, poses) -> "Camera":
        """These intrinsics on a moving camera: ``poses`` ``[T, 4, 4]``, the
        ``world_from_camera`` of each frame (e.g. AgiBot World's per-frame
        camera-to-base extrinsics, or DROID's recorded wrist-camera poses)."""
        p = _float_array("poses", poses, 3)
        if p.shape[1:] != (4, 4) or p.shape[0] == 0:
            raise ValueError(f"poses: expected [T, 4, 4], got shape {p.shape}")
        return Camera(_core_camera=self._c.with_poses(p.tolist()))

    def mounted(self, link: str, link_from_camera=None) -> "Camera":
        """These intrinsics on a camera mounted on robot link ``link`` at
        ``link_from_camera`` (4x4, default identity), posed every frame by
        the robot's forward kinematics (e.g. ``agibot-g1``'s
        ``head_camera_optical``)."""
        m = None
        if link_from_camera is not None:
            m = _float_array("link_from_camera", link_from_camera, 2)
            if m.shape != (4, 4):
                raise ValueError(f"link_from_camera: expected a 4x4 matrix, got shape {m.shape}")
            m = m.tolist()
        return Camera(_core_camera=self._c.mounted(str(link), m))

    @property
    def kind(self) -> str:
        """``"fixed"``, ``"per_frame"`` or ``"mounted"``."""
        return self._c.kind

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels."""
        return self._c.size

    @property
    def K(self) -> np.ndarray:
        """The pinhole intrinsics, float64 3x3 (pixel centres at integer coordinates)."""
        fx, fy, cx, cy = self._c.intrinsics
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @property
    def world_from_camera(self) -> np.ndarray:
        """The pose, float64 4x4 (OpenCV camera axes: x right, y down, z forward)."""
        return np.array(self._c.world_from_camera, dtype=np.float64)

    @property
    def dist(self) -> Optional[np.ndarray]:
        """The distortion ``(k1, k2, p1, p2, k3)``, or None for an ideal pinhole."""
        d = self._c.distortion
        return None if d is None else np.array(d, dtype=np.float64)

    def __repr__(self) -> str:
        return repr(self._c)


def render_masks(robot: Robot, camera: Union[Camera, Sequence[Camera]], *, joints=None, actions=None,
                 labels: bool = False, depth: bool = False, allow_residual: bool = False):
    """The robot's masks as the camera sees them, one per frame: uint8
    ``[T, H, W]`` (1 = robot), or with ``labels=True`` the uint16 per-link
    labels (see :meth:`Robot.link_labels`). Give ``joints`` ``[T, dof]`` or
    end-effector ``actions`` ``[T, action_dim]`` (solved by IK first). With
    ``depth=True`` returns ``(masks, depth)``, depth float32 metres along the
    camera's z, inf where no robot is.

    A batch of sequences, ``joints`` ``[B, T, dof]`` or ``actions`` ``[B, T,
    action_dim]``, gives ``[B, T, H, W]``: every frame of every sequence is
    rendered in parallel on the Rust thread pool. ``camera`` is then one
    camera for all or a list of ``B`` cameras of one size."""
    if not isinstance(robot, Robot):
        raise ValueError(f"robot: expected a bridgev2w.Robot, got {type(robot).__name__}")
    if (joints is None) == (actions is None):
        raise ValueError("render_masks: give exactly one of joints= and actions=")
    if actions is not None:
        q, _ = robot.solve_ik(actions, allow_residual=allow_residual)
    else:
        q = _float_array("joints", joints, (2, 3), len(robot.joint_names))
    single = q.ndim == 2
    seqs = q[None] if single else q
    for b, seq in enumerate(seqs):
        for joint, n, worst, frame, lo, hi in robot._r.limit_violations(seq.tolist()):
            where = f"joints[{b}]" if not single else "joints"
            warnings.warn(f"{where}: joint {joint!r}: {n} frame(s) outside its limits [{lo}, {hi}], worst {worst} "
                          f"(frame {frame}); rendered as given, not clamped", stacklevel=2)
    if isinstance(camera, Camera):
        cams = [camera] * len(seqs)
    elif isinstance(camera, (list, tuple)) and all(isinstance(c, Camera) for c in camera):
        cams = list(camera)
        if single or len(cams) != len(seqs):
            raise ValueError(f"camera: expected one Camera or a list of one per sequence ({len(seqs)} "
                             f"for joints/actions [B, T, ...]), got {len(cams)}")
    else:
        raise ValueError(f"camera: expected a bridgev2w.Camera (or a list of them), got {type(camera).__name__}")
    w, h = cams[0].size
    lab, dep = _core.render(robot._r, [c._c for c in cams], seqs.tolist(), bool(depth))
    shape = (len(seqs), seqs.shape[1], h, w)
    lab = np.frombuffer(lab, dtype="<u2").reshape(shape)
    out = lab if labels else (lab > 0).astype(np.uint8)
    if single:
        out = out[0]
    if depth:
        d = np.frombuffer(dep, dtype="<f4").reshape(shape)
        return out, (d[0] if single else d)
    return out


def _batch_within(name, a, batch_ndim):
    """A batch ``a`` (``batch_ndim`` dimensions) of at most ``MAX_PREDICT_BATCH`` items, checked before any copy."""
    if a.ndim == batch_ndim and len(a) > _core.MAX_PREDICT_BATCH:
        raise ValueError(f"{name}: a batch of {len(a)}, at most {_core.MAX_PREDICT_BATCH} clips per call "
                         f"(predict them in several calls)")


def _frames(name, a, shape, batch_ndim):
    """``a`` (uint8 ``shape`` or ``[B, *shape]``) as a contiguous batch."""
    if a.dtype != np.uint8:
        raise ValueError(f"{name}: expected uint8 {list(shape)} (or [B, ...]), got dtype {a.dtype}")
    if a.ndim not in (batch_ndim - 1, batch_ndim) or tuple(a.shape[-len(shape):]) != tuple(shape):
        raise ValueError(f"{name}: expected {list(shape)} or [B, {', '.join(map(str, shape))}] for this model, "
                         f"got shape {tuple(a.shape)}")
    return np.ascontiguousarray(a if a.ndim == batch_ndim else a[None])


class WorldModel:
    """BridgeV2W: from a first frame and the embodiment masks of the actions
    to the video they cause."""

    def __init__(self, core):
        self._m = core

    @classmethod
    def from_pretrained(cls, model, *, weights=None, device: str = "cpu", precision: str = "f32",
                        seed: int = 0, vae_tile: str = "auto") -> "WorldModel":
        """``model``: a folder as ``assets/demo-model`` (``backbone/`` and
        ``bridgev2w.safetensors``), a diffusers CogVideoX-I2V folder or Hub
        name (from the local Hugging Face cache, offline) with BridgeV2W
        ``weights``, or ``random:PRESET``. ``device``: ``cpu``, ``cuda``,
        ``cuda:N`` or ``auto``; ``precision``: ``f32`` or ``bf16``; ``seed``
        initialises a ``random:`` model (as ``bridgev2w predict --seed``);
        ``vae_tile``: the VAE's spatial tiles, ``auto`` (its own tiles above
        256x256 pixels, as ``bridgev2w predict``), ``off`` (whole frames) or
        ``"HxW"`` pixels (e.g. ``"144x200"`` for a smaller decode peak, as
        ``predict --vae-tile``)."""
        return cls(_core.WorldModel.from_pretrained(
            _path("model", model), _path("weights", weights, optional=True), str(device), str(precision),
            _int("seed", seed, -2 ** 63, 2 ** 63 - 1), str(vae_tile)))

    @property
    def resolution(self) -> tuple[int, int]:
        """``(height, width)``."""
        return self._m.resolution

    @property
    def clip_frames(self) -> int:
        """Frames per prediction (masks per call)."""
        return self._m.clip_frames

    def predict(self, first_frame, masks, *, steps: int = 20, seed: int = 0, guidance: float = 1.0):
        """The predicted video, uint8 ``[T, H, W, 3]`` (frame 0 is the first
        frame's reconstruction), from ``first_frame`` uint8 ``[H, W, 3]`` and
        ``masks`` ``[T, H, W]``, sampled with ``steps`` denoising steps from
        noise seed ``seed``. Masks are link labels (integers 0..255: 0 the
        background, l the link labelled l, as ``render_masks`` and
        ``bridgev2w masks`` write them) or bool / 0-1 masks; a model with
        binary mask coding sees robot vs background, one with link-coded masks
        (``model.mask_coding = "links"``) needs the labels.

        A batch, ``first_frame`` ``[B, H, W, 3]`` and/or ``masks`` ``[B, T,
        H, W]`` (one side may be unbatched: it is shared), gives ``[B, T, H,
        W, 3]`` from one batched run of the model; each item is the video a
        batch of one with the same seed gives. numpy in, numpy out; a torch
        tensor in (either argument), a torch tensor out, on the first such
        argument's device. The GIL is released while the model runs."""
        h, w = self.resolution
        t = self.clip_frames
        as_torch = next((x for x in (first_frame, masks) if _is_tensor(x)), None)
        f = _array("first_frame", first_frame)
        single = f.ndim == 3
        _batch_within("first_frame", f, 4)
        f = _frames("first_frame", f, (h, w, 3), 4)
        m = _array("masks", masks)
        _batch_within("masks", m, 4)
        if m.dtype.kind == "f" and np.isin(m, (0.0, 1.0)).all():
            m = m.astype(np.uint8)
        if m.dtype.kind not in "biu":
            raise ValueError(f"masks: expected link labels (integers 0..255) or bool masks, got dtype {m.dtype}")
        if m.dtype.kind != "b" and m.size and (m.min() < 0 or m.max() > 255):
            raise ValueError(f"masks: link labels must lie in 0..255, got values {m.min()}..{m.max()}")
        if m.ndim not in (3, 4) or tuple(m.shape[-3:]) != (t, h, w):
            raise ValueError(f"masks: expected [{t}, {h}, {w}] or [B, {t}, {h}, {w}] for this model, "
                             f"got shape {tuple(m.shape)}")
        single = single and m.ndim == 3
        m = m if m.ndim == 4 else m[None]
        b = max(len(f), len(m))
        if len(f) not in (1, b) or len(m) not in (1, b):
            raise ValueError(f"first_frame {len(f)} and masks {len(m)}: expected batches of one size")
        f = np.broadcast_to(f, (b, h, w, 3))
        m = np.broadcast_to(m, (b, t, h, w))
        video = self._m.predict(np.ascontiguousarray(f).tobytes(), m.astype(np.uint8).tobytes(), b,
                                _int("steps", steps, 1), _int("seed", seed, 0, 2 ** 64 - 1),
                                _float("guidance", guidance))
        out = np.frombuffer(video, dtype=np.uint8).reshape(b, t, h, w, 3)
        if single:
            out = out[0]
        if as_torch is not None:
            import torch

            return torch.from_numpy(out).to(as_torch.device)
        return out

    def predict_files(self, image, masks, out, *, steps: int = 50, seed: int = 42, guidance: float = 6.0,
                      batch_size: int = 4, overwrite: bool = False) -> dict:
        """``bridgev2w predict`` from files, by the same library call: the
        first frame ``image`` (any image, resized to the model's size), mask
        files ``masks`` (one path, a folder of ``.npy`` files, or a list of
        either: link labels uint8/uint16 as a dataset's ``labels/`` or
        ``bridgev2w masks``' ``labels.npy``, or binary 0/1 or 0/255 masks),
        predictions in batches of ``batch_size``, written to ``out`` as the
        CLI writes them (``frames/``, ``video.npy``, ``video.mp4`` per clip,
        ``clips.json`` when there are several). Returns ``{"out", "clips"
        [(name or None, mask file)], "frames", "seconds"}``. A model with
        link-coded masks refuses binary masks, naming its coding
        (``ValueError``); a missing file is a ``FileNotFoundError``."""
        paths = masks if isinstance(masks, (list, tuple)) else [masks]
        out_dir, clips, frames, seconds = self._m.predict_files(
            _path("image", image), [_path(f"masks[{i}]", m) for i, m in enumerate(paths)], _path("out", out),
            _int("steps", steps, 1), _int("seed", seed, 0, 2 ** 64 - 1), _float("guidance", guidance),
            _int("batch_size", batch_size, 1), bool(overwrite))
        return {"out": out_dir, "clips": clips, "frames": frames, "seconds": seconds}

    def __repr__(self) -> str:
        return repr(self._m)


def read_trajectory(path) -> np.ndarray:
    """The rows of a joint or action file as ``bridgev2w masks --joints`` and
    ``--actions`` read it (a JSON array of arrays, a CSV with an optional
    header row, or a 1-D/2-D ``.npy``): float64 ``[T, n]``. A missing file is
    a ``FileNotFoundError``, a malformed one a ``ValueError`` naming it."""
    return np.array(_core.read_trajectory(_path("path", path)), dtype=np.float64)


def builtin_robots() -> str:
    """The names of the built-in robots."""
    return _core.builtin_robots()


from . import lerobot, synth  # noqa: E402  (use the names above)
from ._data import ConvertReport, Episode, convert, read_episode  # noqa: E402
from ._calibrate import Calibration, calibrate  # noqa: E402
from ._policy import PolicyEvaluation, evaluate_policies  # noqa: E402
