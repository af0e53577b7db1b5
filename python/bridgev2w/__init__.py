"""BridgeV2W from Python: pixel-aligned embodiment masks from robot actions
(any URDF, inverse kinematics, calibrated cameras) and the video metrics of
the paper, over the project's Rust core (``bridgev2w._core``).

    import bridgev2w as bw
    robot = bw.Robot("franka")                       # or bw.Robot.from_urdf(...)
    cam = bw.Camera.from_json("cam.json")            # or bw.Camera(K=..., world_from_camera=..., size=(w, h))
    masks = bw.render_masks(robot, cam, joints=q)    # uint8 [T, H, W]
    q, residuals = robot.solve_ik(actions)           # [T, dof], one residual per frame and arm
    bw.metrics.psnr(pred, gt)

Arrays are numpy arrays; a wrong dtype or shape is a ``ValueError`` naming
the argument, a missing file a ``FileNotFoundError``, anything else the
library refuses a ``bridgev2w.Error``. Rendering and IK release the GIL.
"""

from __future__ import annotations

import json
from typing import NamedTuple, Optional, Sequence

import numpy as np

try:  # libtorch first, from the torch the native module was built against
    import torch  # noqa: F401
except ImportError:  # the module's rpath names the build's libtorch
    pass

from . import _core, metrics  # noqa: E402
from ._core import Error  # noqa: E402

__all__ = ["Robot", "Camera", "Residual", "render_masks", "WorldModel", "metrics", "lerobot", "Error",
           "builtin_robots"]


def _float_array(name, value, ndim, last=None):
    a = np.asarray(value)
    if a.dtype.kind not in "fiu":
        raise ValueError(f"{name}: expected a numeric array, got dtype {a.dtype}")
    if a.ndim != ndim:
        raise ValueError(f"{name}: expected {ndim} dimensions, got shape {a.shape}")
    if last is not None and a.shape[-1] != last:
        raise ValueError(f"{name}: expected {last} values per row, got shape {a.shape}")
    a = a.astype(np.float64)
    if not np.isfinite(a).all():
        raise ValueError(f"{name}: holds NaN or infinite values")
    return a


class Residual(NamedTuple):
    """What the IK left of one arm's target in one frame."""

    frame: int
    arm: str
    position_error_m: float
    rotation_error_rad: float
    reached: bool


class Robot:
    """A robot: a built-in one by name (``franka``, ``agibot-g1``), or a URDF
    with :meth:`from_urdf`."""

    def __init__(self, name: str = "franka", *, _core_robot=None):
        self._r = _core_robot if _core_robot is not None else _core.Robot(name)

    @classmethod
    def from_urdf(cls, path, mesh_paths: Sequence[str] = (), ee_links: Sequence[str] = (),
                  gripper_joints: Sequence[str] = ()) -> "Robot":
        """A robot from a URDF file; ``mesh_paths`` are searched for
        ``package://`` and relative meshes; ``ee_links`` (one per arm, in
        action order) and ``gripper_joints`` enable end-effector actions."""
        return cls(_core_robot=_core.Robot.from_urdf(
            str(path), [str(p) for p in mesh_paths], list(ee_links), list(gripper_joints)))

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

    def solve_ik(self, actions, *, allow_residual: bool = False):
        """Joint positions ``[T, dof]`` for end-effector ``actions``
        ``[T, action_dim]`` (each frame warm-started from the previous one), and
        a :class:`Residual` per frame and arm. An unreachable target is a
        ``bridgev2w.Error`` unless ``allow_residual``."""
        a = _float_array("actions", actions, 2, self.action_dim)
        q, res = self._r.solve_ik(a.tolist(), allow_residual)
        return np.array(q, dtype=np.float64).reshape(len(q), -1), [Residual(*r) for r in res]

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
        if len(size) != 2:
            raise ValueError(f"size: expected (width, height), got {size!r}")
        spec = {
            "fx": k[0, 0], "fy": k[1, 1], "cx": k[0, 2], "cy": k[1, 2],
            "width": int(size[0]), "height": int(size[1]),
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
        return cls(_core_camera=_core.Camera.from_json(str(path)))

    def to_json(self) -> str:
        return self._c.to_json()

    def rescaled(self, width: int, height: int) -> "Camera":
        """This camera with its intrinsics scaled to ``width`` x ``height``."""
        return Camera(_core_camera=self._c.rescaled(int(width), int(height)))

    @property
    def size(self) -> tuple[int, int]:
        return self._c.size

    def __repr__(self) -> str:
        return repr(self._c)


def render_masks(robot: Robot, camera: Camera, *, joints=None, actions=None, labels: bool = False,
                 depth: bool = False, allow_residual: bool = False):
    """The robot's masks as the camera sees them, one per frame: uint8
    ``[T, H, W]`` (1 = robot), or with ``labels=True`` the uint16 per-link
    labels (see :meth:`Robot.link_labels`). Give ``joints`` ``[T, dof]`` or
    end-effector ``actions`` ``[T, action_dim]`` (solved by IK first). With
    ``depth=True`` returns ``(masks, depth)``, depth float32 metres along the
    camera's z, inf where no robot is."""
    if (joints is None) == (actions is None):
        raise ValueError("render_masks: give exactly one of joints= and actions=")
    if actions is not None:
        q, _ = robot.solve_ik(actions, allow_residual=allow_residual)
    else:
        q = _float_array("joints", joints, 2, len(robot.joint_names))
    w, h = camera.size
    lab, dep = _core.render(robot._r, camera._c, q.tolist(), depth)
    lab = np.frombuffer(lab, dtype="<u2").reshape(len(q), h, w)
    out = lab.copy() if labels else (lab > 0).astype(np.uint8)
    if depth:
        return out, np.frombuffer(dep, dtype="<f4").reshape(len(q), h, w).copy()
    return out


class WorldModel:
    """BridgeV2W: from a first frame and the embodiment masks of the actions
    to the video they cause."""

    def __init__(self, core):
        self._m = core

    @classmethod
    def from_pretrained(cls, model, *, weights=None, device: str = "cpu", precision: str = "f32",
                        seed: int = 0) -> "WorldModel":
        """``model``: a folder as ``assets/demo-model`` (``backbone/`` and
        ``bridgev2w.safetensors``), a diffusers CogVideoX-I2V folder or Hub
        name (from the local Hugging Face cache, offline) with BridgeV2W
        ``weights``, or ``random:PRESET``. ``device``: ``cpu``, ``cuda``,
        ``cuda:N`` or ``auto``; ``precision``: ``f32`` or ``bf16``."""
        return cls(_core.WorldModel.from_pretrained(
            str(model), None if weights is None else str(weights), device, precision, int(seed)))

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
        ``masks`` ``[T, H, W]`` (non-zero = robot), sampled with ``steps``
        denoising steps from noise seed ``seed``."""
        h, w = self.resolution
        t = self.clip_frames
        f = np.asarray(first_frame)
        if f.dtype != np.uint8 or f.shape != (h, w, 3):
            raise ValueError(f"first_frame: expected uint8 [{h}, {w}, 3] for this model, got {f.dtype} {f.shape}")
        m = np.asarray(masks)
        if m.shape != (t, h, w):
            raise ValueError(f"masks: expected [{t}, {h}, {w}] for this model, got shape {m.shape}")
        video = self._m.predict(np.ascontiguousarray(f).tobytes(), (m != 0).astype(np.uint8).tobytes(),
                                int(steps), int(seed), float(guidance))
        return np.frombuffer(video, dtype=np.uint8).reshape(t, h, w, 3).copy()

    def __repr__(self) -> str:
        return repr(self._m)


def builtin_robots() -> str:
    """The names of the built-in robots."""
    return _core.builtin_robots()


from . import lerobot  # noqa: E402  (uses the names above)
