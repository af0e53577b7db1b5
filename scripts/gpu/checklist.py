#!/usr/bin/env python3
"""Small helpers of scripts/gpu/run.sh (standard library and numpy only, as
the GPU image has them):

  compare-videos A.npy B.npy NAME   max |A - B| of two uint8 videos -> metrics
  compare-losses A.jsonl B.jsonl NAME  losses of two runs (finite? how close?)
  step-seconds METRICS.jsonl NAME   median step time of a training run
  fits-80gb NAME                    exit 0 (printing why) when NAME's training
                                    steps fit an 80 GB GPU, else exit 1
  peak-mib LOG NAME                 the largest used-memory figure an
                                    nvidia-smi poll wrote (MiB)
  record-seconds NAME KEY SECONDS   one timing figure
  bench-table LOG NAME              the timings of `bench model`
  flow-row LOG NAME MODE [LABEL]    one mode's row of `bench flow` (keys
                                    LABEL_seconds, ...; LABEL defaults to MODE)
  environment MODE COMMIT           the device, torch, the commit, the date
  summary OUT                       OUT/items.tsv + OUT/metrics/*.json ->
                                    OUT/summary.json and OUT/summary.md

Metrics are merged into OUT/metrics/NAME.json (OUT from the environment).
"""

import json
import math
import os
import statistics
import sys


def out_dir():
    return os.environ.get("OUT", "gpu-out")


def record(name, **values):
    path = os.path.join(out_dir(), "metrics", f"{name}.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    old = {}
    if os.path.exists(path):
        with open(path) as f:
            old = json.load(f)
    old.update(values)
    with open(path + ".tmp", "w") as f:
        json.dump(old, f, indent=1, sort_keys=True)
    os.replace(path + ".tmp", path)
    print(json.dumps(values))


def compare_videos(a, b, name):
    import numpy as np

    va, vb = np.load(a).astype(np.int16), np.load(b).astype(np.int16)
    if va.shape != vb.shape:
        raise SystemExit(f"{a} {va.shape} vs {b} {vb.shape}: shapes differ")
    diff = np.abs(va - vb)
    record(
        name,
        shape=list(va.shape),
        max_abs_diff_u8=int(diff.max()),
        mean_abs_diff_u8=float(diff.mean()),
        # 1e-3 of the [0, 1] range is below one 8-bit step: equal bytes, or
        # at most one step from rounding, meet it.
        within_1e3=bool(diff.max() <= 1),
    )


def losses(path):
    with open(path) as f:
        rows = [json.loads(line) for line in f if line.strip()]
    return [r["loss"] for r in rows]


def compare_losses(a, b, name):
    la, lb = losses(a), losses(b)
    finite = all(math.isfinite(v) for v in la + lb)
    n = min(len(la), len(lb))
    rel = [abs(x - y) / max(abs(y), 1e-12) for x, y in zip(la[:n], lb[:n])]
    record(
        name,
        steps=[len(la), len(lb)],
        finite=finite,
        mean_loss=[statistics.fmean(la) if la else None, statistics.fmean(lb) if lb else None],
        max_relative_diff=max(rel) if rel else None,
        median_relative_diff=statistics.median(rel) if rel else None,
    )
    if not finite:
        raise SystemExit("non-finite losses")


def step_seconds(path, name):
    with open(path) as f:
        rows = [json.loads(line) for line in f if line.strip()]
    secs = [r["secs"] for r in rows]
    # The first step carries the warm-up (allocator, kernels): left out when there are more.
    timed = secs[1:] if len(secs) > 1 else secs
    reserved = max(
        (r["cuda_peak_reserved_mib"] for r in rows if "cuda_peak_reserved_mib" in r),
        default=None,
    )
    record(
        name,
        steps=len(secs),
        median_step_seconds=statistics.median(timed) if timed else None,
        # > 0 when the flow loss ran (its weight is 0 before e_switch).
        max_flow_weight=max((r.get("flow_weight", 0.0) for r in rows), default=None),
        finite_losses=all(math.isfinite(r["loss"]) for r in rows),
        # On CUDA, the caching allocator's exact peaks over the steps (MiB):
        # what tensors held, and what the allocator reserved from the device.
        cuda_peak_allocated_mib=max(
            (r["cuda_peak_allocated_mib"] for r in rows if "cuda_peak_allocated_mib" in r),
            default=None,
        ),
        cuda_peak_reserved_mib=reserved,
        # Whether that reserve, with the context, fits an 80 GB card.
        fits_80gb=fits_80gb_of(reserved),
    )


# An 80 GB card (H100/A100 80GB) shows 81,080 MiB to CUDA; the context and
# the libraries' handles take about a GiB of it outside the caching allocator.
CARD_80GB_MIB = 81080
OUTSIDE_ALLOCATOR_MIB = 1024


def fits_80gb_of(reserved_mib):
    return None if reserved_mib is None else reserved_mib + OUTSIDE_ALLOCATOR_MIB <= CARD_80GB_MIB


def fits_80gb(name):
    path = os.path.join(out_dir(), "metrics", f"{name}.json")
    metrics = {}
    if os.path.exists(path):
        with open(path) as f:
            metrics = json.load(f)
    reserved = metrics.get("cuda_peak_reserved_mib")
    if metrics.get("fits_80gb") and metrics.get("finite_losses"):
        print(f"{name} fits an 80 GB GPU (the caching allocator reserved at most {reserved:.0f} MiB)")
        return
    print(f"{name}: not shown to fit an 80 GB GPU (reserved {reserved} MiB)")
    raise SystemExit(1)


def peak_mib(path, name):
    peak = 0
    if os.path.exists(path):
        with open(path) as f:
            for line in f:
                try:
                    peak = max(peak, int(line.strip().split(",")[0]))
                except ValueError:
                    pass
    record(name, peak_gpu_memory_mib=peak if peak else None)


def bench_table(log, name):
    import re

    figures = {}
    with open(log) as f:
        for line in f:
            m = re.match(r"^(\S.*?)\s{2,}([\d.]+)\s+([\d.]+)\s+([\d.]+)x\s*$", line.rstrip())
            if m:
                op = re.sub(r"[^a-z0-9]+", "_", m.group(1).lower()).strip("_")
                figures[f"{op}_seconds"] = [float(m.group(2)), float(m.group(3))]
                figures[f"{op}_speedup"] = float(m.group(4))
    if not figures:
        raise SystemExit(f"{log}: no timing table")
    record(name, **figures)


def flow_row(log, name, mode, label=None):
    label = label or mode
    with open(log) as f:
        for line in f:
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if len(cells) == 7 and cells[0] == mode:
                peak = cells[2].split()[0]
                record(
                    name,
                    **{
                        f"{label}_seconds": float(cells[1]),
                        f"{label}_peak_mib": None if peak == "not" else float(peak),
                        f"{label}_record_mib": None if cells[3] == "-" else float(cells[3]),
                        f"{label}_loss": float(cells[4]),
                        # The CUDA caching allocator's exact peak (tensors).
                        f"{label}_allocator_peak_mib": None if cells[6] == "-" else float(cells[6]),
                    },
                )
                return
    raise SystemExit(f"{log}: no row for {mode}")


def record_seconds(name, key, seconds):
    record(name, **{key: float(seconds)})


def environment(mode, commit):
    import datetime
    import platform

    import torch

    cuda = torch.cuda.is_available()
    record(
        "environment",
        mode=mode,
        commit=commit,
        date=datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        torch=torch.__version__,
        cuda=torch.version.cuda,
        device=torch.cuda.get_device_name(0) if cuda else f"cpu ({platform.processor() or platform.machine()}, {os.cpu_count()} cores)",
        gpu_memory_gib=round(torch.cuda.get_device_properties(0).total_memory / 2**30, 1) if cuda else None,
    )


def summary(out):
    items = []
    tsv = os.path.join(out, "items.tsv")
    if os.path.exists(tsv):
        with open(tsv) as f:
            for line in f:
                name, status, seconds, log = line.rstrip("\n").split("\t")
                metrics = {}
                mpath = os.path.join(out, "metrics", f"{name}.json")
                if os.path.exists(mpath):
                    with open(mpath) as m:
                        metrics = json.load(m)
                items.append(
                    {"item": name, "status": status, "seconds": float(seconds), "log": log, "metrics": metrics}
                )
    env = {}
    epath = os.path.join(out, "metrics", "environment.json")
    if os.path.exists(epath):
        with open(epath) as f:
            env = json.load(f)
    doc = {"environment": env, "items": items}
    with open(os.path.join(out, "summary.json"), "w") as f:
        json.dump(doc, f, indent=1, sort_keys=True)
    lines = [
        "# GPU checklist",
        "",
        f"Device: {env.get('device', '?')}; torch {env.get('torch', '?')}; "
        f"commit {env.get('commit', '?')}; {env.get('date', '?')}; mode {env.get('mode', '?')}.",
        "",
        "| item | status | seconds | figures |",
        "|---|---|---|---|",
    ]
    for it in items:
        figures = ", ".join(f"{k} {v}" for k, v in sorted(it["metrics"].items()))
        lines.append(f"| {it['item']} | {it['status']} | {it['seconds']:.1f} | {figures} |")
    with open(os.path.join(out, "summary.md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))


def main():
    cmd, args = sys.argv[1], sys.argv[2:]
    {
        "compare-videos": compare_videos,
        "compare-losses": compare_losses,
        "step-seconds": step_seconds,
        "peak-mib": peak_mib,
        "fits-80gb": fits_80gb,
        "environment": environment,
        "record-seconds": record_seconds,
        "bench-table": bench_table,
        "flow-row": flow_row,
        "summary": summary,
    }[cmd](*args)


if __name__ == "__main__":
    main()
