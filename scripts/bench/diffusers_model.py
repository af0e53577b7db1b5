#!/usr/bin/env python3
"""Peer for `bridgev2w bench model`: times diffusers' CogVideoX transformer forward and
VAE encode/decode on the same configs, shapes and thread count as the Rust side, each
best of --repeat after one warm-up run (as the Rust side times its own).

Progress goes to stdout as JSON lines, flushed at once, so that a caller that stops
this run at a time limit keeps what finished: `{"starting": OP}` before each
operation's warm-up, and after each operation the result so far (the same object
growing); the last line is the whole result.

`--ops` names the operations to time (default all three, in that order), and only
the models they need are built: a caller that stops a run in one operation (each has
its own time limit) times the operations after it in a new process.

The configs come from JSON files written by the Rust side (the same dicts it uses), so
both sides build the same architecture; weights are random (timing only).
"""
import argparse
import json
import os
import sys
import time


OPS = ("transformer_forward", "vae_encode", "vae_decode")


def emit(obj):
    print(json.dumps(obj), flush=True)


def timed(out, op, fn, repeat):
    """Warm-up, then best of `repeat`, stored as `out[op + "_s"]` and printed."""
    emit({"starting": op})
    fn()
    out[op + "_s"] = best_of(fn, repeat)
    emit(out)


def best_of(fn, repeat):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--transformer-config", required=True)
    ap.add_argument("--vae-config", required=True)
    ap.add_argument("--frames", type=int, required=True, help="video frames (latent frames = (F-1)/4+1)")
    ap.add_argument("--height", type=int, required=True)
    ap.add_argument("--width", type=int, required=True)
    ap.add_argument("--text-len", type=int, default=226)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--batch", type=int, default=1, help="transformer batch (2: one CFG denoising step)")
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--dtype", choices=["f32", "bf16"], default="f32")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--vae-tiling", action="store_true", help="vae.enable_tiling() (default tiles)")
    ap.add_argument("--ops", default=",".join(OPS),
                    help=f"comma-separated operations to time, of {', '.join(OPS)} (default: all)")
    args = ap.parse_args()
    ops = args.ops.split(",")
    unknown = [op for op in ops if op not in OPS]
    if unknown or not ops or len(set(ops)) != len(ops):
        ap.error(f"--ops {args.ops!r}: expected each of {', '.join(OPS)} at most once")

    import torch

    if args.threads > 0:
        torch.set_num_threads(args.threads)
    dtype = torch.float32 if args.dtype == "f32" else torch.bfloat16
    dev = torch.device(args.device)
    torch.manual_seed(0)
    with open(args.transformer_config) as f:
        tcfg = {k: v for k, v in json.load(f).items() if not k.startswith("_")}
    with open(args.vae_config) as f:
        vcfg = {k: v for k, v in json.load(f).items() if not k.startswith("_")}
    out = {"threads": torch.get_num_threads(), "device": args.device, "dtype": args.dtype}

    lat_f = (args.frames - 1) // 4 + 1
    lat_h, lat_w = args.height // 8, args.width // 8
    if "transformer_forward" in ops:
        time_transformer(args, tcfg, out, dev, dtype, lat_f, lat_h, lat_w)
    if "vae_encode" in ops or "vae_decode" in ops:
        time_vae(args, vcfg, out, dev, dtype, lat_f, lat_h, lat_w, ops)
    emit(out)
    return 0


def time_transformer(args, tcfg, out, dev, dtype, lat_f, lat_h, lat_w):
    import torch
    from diffusers import CogVideoXTransformer3DModel

    transformer = CogVideoXTransformer3DModel(**tcfg).to(dev, dtype).eval()
    b = args.batch
    x = torch.randn(b, lat_f, tcfg.get("in_channels", 16), lat_h, lat_w, device=dev, dtype=dtype)
    text = torch.randn(b, args.text_len, tcfg.get("text_embed_dim", 4096), device=dev, dtype=dtype)
    ts = torch.full((b,), 500, device=dev, dtype=torch.int64)
    rope = None
    if tcfg.get("use_rotary_positional_embeddings"):
        from diffusers.models.embeddings import get_3d_rotary_pos_embed
        p = tcfg.get("patch_size", 2)
        gh, gw = lat_h // p, lat_w // p
        rope = get_3d_rotary_pos_embed(
            embed_dim=tcfg.get("attention_head_dim", 64), crops_coords=((0, 0), (gh, gw)),
            grid_size=(gh, gw), temporal_size=lat_f, device=dev,
        )
    with torch.no_grad():
        def fwd():
            transformer(hidden_states=x, encoder_hidden_states=text, timestep=ts,
                        image_rotary_emb=rope, return_dict=False)
            if dev.type == "cuda":
                torch.cuda.synchronize()
        timed(out, "transformer_forward", fwd, args.repeat)
    if dev.type == "cuda":
        # The caching allocator's peaks (the Rust side reads nvidia-smi, like this run's
        # probe on the Rust side of `bench model`; these are extra detail).
        out["transformer_peak_allocated_mib"] = torch.cuda.max_memory_allocated(dev) / 2**20
        torch.cuda.reset_peak_memory_stats(dev)


def time_vae(args, vcfg, out, dev, dtype, lat_f, lat_h, lat_w, ops):
    import torch
    from diffusers import AutoencoderKLCogVideoX

    vae = AutoencoderKLCogVideoX(**vcfg).to(dev, dtype).eval()
    if args.vae_tiling:
        vae.enable_tiling()
    video = torch.rand(1, 3, args.frames, args.height, args.width, device=dev, dtype=dtype) * 2 - 1
    latents = torch.randn(1, vcfg.get("latent_channels", 16), lat_f, lat_h, lat_w, device=dev, dtype=dtype)
    with torch.no_grad():
        def enc():
            vae.encode(video).latent_dist.mean
            if dev.type == "cuda":
                torch.cuda.synchronize()

        def dec():
            vae.decode(latents)
            if dev.type == "cuda":
                torch.cuda.synchronize()
        if "vae_encode" in ops:
            timed(out, "vae_encode", enc, args.repeat)
        if "vae_decode" in ops:
            timed(out, "vae_decode", dec, args.repeat)
    if dev.type == "cuda":
        out["vae_peak_allocated_mib"] = torch.cuda.max_memory_allocated(dev) / 2**20


if __name__ == "__main__":
    sys.exit(main())
