#!/usr/bin/env python3
"""Where diffusers' CogVideoX spends a forward pass on this CPU: torch.profiler's
table of ATen ops (self time) for one transformer forward, VAE encode or VAE
decode at `bridgev2w bench model`'s default shapes (2B width, 8 blocks, 9 frames
at 128x192), the GEMM rate of the feed-forward's shape, one of the VAE's 3x3x3
convolutions (`conv`: which kernel libtorch picks shows in its time, e.g. the
single-threaded `slow_conv3d` for bf16 on a CPU without AVX-512), and (`linear`) one
block's products through libtorch's `linear` (as diffusers runs them) against
oneDNN's linear layer on a weight packed once, GELU fused (as this crate runs
them on the CPU outside autograd, `world_model::cpu_linear`), and two decoder
layers in diffusers' order of operations against this crate's (`spatial-norm`:
the 1x1x1 convolutions at the latent's size and a broadcast `addcmul`;
`upsampler`: the convolution of the 2x-upsampled frame as four 2x2 phases and a
pixel shuffle), with the largest difference between the two; and
(`conv-layouts`) a resnet's 3x3x3 convolution as libtorch's conv3d against
three other ways to the same sums (its time taps stacked into the channels
as one 2-D convolution, three 2-D convolutions summed, channels-last);
(`decoder-products`) the decoder's multiply-adds by convolution shape, counted
by hooks on one decode at the bench's shapes; and (`winograd`) the same
convolution by Winograd's F(2x2, 3x3) (2.25x fewer products) built on
libtorch's batched GEMM, against conv3d, with the time of each stage; and
(`pooled-conv`) an encoder block's last causal convolution followed by the
downsampler's mean of frame pairs, in diffusers' order against this crate's
(each pair's mean as one stride-2 convolution with 4 time taps).

The same libtorch kernels run under this crate's model, so the table says what
any implementation at these shapes is made of (docs/benchmarks.md).

    .venv/bin/python scripts/bench/profile_diffusers.py transformer --dtype f32
    .venv/bin/python scripts/bench/profile_diffusers.py decode --dtype bf16
    .venv/bin/python scripts/bench/profile_diffusers.py linear --dtype f32
    .venv/bin/python scripts/bench/profile_diffusers.py conv --dtype bf16
    .venv/bin/python scripts/bench/profile_diffusers.py spatial-norm
    .venv/bin/python scripts/bench/profile_diffusers.py upsampler
    .venv/bin/python scripts/bench/profile_diffusers.py conv-layouts
    .venv/bin/python scripts/bench/profile_diffusers.py decoder-products
    .venv/bin/python scripts/bench/profile_diffusers.py winograd
    .venv/bin/python scripts/bench/profile_diffusers.py pooled-conv
"""

import argparse
import sys
import time


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("part", choices=["transformer", "encode", "decode", "gemm", "conv", "linear", "spatial-norm", "upsampler", "conv-layouts",
                                     "decoder-products", "winograd", "pooled-conv"])
    ap.add_argument("--dtype", choices=["f32", "bf16"], default="f32")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rows", type=int, default=12, help="ops in the table")
    args = ap.parse_args()

    import torch

    torch.set_num_threads(args.threads)
    dtype = torch.float32 if args.dtype == "f32" else torch.bfloat16
    torch.manual_seed(0)

    if args.part == "gemm":
        # The feed-forward's first projection: 514 tokens x 1920 -> 7680.
        a = torch.randn(514, 1920, dtype=dtype)
        b = torch.randn(1920, 7680, dtype=dtype)
        for _ in range(3):
            a @ b
        n = 20
        t0 = time.perf_counter()
        for _ in range(n):
            a @ b
        s = (time.perf_counter() - t0) / n
        print(f"gemm 514x1920x7680 {args.dtype}: {s * 1e3:.1f} ms, {2 * 514 * 1920 * 7680 / s / 1e9:.0f} GFLOP/s")
        return 0

    if args.part == "conv":
        # A 128-channel resnet convolution of the VAE's first stage, 3 latent
        # frames' worth of time steps at half the bench's resolution.
        x = torch.randn(1, 128, 3, 66, 98, dtype=dtype)
        w = torch.randn(128, 128, 3, 3, 3, dtype=dtype) * 0.03
        with torch.no_grad():
            torch.nn.functional.conv3d(x, w)
            n = 3
            t0 = time.perf_counter()
            for _ in range(n):
                torch.nn.functional.conv3d(x, w)
        s = (time.perf_counter() - t0) / n
        print(f"conv3d 128->128 3x3x3 on 1x128x3x66x98 {args.dtype}: {s * 1e3:.1f} ms (mean of {n} after a warm-up)")
        return 0

    if args.part == "linear":
        return linear_kernels(torch, dtype, args.dtype)
    if args.part == "conv-layouts":
        with torch.no_grad():
            return conv_layouts(torch, dtype)
    if args.part == "decoder-products":
        with torch.no_grad():
            return decoder_products(torch, dtype)
    if args.part == "winograd":
        with torch.no_grad():
            return winograd(torch, dtype)
    if args.part == "pooled-conv":
        with torch.no_grad():
            return pooled_conv(torch, dtype)
    if args.part in ("spatial-norm", "upsampler"):
        with torch.no_grad():
            return decoder_layers(torch, args.part, dtype)

    if args.part == "transformer":
        from diffusers import CogVideoXTransformer3DModel

        model = CogVideoXTransformer3DModel(
            num_attention_heads=30, attention_head_dim=64, num_layers=8,
            sample_width=24, sample_height=16, sample_frames=9,
        ).to(dtype).eval()
        x = torch.randn(1, 3, 16, 16, 24, dtype=dtype)
        text = torch.randn(1, 226, 4096, dtype=dtype)
        ts = torch.full((1,), 500)

        def run():
            model(hidden_states=x, encoder_hidden_states=text, timestep=ts, return_dict=False)
    else:
        from diffusers import AutoencoderKLCogVideoX

        vae = AutoencoderKLCogVideoX().to(dtype).eval()
        latents = torch.randn(1, 16, 3, 16, 24, dtype=dtype)
        video = torch.rand(1, 3, 9, 128, 192, dtype=dtype) * 2 - 1

        def run():
            if args.part == "encode":
                vae.encode(video)
            else:
                vae.decode(latents)

    with torch.no_grad():
        run()  # warm-up
        t0 = time.perf_counter()
        run()
        print(f"{args.part} {args.dtype}: {time.perf_counter() - t0:.3f} s (one run, unprofiled)")
        with torch.profiler.profile() as prof:
            run()
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=args.rows))
    return 0


def linear_kernels(torch, dtype, name) -> int:
    """One 2B block's products at 514 tokens (226 text + 288 video): libtorch's
    linear (then GELU) vs oneDNN on a packed weight (GELU fused), median of 20."""
    F = torch.nn.functional
    pointwise = torch.ops.mkldnn._linear_pointwise
    pack = torch.ops.mkldnn._reorder_linear_weight

    def median_s(fn):
        return run_times(fn, 20)[10]

    rows, d = 514, 1920
    shapes = [("q, k, v, out (each)", d, d, 4, False), ("ff.net.0 + GELU", d, 4 * d, 1, True),
              ("ff.net.2", 4 * d, d, 1, False)]
    total_aten = total_onednn = 0.0
    print(f"{name}, {rows} rows: libtorch linear vs oneDNN packed (ms)")
    for label, k, n, count, gelu in shapes:
        x = torch.randn(rows, k, dtype=dtype)
        w = (torch.randn(n, k) * 0.02).to(dtype)
        b = torch.randn(n).to(dtype)
        packed = pack(w, None)
        if gelu:
            aten = median_s(lambda: F.gelu(F.linear(x, w, b), approximate="tanh"))
            onednn = median_s(lambda: pointwise(x, packed, b, "gelu", [], "tanh"))
        else:
            aten = median_s(lambda: F.linear(x, w, b))
            onednn = median_s(lambda: pointwise(x, packed, b, "none", [], ""))
        total_aten += count * aten
        total_onednn += count * onednn
        print(f"  {label:<22} {aten * 1e3:8.2f} {onednn * 1e3:8.2f}  {aten / onednn:.2f}x")
    print(f"  {'one block':<22} {total_aten * 1e3:8.2f} {total_onednn * 1e3:8.2f}  {total_aten / total_onednn:.2f}x")
    return 0


def run_times(fn, n):
    """Seconds of `n` runs of `fn` after two warm-ups, sorted."""
    fn()
    fn()
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return sorted(times)


def best_s(fn):
    return run_times(fn, 5)[0]


def decoder_layers(torch, part, dtype) -> int:
    """A decoder layer at the bench's shapes (best of 5 after 2 warm-ups):
    diffusers' order of operations against this crate's, in libtorch ops."""
    F = torch.nn.functional
    print(f"{part}: diffusers' order vs this crate's (ms), max difference")
    if part == "spatial-norm":
        # Features [C, T, H, W] of one decoder batch; the latent: 2 frames at 16x24.
        for c, t, h, w in [(128, 8, 128, 192), (256, 8, 64, 96), (512, 4, 32, 48)]:
            f = torch.randn(1, c, t, h, w, dtype=dtype)
            zq = torch.randn(1, 16, 2, 16, 24, dtype=dtype)
            wy, wb = (torch.randn(c, 16, 1, 1, 1, dtype=dtype) * 0.2 for _ in range(2))
            by, bb = torch.randn(c, dtype=dtype), torch.randn(c, dtype=dtype)
            sh, sw = h // 16, w // 24

            def diffusers_order():
                z = F.interpolate(zq, size=(t, h, w))
                return F.group_norm(f, 32, eps=1e-6) * F.conv3d(z, wy, by) + F.conv3d(z, wb, bb)

            def this_crate():
                y = F.interpolate(F.conv3d(zq, wy, by), size=(t, 16, 24)).view(1, c, t, 16, 1, 24, 1)
                b = F.interpolate(F.conv3d(zq, wb, bb), size=(t, 16, 24)).view(1, c, t, 16, 1, 24, 1)
                n = F.group_norm(f, 32, eps=1e-6).view(1, c, t, 16, sh, 24, sw)
                return torch.addcmul(b, n, y).view(1, c, t, h, w)

            report(torch, f"{c} channels, {t}x{h}x{w}", diffusers_order, this_crate)
        return 0
    for c, t, h, w in [(256, 9, 64, 96), (256, 5, 32, 48), (512, 3, 16, 24)]:
        x = torch.randn(t, c, h, w, dtype=dtype)  # the frames as images
        k = torch.randn(c, c, 3, 3, dtype=dtype) * 0.03
        bias = torch.randn(c, dtype=dtype)

        def fold(k, dim, a):
            one, two = (k.narrow(dim, 0, 1), k.narrow(dim, 1, 2).sum(dim, keepdim=True)) if a == 0 else (
                k.narrow(dim, 0, 2).sum(dim, keepdim=True), k.narrow(dim, 2, 1))
            return torch.cat([one, two], dim)

        phases = torch.stack([fold(fold(k, 2, a), 3, b) for a in (1, 0) for b in (1, 0)], 1)
        phases = phases.reshape(4 * c, c, 2, 2)
        bias4 = bias.repeat_interleave(4)

        def diffusers_order():
            return F.conv2d(F.interpolate(x, scale_factor=2.0), k, bias, padding=1)

        def this_crate():
            out = F.pixel_shuffle(F.conv2d(F.pad(x, (1, 1, 1, 1)), phases, bias4), 2)
            return out[:, :, 1:2 * h + 1, 1:2 * w + 1].contiguous()

        report(torch, f"{c} channels, {t} frames of {h}x{w}", diffusers_order, this_crate)
    return 0


def conv_layouts(torch, dtype) -> int:
    """A decoder resnet's causal 3x3x3 convolution (time already padded) at
    the bench's shapes, four ways (best of 5 after 2 warm-ups)."""
    F = torch.nn.functional
    print("conv-layouts: ms (and conv3d's time over it), max difference to conv3d")
    for c, t, h, w in [(128, 9, 128, 192), (256, 5, 64, 96), (512, 3, 32, 48)]:
        x = torch.randn(1, c, t + 2, h, w, dtype=dtype)
        k = torch.randn(c, c, 3, 3, 3, dtype=dtype) * 0.01
        bias = torch.randn(c, dtype=dtype)
        # [Cout, Cin, kt, kh, kw] -> [Cout, kt * Cin, kh, kw]
        stacked = k.permute(0, 2, 1, 3, 4).reshape(c, 3 * c, 3, 3)
        x_last = x.contiguous(memory_format=torch.channels_last_3d)
        k_last = k.contiguous(memory_format=torch.channels_last_3d)

        def conv3d():
            return F.conv3d(x, k, bias, padding=(0, 1, 1))

        def taps_in_channels():
            # [1, C, T + 2, H, W] -> [T, 3C, H, W]: frame o with its next two
            frames = torch.cat([x[0, :, j:j + t] for j in range(3)], 0).transpose(0, 1)
            return F.conv2d(frames, stacked, bias, padding=1).transpose(0, 1).unsqueeze(0)

        def summed_2d():
            frames = x[0].transpose(0, 1)  # [T + 2, C, H, W]
            y = F.conv2d(frames[0:t], k[:, :, 0], bias, padding=1)
            for j in (1, 2):
                y = y + F.conv2d(frames[j:j + t], k[:, :, j], None, padding=1)
            return y.transpose(0, 1).unsqueeze(0)

        def channels_last():
            return F.conv3d(x_last, k_last, bias, padding=(0, 1, 1))

        ref = conv3d()
        base = best_s(conv3d)
        print(f"  {c} channels, {t} frames of {h}x{w}: conv3d {base * 1e3:.1f}")
        for name, fn in [("taps in channels", taps_in_channels), ("three conv2d", summed_2d),
                         ("channels-last", channels_last)]:
            diff = (fn() - ref).abs().max().item()
            s = best_s(fn)
            print(f"    {name:<18} {s * 1e3:8.1f}  {base / s:.2f}x  max diff {diff:.1e}")
    return 0


def decoder_products(torch, dtype) -> int:
    """diffusers' decoder at the bench's shapes (latents 1x16x3x16x24, so 9
    frames of 128x192): the multiply-adds of each convolution shape, counted
    by forward hooks on one decode, largest first."""
    from diffusers import AutoencoderKLCogVideoX

    vae = AutoencoderKLCogVideoX().to(dtype).eval()
    flops = {}

    def count(module, inputs, output):
        w = module.weight
        # [Cout, Cin, *kernel]: one multiply-add per output, input channel and tap
        key = (w.shape[1], w.shape[0], tuple(w.shape[2:]), tuple(inputs[0].shape[2:]))
        flops[key] = flops.get(key, 0) + 2 * output.numel() * w.shape[1] * w[0, 0].numel()

    for m in vae.decoder.modules():
        if isinstance(m, (torch.nn.Conv2d, torch.nn.Conv3d)):
            m.register_forward_hook(count)
    vae.decode(torch.randn(1, 16, 3, 16, 24, dtype=dtype))
    total = sum(flops.values())
    print(f"decoder-products: {total / 1e9:.0f} GFLOP in the decoder's convolutions")
    print("  Cin -> Cout, kernel, input (frames, H, W): GFLOP, share")
    for (cin, cout, kernel, shape), f in sorted(flops.items(), key=lambda kv: -kv[1]):
        print(f"  {cin:>4} -> {cout:<4} {'x'.join(map(str, kernel)):<6} {'x'.join(map(str, shape)):<12}"
              f" {f / 1e9:8.1f}  {100 * f / total:5.1f}%")
    return 0


def winograd(torch, dtype) -> int:
    """A decoder resnet's causal 3x3x3 convolution (time already padded) by
    Winograd's F(2x2, 3x3) in space, its three time taps summed in the
    transformed domain, channels-last, on libtorch's batched GEMM: 16
    products of [frames x tiles, Cin] x [Cin, Cout] per tap instead of 9
    per output pixel over 4 pixels (2.25x fewer multiply-adds). Best of 5
    after 2 warm-ups, each stage alone too; the GEMM's rate from its
    multiply-adds."""
    F = torch.nn.functional
    # Winograd's F(2, 3) matrices: G (kernel), B^T (input), A^T (output)
    g = torch.tensor([[1, 0, 0], [0.5, 0.5, 0.5], [0.5, -0.5, 0.5], [0, 0, 1]], dtype=dtype)

    def kernel_transform(k):
        # [Cout, Cin, kt, 3, 3] -> [kt, 16, Cin, Cout]
        u = torch.einsum("ai,octij,bj->tabco", g, k, g)
        return u.reshape(k.shape[2], 16, k.shape[1], k.shape[0]).contiguous()

    def input_transform(x):
        # [Cin, T + 2, H, W] -> [16, T + 2, H/2 * W/2, Cin]: B^T d B of each 4x4 tile, stride 2
        c, tp, h, w = x.shape
        th, tw = h // 2, w // 2
        xp = torch.zeros(tp, h + 2, w + 2, c, dtype=dtype)
        xp[:, 1:h + 1, 1:w + 1].copy_(x.permute(1, 2, 3, 0))
        r = [xp[:, k:k + 2 * th:2] for k in range(4)]
        rows = [r[0] - r[2], r[1] + r[2], r[2] - r[1], r[1] - r[3]]
        v = torch.empty(4, 4, tp, th, tw, c, dtype=dtype)
        for a in range(4):
            q = [rows[a][:, :, k:k + 2 * tw:2] for k in range(4)]
            torch.sub(q[0], q[2], out=v[a, 0])
            torch.add(q[1], q[2], out=v[a, 1])
            torch.sub(q[2], q[1], out=v[a, 2])
            torch.sub(q[1], q[3], out=v[a, 3])
        return v.view(16, tp, th * tw, c)

    def products(v, u, t):
        # [16, T + 2, tiles, Cin] x [kt, 16, Cin, Cout] -> [16, T * tiles, Cout]
        _, _, tiles, c = v.shape
        m = torch.bmm(v[:, 0:t].reshape(16, t * tiles, c), u[0])
        for j in range(1, u.shape[0]):
            m.baddbmm_(v[:, j:j + t].reshape(16, t * tiles, c), u[j])
        return m

    def output_transform(m, bias, t, h, w):
        # [16, T * tiles, Cout] -> [Cout, T, H, W]: A^T m A, each tile's 2x2 outputs
        th, tw, c = h // 2, w // 2, m.shape[2]
        m = m.view(4, 4, t, th, tw, c)
        s = (m[0] + m[1] + m[2], m[1] - m[2] - m[3])
        out = torch.empty(t, th, 2, tw, 2, c, dtype=dtype)
        for a in range(2):
            torch.add(s[a][0] + s[a][1], s[a][2], out=out[:, :, a, :, 0])
            torch.sub(s[a][1] - s[a][2], s[a][3], out=out[:, :, a, :, 1])
        return out.view(t, h, w, c).permute(3, 0, 1, 2) + bias.view(c, 1, 1, 1)

    print("winograd: ms (and conv3d's time over it); stages: input transform, GEMM (GFLOP/s), output transform")
    for c, t, h, w in [(128, 9, 128, 192), (256, 9, 64, 96), (256, 5, 32, 48), (512, 3, 16, 24)]:
        x = torch.randn(1, c, t + 2, h, w, dtype=dtype)
        k = torch.randn(c, c, 3, 3, 3, dtype=dtype) * 0.01
        bias = torch.randn(c, dtype=dtype)
        u = kernel_transform(k)

        def conv3d():
            return F.conv3d(x, k, bias, padding=(0, 1, 1))

        def wino():
            return output_transform(products(input_transform(x[0]), u, t), bias, t, h, w).unsqueeze(0)

        ref = conv3d()
        diff = (wino() - ref).abs().max().item() / ref.abs().max().item()
        base, total = best_s(conv3d), best_s(wino)
        v = input_transform(x[0])
        m = products(v, u, t)
        s_in = best_s(lambda: input_transform(x[0]))
        s_mm = best_s(lambda: products(v, u, t))
        s_out = best_s(lambda: output_transform(m, bias, t, h, w))
        gemm_flop = 2 * 16 * 3 * t * (h // 2) * (w // 2) * c * c
        print(f"  {c} channels, {t} frames of {h}x{w}: conv3d {base * 1e3:.1f}"
              f" ({2 * 27 * c * c * t * h * w / base / 1e9:.0f} GFLOP/s), winograd {total * 1e3:.1f}"
              f" ({base / total:.2f}x; {s_in * 1e3:.1f} + {s_mm * 1e3:.1f} ({gemm_flop / s_mm / 1e9:.0f} GFLOP/s)"
              f" + {s_out * 1e3:.1f}), max difference {diff:.1e} of the largest value")
    return 0


def pooled_conv(torch, dtype) -> int:
    """An encoder block's last causal 3x3x3 convolution (the first frame batch:
    the first frame twice in front) and the time-compressing downsampler's
    pooling (the first frame alone, then the mean of each pair), at the
    bench's shapes (best of 5 after 2 warm-ups): diffusers' order against
    this crate's (`CausalConv3d::forward_time_pooled`)."""
    F = torch.nn.functional
    print("pooled-conv: diffusers' order vs this crate's (ms), max difference")
    for c, t, h, w in [(128, 9, 128, 192), (256, 5, 64, 96)]:
        x = torch.randn(1, c, t, h, w, dtype=dtype)
        k = torch.randn(c, c, 3, 3, 3, dtype=dtype) * 0.03
        bias = torch.randn(c, dtype=dtype)
        # The pair-mean kernel: taps (W0, W0 + W1, W1 + W2, W2) / 2.
        v = (F.pad(k, (0, 0, 0, 0, 1, 0)) + F.pad(k, (0, 0, 0, 0, 0, 1))) * 0.5
        stacked = torch.cat([k.sum(2), v[:, :, 0]], 0)
        bias2 = torch.cat([bias, torch.zeros_like(bias)])

        def diffusers_order():
            padded = torch.cat([x[:, :, :1], x[:, :, :1], x], 2)
            y = F.conv3d(padded, k, bias, padding=(0, 1, 1))
            rest = F.avg_pool3d(y[:, :, 1:], kernel_size=(2, 1, 1), stride=(2, 1, 1))
            return torch.cat([y[:, :, :1], rest], 2)

        def this_crate():
            firsts = F.conv2d(x[:, :, 0], stacked, bias2, padding=1)
            pairs = F.conv3d(x, v, bias, stride=(2, 1, 1), padding=(1, 1, 1))
            pairs[:, :, :1] += firsts[:, c:].unsqueeze(2)
            return torch.cat([firsts[:, :c].unsqueeze(2), pairs], 2)

        def without_pair_means():
            # This crate before (2026-12-03): the first frame's taps summed
            # for output frames 0 and 1, conv3d for the rest, then the pooling.
            f0, f1 = x[:, :, 0], x[:, :, 1]
            y0 = F.conv2d(f0, k.sum(2), bias, padding=1)
            y1 = F.conv2d(f0, k[:, :, :2].sum(2), bias, padding=1) + F.conv2d(f1, k[:, :, 2], padding=1)
            y = torch.cat([y0.unsqueeze(2), y1.unsqueeze(2), F.conv3d(x, k, bias, padding=(0, 1, 1))], 2)
            rest = F.avg_pool3d(y[:, :, 1:], kernel_size=(2, 1, 1), stride=(2, 1, 1))
            return torch.cat([y[:, :, :1], rest], 2)

        report(torch, f"{c} channels, {t} frames of {h}x{w}", diffusers_order, this_crate)
        report(torch, "  the same, without pair means", diffusers_order, without_pair_means)
    return 0


def report(torch, label, theirs, ours):
    diff = (theirs() - ours()).abs().max().item()
    a, b = best_s(theirs), best_s(ours)
    print(f"  {label:<32} {a * 1e3:8.1f} {b * 1e3:8.1f}  {a / b:.2f}x  max diff {diff:.1e}")


if __name__ == "__main__":
    sys.exit(main())
