"""A LeRobot-style transform: adds each camera's embodiment mask to a
dataset item, rendered from the item's joint state.

    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    import bridgev2w as bw

    robot = bw.Robot("franka")
    cams = {"observation.images.main": bw.Camera.from_json("main.json")}
    masks = bw.lerobot.EmbodimentMasks(robot, cams)
    ds = LeRobotDataset("me/my-robot", image_transforms=None)
    item = masks(ds[0])      # item["observation.images.main.mask"]: uint8 [T?, H, W]

The state (``observation.state`` by default) holds the robot's joint
positions in the order of ``robot.joint_names``, one frame ``[dof]`` or a
window ``[T, dof]`` (LeRobot's ``delta_timestamps``); ``state_to_joints``
maps another state layout to joints. The mask has the size of the item's
image under the same key when the item has one (the camera is rescaled),
else the camera's own size, and the type of the state (a torch tensor for
a torch state, else a numpy array).
"""

from __future__ import annotations

from typing import Callable, Mapping, Optional

import numpy as np

from . import Camera, Robot, render_masks


class EmbodimentMasks:
    """Adds ``<camera key><suffix>`` masks (uint8, 1 = robot) to an item."""

    def __init__(self, robot: Robot, cameras: Mapping[str, Camera], *,
                 state_key: str = "observation.state", suffix: str = ".mask",
                 state_to_joints: Optional[Callable[[np.ndarray], np.ndarray]] = None):
        if not cameras:
            raise ValueError("cameras: expected at least one {video key: Camera}")
        self.robot, self.cameras = robot, dict(cameras)
        self.state_key, self.suffix = state_key, suffix
        self.state_to_joints = state_to_joints

    def _image_size(self, image):
        """(width, height) of an image [C, H, W] (torch) or [H, W, C] (numpy), with optional time."""
        shape = tuple(image.shape)
        if hasattr(image, "detach"):  # torch: [..., C, H, W]
            return shape[-1], shape[-2]
        return shape[-2], shape[-3]  # numpy: [..., H, W, C]

    def __call__(self, item: dict) -> dict:
        if self.state_key not in item:
            raise ValueError(f"item: no {self.state_key!r} (state_key); keys: {sorted(item)}")
        state = item[self.state_key]
        is_torch = hasattr(state, "detach")
        s = state.detach().cpu().numpy() if is_torch else np.asarray(state)
        single = s.ndim == 1
        q = s[None] if single else s
        if self.state_to_joints is not None:
            q = np.asarray(self.state_to_joints(q))
        out = dict(item)
        for key, cam in self.cameras.items():
            if key in item:
                w, h = self._image_size(item[key])
                if (w, h) != cam.size:
                    cam = cam.rescaled(w, h)
            m = render_masks(self.robot, cam, joints=q)
            m = m[0] if single else m
            if is_torch:
                import torch

                m = torch.from_numpy(m)
            out[key + self.suffix] = m
        return out
