#!/usr/bin/env python3
"""PSNR and SSIM of frame pairs with scikit-image (reference + benchmark peer).

Inputs: two uint8 arrays [N, H, W, 3] (.npy), predicted and ground truth.
Every frame pair is scored with
  peak_signal_noise_ratio(gt, pred, data_range=1.0)
  structural_similarity(gt, pred, gaussian_weights=True, sigma=1.5,
                        use_sample_covariance=False, data_range=1.0, channel_axis=-1)
on float64 values in [0, 1], split over --workers processes.

Prints one JSON line: {"frames":..,"seconds":..,"workers":..,"psnr":[..],"ssim":[..]}
`seconds` is the wall time of the scoring phase only (first worker starting
its first frame to last worker finishing), excluding process start-up and
loading.
"""

import argparse
import json
import multiprocessing as mp
import time

import numpy as np


def _score(args):
    pred, gt = args
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    t0 = time.time()
    psnr, ssim = [], []
    for p, g in zip(pred, gt):
        p = p.astype(np.float64) / 255.0
        g = g.astype(np.float64) / 255.0
        psnr.append(float(peak_signal_noise_ratio(g, p, data_range=1.0)))
        ssim.append(
            float(
                structural_similarity(
                    g, p, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                    data_range=1.0, channel_axis=-1,
                )
            )
        )
    return t0, time.time(), psnr, ssim


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pred", required=True)
    ap.add_argument("--gt", required=True)
    ap.add_argument("--workers", type=int, default=1)
    args = ap.parse_args()
    pred, gt = np.load(args.pred), np.load(args.gt)
    if pred.shape != gt.shape or pred.ndim != 4 or pred.shape[-1] != 3:
        raise SystemExit(f"expected two uint8 arrays [N, H, W, 3] of one shape, got {pred.shape} and {gt.shape}")
    workers = max(1, min(args.workers, len(pred)))
    jobs = [(p, g) for p, g in zip(np.array_split(pred, workers), np.array_split(gt, workers)) if len(p)]
    if workers == 1:
        results = [_score(jobs[0])]
    else:
        with mp.get_context("fork").Pool(workers) as pool:
            results = pool.map(_score, jobs)
    start = min(r[0] for r in results)
    end = max(r[1] for r in results)
    psnr = [v for r in results for v in r[2]]
    ssim = [v for r in results for v in r[3]]
    print(json.dumps({"frames": len(pred), "seconds": end - start, "workers": workers, "psnr": psnr, "ssim": ssim}))


if __name__ == "__main__":
    main()
