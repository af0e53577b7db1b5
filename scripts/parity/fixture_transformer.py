"""Transformer fixtures: a randomly initialised diffusers CogVideoXTransformer3DModel
(LayerNorm affines and the learned positional embedding perturbed so they matter).

model/: save_pretrained() output (config.json + safetensors, sharded with --shard)
io inputs:  hidden_states [B,F,C,H,W], encoder_hidden_states [B,L,D_text], timestep [B] int64,
            ofs [1] (models with an ofs embedding)
io outputs: sample [B,F,C_out,H,W] with the rotary embedding that diffusers'
            CogVideoXImageToVideoPipeline computes for this latent grid (RoPE models);
            rope_cos / rope_sin: those tables;
            with --bf16 also sample_bf16: the same forward with the model and its inputs in
            bfloat16 (diffusers' own bf16 error is sample_bf16 - sample; stored as float32)
"""
import json
import types


def add_args(parser):
    parser.add_argument("--style", choices=["2b", "5b-i2v"], default="5b-i2v",
                        help="2b: sin-cos positions, 16 input channels; 5b-i2v: RoPE + learned positions, 32 channels")
    parser.add_argument("--shape", default="2,3,8,8,12", help="latents B,F,C,H,W")
    parser.add_argument("--layers", type=int, default=2)
    parser.add_argument("--sample-frames", type=int, default=None, help="config sample_frames (default: the F of --shape)")
    parser.add_argument("--sample-size", default=None, help="config sample H,W (default: the H,W of --shape)")
    parser.add_argument("--config-json", default=None, help="extra config fields as JSON")
    parser.add_argument("--shard", action="store_true", help="save in several shards")
    parser.add_argument("--bf16", action="store_true", help="also write sample_bf16 (the model run in bfloat16)")


def build(args, model_dir):
    import torch
    from diffusers import CogVideoXTransformer3DModel
    from diffusers.pipelines.cogvideo.pipeline_cogvideox_image2video import CogVideoXImageToVideoPipeline

    b, f, c, h, w = (int(v) for v in args.shape.split(","))
    sh, sw = (int(v) for v in args.sample_size.split(",")) if args.sample_size else (h, w)
    sample_frames = args.sample_frames if args.sample_frames else (f - 1) * 4 + 1
    text_len = 8
    cfg = dict(
        num_attention_heads=2, attention_head_dim=16, in_channels=c, out_channels=4,
        time_embed_dim=32, text_embed_dim=24, num_layers=args.layers,
        sample_width=sw, sample_height=sh, sample_frames=sample_frames,
        max_text_seq_length=text_len, patch_size=2,
    )
    if args.style == "5b-i2v":
        cfg.update(use_rotary_positional_embeddings=True, use_learned_positional_embeddings=True)
    if args.config_json:
        cfg.update(json.loads(args.config_json))
    model = CogVideoXTransformer3DModel(**cfg).eval()
    with torch.no_grad():
        for name, p in model.named_parameters():
            if "norm" in name:
                p.add_(0.1 * torch.randn_like(p))
            if name.endswith("pos_embedding"):
                p.add_(0.1 * torch.randn_like(p))
        if not cfg.get("use_learned_positional_embeddings") and hasattr(model.patch_embed, "pos_embedding"):
            pass  # sin-cos buffer: not a weight
    model.save_pretrained(model_dir, max_shard_size="200KB" if args.shard else "10GB", safe_serialization=True)
    hidden = torch.randn(b, f, c, h, w)
    text = torch.randn(b, text_len, cfg["text_embed_dim"])
    timestep = torch.randint(0, 1000, (b,), dtype=torch.int64)
    io = {"hidden_states": hidden, "encoder_hidden_states": text, "timestep": timestep}
    ofs = None
    if model.config.ofs_embed_dim:
        # The I2V pipeline's ofs value (CogVideoX 1.5): one value for the batch.
        ofs = torch.full((1,), 2.0)
        io["ofs"] = ofs
    rope = None
    if model.config.use_rotary_positional_embeddings:
        pipe = types.SimpleNamespace(vae_scale_factor_spatial=8, transformer=model)
        rope = CogVideoXImageToVideoPipeline._prepare_rotary_positional_embeddings(pipe, h * 8, w * 8, f, torch.device("cpu"))
        io["rope_cos"], io["rope_sin"] = rope
    with torch.no_grad():
        io["sample"] = model(hidden_states=hidden, encoder_hidden_states=text, timestep=timestep,
                             ofs=ofs, image_rotary_emb=rope, return_dict=False)[0]
        if args.bf16:
            # As a pipeline loaded with torch_dtype=torch.bfloat16 runs it: weights and
            # latents in bf16, the rotary tables in float32.
            # No module of this class is kept in float32 (_keep_in_fp32_modules is empty),
            # so the cast equals from_pretrained(torch_dtype=torch.bfloat16); quiet its warning.
            from diffusers.utils import logging as diffusers_logging
            diffusers_logging.set_verbosity_error()
            model.to(torch.bfloat16)
            io["sample_bf16"] = model(hidden_states=hidden.bfloat16(), encoder_hidden_states=text.bfloat16(),
                                      timestep=timestep, ofs=ofs, image_rotary_emb=rope,
                                      return_dict=False)[0].float()
    meta = {"style": args.style, "config": cfg, "shape": [b, f, c, h, w], "sharded": bool(args.shard),
            "bf16": bool(args.bf16)}
    return meta, io
