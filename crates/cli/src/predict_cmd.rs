//! `bridgev2w predict`: the video a mask sequence causes, from a first frame;
//! several mask sequences (clips) from the same frame in batches.

use crate::progress::TerminalProgress;
use anyhow::Result;
use bridgev2w_train::predict_files::PredictJob;
use bridgev2w_world_model::bridge::BridgeV2W;
use bridgev2w_world_model::pipeline::{BatchNoise, SampleOptions, WorldModel};
use bridgev2w_world_model::spec::ModelSpec;
use bridgev2w_world_model::vae::{TileSize, VaeTiling};
use bridgev2w_world_model::{ComputeDevice, Precision};
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct PredictArgs {
    /// A CogVideoX image-to-video diffusers folder (model_index.json, vae/,
    /// transformer/, scheduler/), or `random:PRESET` (random weights of tiny,
    /// small, small2x or small2x-wide at 9 frames of 96x64: a smoke test
    /// whose output is noise).
    #[arg(long)]
    model: ModelSpec,
    /// BridgeV2W weights (ControlNet + LoRA safetensors written by `bridgev2w train`).
    #[arg(long)]
    weights: Option<PathBuf>,
    /// The fixed prompt's T5 embedding (scripts/encode_prompt.py); default: zeros.
    #[arg(long)]
    prompt_embeds: Option<PathBuf>,
    /// The first frame (PNG/JPEG; resized to the model's resolution if needed).
    #[arg(long)]
    image: PathBuf,
    /// Embodiment masks, uint8 `[T, H, W]` `.npy` (`bridgev2w masks` writes masks.npy)
    /// at the model's frames and resolution. Repeat it, or name a folder (its
    /// `.npy` files, by name), to predict several clips from the same --image
    /// in one call: each clip is written to OUT/NAME/ (NAME: the file's stem,
    /// or NNN-STEM numbered in order when two stems are the same) and
    /// OUT/clips.json lists the clips and their masks.
    #[arg(long, required = true)]
    masks: Vec<PathBuf>,
    /// Output folder: frames/000000.png..., video.npy (uint8 [T, H, W, 3]),
    /// video.mp4 (H.264), or one such folder per clip when several --masks;
    /// written to a temporary folder beside it, then renamed (all clips or none). An existing one
    /// is refused unless --overwrite.
    #[arg(long)]
    out: PathBuf,
    /// Replace an existing --out folder (as a whole: no earlier file stays).
    #[arg(long)]
    overwrite: bool,
    /// Denoising steps.
    #[arg(long, default_value_t = 50)]
    steps: usize,
    /// Classifier-free guidance scale (1 = off).
    #[arg(long, default_value_t = 6.0)]
    guidance: f64,
    /// CogVideoX's dynamic guidance schedule.
    #[arg(long)]
    dynamic_cfg: bool,
    /// Where sampling starts, in (0, 1]: 1 from pure noise (diffusers'
    /// pipeline); s < 1 from the first frame's latent in every frame, noised
    /// to the level a fraction s from the end (only the last ceil(s * steps)
    /// steps run).
    #[arg(long, default_value_t = 1.0)]
    strength: f64,
    /// Keep the static scene (beyond the paper): outside the region the
    /// robot's masks have swept so far, dilated by this many pixels, each
    /// predicted frame is the first frame. Off when not given.
    #[arg(long, value_name = "MARGIN_PX")]
    keep_static: Option<u32>,
    /// The seed of the noise (every clip of a call gets the same: see --batch-size).
    #[arg(long, default_value_t = 42)]
    seed: u64,
    /// Clips denoised together: per batch the first frame is encoded once,
    /// the masks in one VAE call, and each denoising step is one transformer
    /// call for all clips (two with guidance). Lower it if memory runs out.
    /// The clips of a batch share one noise draw (not diffusers' independent
    /// draw per batch item), so a clip's video does not depend on the batch
    /// size or the other clips: it is the video a call with its masks alone
    /// and the same --seed gives (to float rounding: one uint8 level).
    #[arg(long, default_value_t = 4)]
    batch_size: usize,
    /// cpu, cuda, cuda:N or auto.
    #[arg(long, default_value = "auto")]
    device: ComputeDevice,
    /// f32 or bf16.
    #[arg(long, default_value = "f32")]
    precision: Precision,
    /// Run the VAE without spatial tiling (tiling, as diffusers'
    /// `vae.enable_tiling()`, bounds memory at 720x480; it is on by default
    /// for frames above 256x256 pixels).
    #[arg(long)]
    no_vae_tiling: bool,
    /// The VAE's spatial tiles, HEIGHTxWIDTH pixels, at any resolution (e.g.
    /// 144x200, a third of CogVideoX's default 240x360, for a smaller decode
    /// peak on a smaller GPU; tiles that would not join exactly are
    /// refused). Default: the VAE's own tiles above 256x256 pixels.
    #[arg(long, value_name = "HxW", conflicts_with = "no_vae_tiling")]
    vae_tile: Option<TileSize>,
}

fn load_model(a: &PredictArgs) -> Result<BridgeV2W> {
    Ok(a.model.load_bridge(
        a.weights.as_deref(),
        a.prompt_embeds.as_deref(),
        a.device,
        a.precision,
        a.seed as i64,
    )?)
}

pub fn run(a: &PredictArgs) -> Result<()> {
    a.model
        .check_inputs(a.weights.as_deref(), a.prompt_embeds.as_deref())?;
    let job = PredictJob {
        image: a.image.clone(),
        masks: a.masks.clone(),
        out: a.out.clone(),
        overwrite: a.overwrite,
        batch_size: a.batch_size,
        sample: SampleOptions {
            steps: a.steps,
            guidance_scale: a.guidance,
            dynamic_cfg: a.dynamic_cfg,
            seed: a.seed,
            first_frame: Default::default(),
            // Each clip the noise of a batch of one: its single prediction.
            batch_noise: BatchNoise::Shared,
            strength: a.strength,
            keep_static_margin_px: a.keep_static,
        },
        other_inputs: a.weights.iter().chain(&a.prompt_embeds).cloned().collect(),
    };
    // Options, clips and --out are checked before the model is loaded.
    let job = job.prepare()?;
    let mut model = load_model(a)?;
    let res = model.resolution();
    let tiling = match (a.vae_tile, a.no_vae_tiling) {
        (Some(size), _) => VaeTiling::Tiles(size),
        (None, true) => VaeTiling::Off,
        (None, false) => VaeTiling::Auto,
    };
    model.vae.set_tiling(tiling, res, "--vae-tile")?;
    let n = job.clips().len();
    let batches = n.div_ceil(a.batch_size);
    eprintln!(
        "predicting {} frames at {}x{} (HxW), {} steps, guidance {}{}...",
        model.clip_frames(),
        res.0,
        res.1,
        a.steps,
        a.guidance,
        if n > 1 {
            format!(
                ", {n} clips in {batches} batch{} of up to {}",
                if batches == 1 { "" } else { "es" },
                a.batch_size
            )
        } else {
            String::new()
        }
    );
    let run = job.run(&model, &TerminalProgress::default())?;
    println!("{}", run.summary());
    Ok(())
}
