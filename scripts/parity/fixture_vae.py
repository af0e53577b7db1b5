"""VAE parity fixtures: diffusers `AutoencoderKLCogVideoX` (random, perturbed weights).

    make_parity_fixture.py vae --out DIR [--seed S] [--preset tiny] [--batch B]
        [--frames T] [--height H] [--width W] [--latent-frames t]
        [--tiling [--tile-sample-height H --tile-sample-width W
                   --tile-overlap-height F --tile-overlap-width F]]
        [--slicing] [--sample-seed S] [--noise-std STD] [--bf16]

io.safetensors:
  video         [B, 3, T, H, W] uniform in [-1, 1]       (input of encode)
  latent_mean   [B, C, t, h, w] posterior mean of encode  (unscaled)
  latent_sample [B, C, t, h, w] posterior.sample(torch.Generator().manual_seed(sample_seed))
  latents       [B, C, t', h', w'] standard normal        (input of decode)
  decoded       [B, 3, T', H', W'] decode(latents)
  with --bf16 also latent_mean_bf16 and decoded_bf16: the same with the model and its inputs
  in bfloat16 (diffusers' own bf16 error; stored as float32)

meta.json: {"config": the diffusers config, "options": {batch, frames, height, width,
latent_frames, tiling: null | {tile_sample_min_height, tile_sample_min_width,
tile_overlap_factor_height, tile_overlap_factor_width}, slicing, sample_seed, noise_std}}.
"""

BLOCKS = 4

# Configs by name. `cogvideox-5b-i2v` is THUDM/CogVideoX-5b-I2V's vae/config.json
# (the architecture of every CogVideoX 1.0 VAE; CogVideoX-2b differs only in
# scaling_factor 1.15258426); `tiny` keeps the structure (4 blocks, 2 of them compressing
# time) with a few channels for fast tests.
PRESETS = {
    "cogvideox-5b-i2v": dict(
        in_channels=3,
        out_channels=3,
        down_block_types=["CogVideoXDownBlock3D"] * 4,
        up_block_types=["CogVideoXUpBlock3D"] * 4,
        block_out_channels=[128, 256, 256, 512],
        latent_channels=16,
        layers_per_block=3,
        act_fn="silu",
        norm_eps=1e-6,
        norm_num_groups=32,
        temporal_compression_ratio=4,
        sample_height=480,
        sample_width=720,
        scaling_factor=0.7,
        force_upcast=True,
        use_quant_conv=False,
        use_post_quant_conv=False,
    ),
    "tiny": dict(
        in_channels=3,
        out_channels=3,
        down_block_types=["CogVideoXDownBlock3D"] * 4,
        up_block_types=["CogVideoXUpBlock3D"] * 4,
        block_out_channels=[8, 16, 16, 24],
        latent_channels=4,
        layers_per_block=1,
        act_fn="silu",
        norm_eps=1e-6,
        norm_num_groups=4,
        temporal_compression_ratio=4,
        sample_height=32,
        sample_width=32,
        scaling_factor=0.7,
        force_upcast=True,
        use_quant_conv=False,
        use_post_quant_conv=False,
    ),
}
PRESETS["cogvideox-2b"] = dict(PRESETS["cogvideox-5b-i2v"], scaling_factor=1.15258426)


def add_args(parser):
    parser.add_argument("--preset", choices=sorted(PRESETS), default="tiny")
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--frames", type=int, default=9)
    parser.add_argument("--height", type=int, default=16)
    parser.add_argument("--width", type=int, default=16)
    parser.add_argument(
        "--latent-frames", type=int, default=None, help="frames of the decode input (default: those of the encode output)"
    )
    parser.add_argument("--tiling", action="store_true", help="enable_tiling() before encode and decode")
    parser.add_argument("--tile-sample-height", type=int, default=None)
    parser.add_argument("--tile-sample-width", type=int, default=None)
    parser.add_argument("--tile-overlap-height", type=float, default=None)
    parser.add_argument("--tile-overlap-width", type=float, default=None)
    parser.add_argument("--slicing", action="store_true", help="enable_slicing() (batch split into samples)")
    parser.add_argument("--sample-seed", type=int, default=1234, help="seed of the posterior sample's generator")
    parser.add_argument(
        "--noise-std", type=float, default=0.05, help="std of the noise added to every parameter (zero-inits hide bugs)"
    )
    parser.add_argument("--bf16", action="store_true", help="also write the bfloat16 outputs (*_bf16)")


def build(args, model_dir):
    import torch
    from diffusers import AutoencoderKLCogVideoX

    config = dict(PRESETS[args.preset])
    model = AutoencoderKLCogVideoX(**config)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(torch.randn_like(p) * args.noise_std)
    model.eval()
    model.save_pretrained(model_dir, safe_serialization=True)

    tiling = None
    if args.tiling:
        model.enable_tiling(
            tile_sample_min_height=args.tile_sample_height,
            tile_sample_min_width=args.tile_sample_width,
            tile_overlap_factor_height=args.tile_overlap_height,
            tile_overlap_factor_width=args.tile_overlap_width,
        )
        tiling = dict(
            tile_sample_min_height=model.tile_sample_min_height,
            tile_sample_min_width=model.tile_sample_min_width,
            tile_overlap_factor_height=model.tile_overlap_factor_height,
            tile_overlap_factor_width=model.tile_overlap_factor_width,
        )
    if args.slicing:
        model.enable_slicing()

    video = torch.rand(args.batch, config["in_channels"], args.frames, args.height, args.width) * 2 - 1
    with torch.no_grad():
        posterior = model.encode(video).latent_dist
        latent_mean = posterior.mean
        latent_sample = posterior.sample(generator=torch.Generator().manual_seed(args.sample_seed))
        shape = list(latent_mean.shape)
        if args.latent_frames is not None:
            shape[2] = args.latent_frames
        latents = torch.randn(shape)
        decoded = model.decode(latents).sample
        if args.bf16:
            # As from_pretrained(torch_dtype=torch.bfloat16) loads it (no module of this
            # class is kept in float32); quiet the cast's warning.
            from diffusers.utils import logging as diffusers_logging
            diffusers_logging.set_verbosity_error()
            model.to(torch.bfloat16)
            latent_mean_bf16 = model.encode(video.bfloat16()).latent_dist.mean.float()
            decoded_bf16 = model.decode(latents.bfloat16()).sample.float()

    meta = {
        "config": config,
        "options": {
            "preset": args.preset,
            "batch": args.batch,
            "frames": args.frames,
            "height": args.height,
            "width": args.width,
            "latent_frames": shape[2],
            "tiling": tiling,
            "slicing": args.slicing,
            "sample_seed": args.sample_seed,
            "noise_std": args.noise_std,
            "bf16": args.bf16,
        },
    }
    io = {
        "video": video,
        "latent_mean": latent_mean,
        "latent_sample": latent_sample,
        "latents": latents,
        "decoded": decoded,
    }
    if args.bf16:
        io["latent_mean_bf16"] = latent_mean_bf16
        io["decoded_bf16"] = decoded_bf16
    return meta, io
