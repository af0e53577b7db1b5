"""The paper's frame metrics on uint8 RGB frames ``[H, W, 3]`` (or videos
``[T, H, W, 3]``, averaged over frames): PSNR and SSIM on [0, 1] values,
and the IoU of binary masks."""

from __future__ import annotations

import numpy as np

from . import _core


def _frames(name, a):
    a = np.asarray(a)
    if a.dtype != np.uint8:
        raise ValueError(f"{name}: expected uint8 RGB, got dtype {a.dtype}")
    if a.ndim == 3:
        a = a[None]
    if a.ndim != 4 or a.shape[-1] != 3:
        raise ValueError(f"{name}: expected [H, W, 3] or [T, H, W, 3], got shape {a.shape}")
    return np.ascontiguousarray(a)


def _pair(pred, gt):
    p, g = _frames("pred", pred), _frames("gt", gt)
    if p.shape != g.shape:
        raise ValueError(f"pred {p.shape} and gt {g.shape}: expected the same shape")
    return p, g


def psnr(pred, gt) -> float:
    """PSNR in dB (per frame, then the mean over frames)."""
    p, g = _pair(pred, gt)
    h, w = p.shape[1:3]
    return float(np.mean([_core.psnr(a.tobytes(), b.tobytes(), h, w) for a, b in zip(p, g)]))


def ssim(pred, gt) -> float:
    """SSIM (Gaussian window, sigma 1.5, as scikit-image's with
    ``gaussian_weights=True``), per frame, then the mean."""
    p, g = _pair(pred, gt)
    h, w = p.shape[1:3]
    return float(np.mean([_core.ssim(a.tobytes(), b.tobytes(), h, w) for a, b in zip(p, g)]))


def mask_iou(pred, gt) -> float:
    """Intersection over union of two masks of the same shape (non-zero =
    inside); 1 when both are empty."""
    p, g = np.asarray(pred), np.asarray(gt)
    if p.shape != g.shape:
        raise ValueError(f"pred {p.shape} and gt {g.shape}: expected the same shape")
    return _core.mask_iou((p != 0).astype(np.uint8).tobytes(), (g != 0).astype(np.uint8).tobytes())
