//! `bridgev2w predict`: the video a mask sequence causes, from a first frame;
//! several mask sequences (clips) from the same frame in batches.

use crate::progress::TerminalProgress;
use anyhow::{bail, Context, Result};
use bridgev2w_data::video::Mp4VideoWriter;
use bridgev2w_io::frame::{u8_from_unit, unit_from_u8, RgbFrame};
use bridgev2w_io::json::write_json_atomic;
use bridgev2w_io::npy::{read_npy, write_atomic, write_npy};
use bridgev2w_io::output::OutputDir;
use bridgev2w_io::png::encode_rgb8;
use bridgev2w_io::progress::Progress;
use bridgev2w_world_model::bridge::BridgeV2W;
use bridgev2w_world_model::pipeline::{BatchNoise, PredictOptions, SampleOptions, WorldModel};
use bridgev2w_world_model::spec::ModelSpec;
use bridgev2w_world_model::vae::{TileSize, VaeTiling};
use bridgev2w_world_model::video::{MaskVideo, Video};
use bridgev2w_world_model::{ComputeDevice, Precision};
use std::path::{Path, PathBuf};

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

fn read_image(path: &Path, (h, w): (usize, usize)) -> Result<RgbFrame> {
    let img = image::open(path)
        .with_context(|| format!("--image {}: not a readable image", path.display()))?
        .to_rgb8();
    let img = if img.dimensions() != (w as u32, h as u32) {
        eprintln!(
            "note: resizing {} from {}x{} to the model's {w}x{h} (WxH)",
            path.display(),
            img.width(),
            img.height()
        );
        image::imageops::resize(
            &img,
            w as u32,
            h as u32,
            image::imageops::FilterType::Triangle,
        )
    } else {
        img
    };
    Ok(RgbFrame {
        width: w,
        height: h,
        rgb: img.as_raw().iter().map(|&v| unit_from_u8(v)).collect(),
    })
}

fn read_masks(path: &Path, frames: usize, (h, w): (usize, usize)) -> Result<MaskVideo> {
    let arr = read_npy(path)?;
    let [t, mh, mw] = arr.shape[..] else {
        bail!(
            "--masks {}: shape {:?}, expected [T, H, W]",
            path.display(),
            arr.shape
        );
    };
    if (t, mh, mw) != (frames, h, w) {
        bail!(
            "--masks {}: shape [{t}, {mh}, {mw}] but the model takes [{frames}, {h}, {w}] \
             (render them with `bridgev2w masks ... --width {w} --height {h}` over {frames} frames)",
            path.display()
        );
    }
    // Binary masks (uint8 or bool, 0/1 or 0/255: masks.npy of `bridgev2w
    // masks`; a grey value is refused) or link labels (uint16 up to 255: its
    // labels.npy, which a `links` model needs and a binary one reads as the
    // silhouette). Soft (float) masks would be read as "non-zero = robot"
    // without a word: refused.
    let data = match arr.descr.as_str() {
        "|u1" | "|b1" => arr
            .binary_mask()
            .map_err(|m| anyhow::anyhow!("--masks {}: {m}", path.display()))?,
        "<u2" => match arr.data.iter().find(|&&v| v > 255.0) {
            Some(v) => bail!(
                "--masks {}: link label {v}, expected labels up to 255",
                path.display()
            ),
            None => arr.data.iter().map(|&v| v as u8).collect(),
        },
        other => bail!(
            "--masks {}: dtype {other}, expected uint8 or bool binary masks (0/1 or 0/255, masks.npy of `bridgev2w masks`) or uint16 link labels (its labels.npy)",
            path.display(),
        ),
    };
    Ok(MaskVideo {
        frames,
        height: h,
        width: w,
        data,
    })
}

/// One clip of a call: its masks and the subfolder of --out it goes to
/// (`None`: --out itself, the single-clip layout).
#[derive(Debug, Clone, PartialEq)]
struct Clip {
    name: Option<String>,
    masks: PathBuf,
}

/// The clips of `--masks`: files as given, folders as their `.npy` files by
/// name. One file keeps the single-clip layout; otherwise each clip is
/// named by its file's stem (`NNN-STEM`, numbered in order, when stems repeat).
fn clips(masks: &[PathBuf]) -> Result<Vec<Clip>> {
    let mut files = Vec::new();
    for m in masks {
        if m.is_dir() {
            let mut found: Vec<PathBuf> = std::fs::read_dir(m)
                .with_context(|| format!("--masks {}: reading the folder", m.display()))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| {
                    p.is_file() && p.extension().is_some_and(|e| e.eq_ignore_ascii_case("npy"))
                })
                .collect();
            if found.is_empty() {
                bail!(
                    "--masks {}: no .npy files in this folder (expected uint8 [T, H, W] masks as `bridgev2w masks` writes)",
                    m.display()
                );
            }
            found.sort();
            files.extend(found);
        } else {
            files.push(m.clone());
        }
    }
    if let ([one], [file]) = (masks, files.as_slice()) {
        if one == file {
            return Ok(vec![Clip {
                name: None,
                masks: file.clone(),
            }]);
        }
    }
    // A clip's name is its mask file's stem, and becomes a folder under
    // --out: it must be a plain name (`...npy` has the stem `..`).
    let stems: Vec<String> = files
        .iter()
        .map(|f| {
            let stem = f
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_else(|| "clip".to_owned());
            bridgev2w_io::confine::check_name(&stem).map_err(|e| {
                anyhow::anyhow!(
                    "--masks {}: the clip name taken from this file's name is {e}",
                    f.display()
                )
            })?;
            Ok(stem)
        })
        .collect::<Result<_>>()?;
    let unique = stems
        .iter()
        .collect::<std::collections::BTreeSet<_>>()
        .len()
        == stems.len();
    Ok(files
        .into_iter()
        .zip(stems)
        .enumerate()
        .map(|(i, (masks, stem))| Clip {
            name: Some(if unique {
                stem
            } else {
                format!("{i:03}-{stem}")
            }),
            masks,
        })
        .collect())
}

/// Writes one predicted clip into `dir`: frames/NNNNNN.png, video.npy and
/// video.mp4.
fn write_clip(dir: &Path, video: &Video) -> Result<()> {
    let bytes: Vec<u8> = video.data.iter().map(|&v| u8_from_unit(v)).collect();
    let frames_dir = dir.join("frames");
    std::fs::create_dir_all(&frames_dir)
        .with_context(|| format!("creating {}", frames_dir.display()))?;
    let frame_len = video.height * video.width * 3;
    for (i, frame) in bytes.chunks(frame_len).enumerate() {
        let path = frames_dir.join(format!("{i:06}.png"));
        write_atomic(
            &path,
            &encode_rgb8(video.width as u32, video.height as u32, frame),
        )
        .with_context(|| format!("writing {}", path.display()))?;
    }
    write_npy(
        &dir.join("video.npy"),
        &[video.frames, video.height, video.width, 3],
        &bytes,
    )?;
    // The same frames as H.264 for people to watch (8 frames per second,
    // CogVideoX's rate).
    let mp4 = dir.join("video.mp4");
    let mut writer = Mp4VideoWriter::new(&mp4, video.width, video.height, 8)?;
    for (i, frame) in bytes.chunks(frame_len).enumerate() {
        writer.push(frame, i == 0)?;
    }
    write_atomic(&mp4, &writer.to_bytes()?).with_context(|| format!("writing {}", mp4.display()))
}

pub fn run(a: &PredictArgs) -> Result<()> {
    bridgev2w_world_model::bridge::check_predict_batch("--batch-size", a.batch_size)?;
    a.model
        .check_inputs(a.weights.as_deref(), a.prompt_embeds.as_deref())?;
    let sample = SampleOptions {
        steps: a.steps,
        guidance_scale: a.guidance,
        dynamic_cfg: a.dynamic_cfg,
        seed: a.seed,
        first_frame: Default::default(),
        // Each clip the noise of a batch of one: its single prediction.
        batch_noise: BatchNoise::Shared,
        strength: a.strength,
        keep_static_margin_px: a.keep_static,
    };
    // --steps, --guidance and --strength, before the model is loaded.
    sample.validate()?;
    let clips = clips(&a.masks)?;
    // An output equal to, inside or containing an input would delete it.
    let inputs: Vec<&Path> = a
        .masks
        .iter()
        .map(PathBuf::as_path)
        .chain([a.image.as_path()])
        .chain(a.weights.as_deref())
        .chain(a.prompt_embeds.as_deref())
        .collect();
    let out = OutputDir::create_for(&a.out, a.overwrite, &inputs)?;
    let mut model = load_model(a)?;
    let res = model.resolution();
    let tiling = match (a.vae_tile, a.no_vae_tiling) {
        (Some(size), _) => VaeTiling::Tiles(size),
        (None, true) => VaeTiling::Off,
        (None, false) => VaeTiling::Auto,
    };
    model.vae.set_tiling(tiling, res, "--vae-tile")?;
    let image = read_image(&a.image, res)?;
    // Every clip's masks are checked before the first is predicted.
    for clip in &clips {
        read_masks(&clip.masks, model.clip_frames(), res)?;
    }
    let opts = PredictOptions {
        sample,
        max_batch: None,
        ..PredictOptions::default()
    };
    let batches = clips.len().div_ceil(a.batch_size);
    eprintln!(
        "predicting {} frames at {}x{} (HxW), {} steps, guidance {}{}...",
        model.clip_frames(),
        res.0,
        res.1,
        a.steps,
        a.guidance,
        if clips.len() > 1 {
            format!(
                ", {} clips in {batches} batch{} of up to {}",
                clips.len(),
                if batches == 1 { "" } else { "es" },
                a.batch_size
            )
        } else {
            String::new()
        }
    );
    let progress = TerminalProgress::default();
    let t0 = std::time::Instant::now();
    for (b, batch) in clips.chunks(a.batch_size).enumerate() {
        if batches > 1 {
            progress.note(&format!("batch {}/{batches}", b + 1));
        }
        let masks = batch
            .iter()
            .map(|c| read_masks(&c.masks, model.clip_frames(), res))
            .collect::<Result<Vec<_>>>()?;
        let frames = vec![image.clone(); batch.len()];
        let videos = model.predict_batch_with_progress(&frames, &masks, &opts, &progress)?;
        for (clip, video) in batch.iter().zip(&videos) {
            let dir = match &clip.name {
                Some(name) => out.path().join(name),
                None => out.path().to_path_buf(),
            };
            write_clip(&dir, video)?;
        }
    }
    let secs = t0.elapsed().as_secs_f64();
    if clips.iter().any(|c| c.name.is_some()) {
        let list: Vec<serde_json::Value> = clips
            .iter()
            .map(|c| serde_json::json!({"name": c.name, "masks": c.masks}))
            .collect();
        write_json_atomic(
            &out.path().join("clips.json"),
            &serde_json::json!({ "seed": a.seed, "steps": a.steps, "clips": list }),
        )?;
    }
    out.commit()?;
    let what = match clips.len() {
        1 => format!("{} frames", model.clip_frames()),
        n => format!("{n} clips of {} frames", model.clip_frames()),
    };
    println!("wrote {what} to {} ({secs:.1} s)", a.out.display());
    Ok(())
}
