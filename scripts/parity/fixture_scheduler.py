"""Scheduler fixtures: a deterministic run of CogVideoXDDIMScheduler or
CogVideoXDPMScheduler, exactly as the CogVideoX pipelines call them.

io inputs:  sample [B,C,T,H,W], model_output [K,B,C,T,H,W] (the model output used at
            step k), num_inference_steps (scalar int64), noise_step_K_J (the J-th
            normal draw of DPM step K), original/noise/add_noise_timesteps
io outputs: timesteps [K], prev_sample_step_K, noisy (add_noise), velocity (get_velocity)
"""
import json
import os


def add_args(parser):
    parser.add_argument("--sampler", choices=["ddim", "dpm"], default="ddim")
    parser.add_argument("--preset", choices=["cogvideox-5b-i2v", "cogvideox-2b", "custom"], default="cogvideox-5b-i2v")
    parser.add_argument("--steps", type=int, default=8)
    parser.add_argument("--config-json", default=None, help="extra scheduler config fields as JSON (override the preset)")
    parser.add_argument("--shape", default="1,4,3,6,8", help="sample shape B,C,T,H,W")


PRESETS = {
    # THUDM/CogVideoX-5b-I2V and THUDM/CogVideoX-2b scheduler/scheduler_config.json
    "cogvideox-5b-i2v": dict(
        beta_end=0.012, beta_schedule="scaled_linear", beta_start=0.00085, clip_sample=False,
        clip_sample_range=1.0, num_train_timesteps=1000, prediction_type="v_prediction",
        rescale_betas_zero_snr=True, sample_max_value=1.0, set_alpha_to_one=True,
        snr_shift_scale=1.0, steps_offset=0, timestep_spacing="trailing", trained_betas=None,
    ),
    "cogvideox-2b": dict(
        beta_end=0.012, beta_schedule="scaled_linear", beta_start=0.00085, clip_sample=False,
        clip_sample_range=1.0, num_train_timesteps=1000, prediction_type="v_prediction",
        rescale_betas_zero_snr=True, sample_max_value=1.0, set_alpha_to_one=True,
        snr_shift_scale=3.0, steps_offset=0, timestep_spacing="trailing", trained_betas=None,
    ),
    "custom": {},
}


def build(args, model_dir):
    import torch
    from diffusers import CogVideoXDDIMScheduler, CogVideoXDPMScheduler

    cfg = dict(PRESETS[args.preset])
    if args.config_json:
        cfg.update(json.loads(args.config_json))
    cls = CogVideoXDDIMScheduler if args.sampler == "ddim" else CogVideoXDPMScheduler
    sched = cls(**cfg)
    os.makedirs(model_dir, exist_ok=True)
    sched.save_config(model_dir)

    shape = [int(x) for x in args.shape.split(",")]
    sample = torch.randn(shape)
    sched.set_timesteps(args.steps)
    timesteps = sched.timesteps.clone()
    k = len(timesteps)
    model_output = torch.randn([k] + shape)

    io = {
        "sample": sample.clone(),
        "model_output": model_output,
        "num_inference_steps": torch.tensor(args.steps, dtype=torch.int64),
        "timesteps": timesteps.to(torch.int64),
    }
    gen = torch.Generator().manual_seed(args.seed + 1)
    # Record DPM's normal draws: replay the step's draws on an identical generator.
    record = torch.Generator().manual_seed(args.seed + 1)
    latents = sample
    old_pred = None
    for i, t in enumerate(timesteps):
        if args.sampler == "ddim":
            latents = sched.step(model_output[i], t, latents, return_dict=False)[0]
        else:
            prev_t = t - sched.config.num_train_timesteps // sched.num_inference_steps
            draws = 2 if (old_pred is not None and prev_t >= 0) else 1
            for j in range(draws):
                io[f"noise_step_{i}_{j}"] = torch.randn(shape, generator=record, dtype=latents.dtype)
            latents, old_pred = sched.step(
                model_output[i], old_pred, t, timesteps[i - 1] if i > 0 else None, latents,
                generator=gen, return_dict=False,
            )
        io[f"prev_sample_step_{i}"] = latents.clone()

    original = torch.randn(shape)
    b = shape[0]
    io["original"] = original
    io["noise"] = torch.randn(shape)
    io["add_noise_timesteps"] = torch.randint(0, sched.config.num_train_timesteps, (b,), dtype=torch.int64)
    io["noisy"] = sched.add_noise(original, io["noise"], io["add_noise_timesteps"])
    io["velocity"] = sched.get_velocity(original, io["noise"], io["add_noise_timesteps"])
    meta = {"sampler": args.sampler, "preset": args.preset, "steps": args.steps, "config": dict(sched.config)}
    return meta, io
