//! `bridgev2w demo`: the built-in Franka doing a pick-and-place, seen from a
//! built-in camera; writes masks, labels, PNGs and an animated GIF overlay.
//! Then the world model: the shipped small BridgeV2W (trained on the
//! synthetic world by `scripts/reproduce-synthetic.sh`) predicts the video of
//! a built-in synthetic pick-and-place from its first frame and the masks of
//! its actions: `prediction.mp4` and a side-by-side GIF.

use crate::masks_cmd::{render_with_progress, report_empty, write_ik_report};
use crate::overlay::{floor_background, overlay, write_gif};
use anyhow::{bail, Context, Result};
use bridgev2w_data::synth::{Split, SynthConfig, Task, World};
use bridgev2w_data::video::Mp4VideoWriter;
use bridgev2w_embodiment::actions::{actions_to_joints, Trajectory};
use bridgev2w_embodiment::camera::{Camera, Intrinsics};
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_embodiment::kinematics::{xyz_rpy_from_pose, IkOptions};
use bridgev2w_embodiment::masks::{write_outputs, WriteOptions};
use bridgev2w_embodiment::npy::write_atomic;
use bridgev2w_embodiment::output::OutputDir;
use bridgev2w_eval::clip::{compare_with_copy, ClipScore};
use bridgev2w_eval::video::Frame;
use bridgev2w_world_model::bridge::{BridgeV2W, BridgeV2WConfig};
use bridgev2w_world_model::pipeline::{FirstFrame, PredictOptions, SampleOptions, WorldModel};
use bridgev2w_world_model::video::{Image, MaskVideo};
use bridgev2w_world_model::{ComputeDevice, Precision};
use nalgebra::{Point3, UnitQuaternion, Vector3};
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Arguments of `demo`.
#[derive(Debug, clap::Args)]
pub struct DemoArgs {
    /// Output directory (written to OUT.tmp, then renamed). An earlier
    /// demo's output there is replaced; any other existing folder is refused
    /// unless --overwrite.
    #[arg(long, default_value = "demo-out")]
    pub out: PathBuf,
    /// Replace an existing --out folder that is not an earlier demo's output.
    #[arg(long)]
    pub overwrite: bool,
    /// Frames in the trajectory (CogVideoX clips are 49 frames).
    #[arg(long, default_value_t = 49)]
    pub frames: usize,
    /// The world model for the prediction: a folder with `backbone/` (a
    /// diffusers CogVideoX I2V folder) and `bridgev2w.safetensors`; default:
    /// the shipped demo model (assets/demo-model).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Skip the world-model prediction (masks and overlay only).
    #[arg(long)]
    pub no_predict: bool,
    /// Denoising steps of the prediction.
    #[arg(long, default_value_t = 20)]
    pub steps: usize,
    /// Sampling seed of the prediction.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// The first latent frame of the prediction: `generated` (diffusers'
    /// sampler) or `replaced` by the image latent at every step.
    #[arg(long, default_value = "generated")]
    pub first_frame: FirstFrame,
}

/// The shipped demo model: `assets/demo-model` under the working directory,
/// else in the source tree the binary was built from.
fn default_model_dir() -> PathBuf {
    let local = PathBuf::from("assets/demo-model");
    if local.is_dir() {
        local
    } else {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/demo-model")
    }
}

/// Nearest-neighbour upscaling of an RGB8 image by `k`.
fn upscale(rgb: &[u8], w: usize, h: usize, k: usize) -> Vec<u8> {
    let mut out = Vec::with_capacity(rgb.len() * k * k);
    for y in 0..h * k {
        for x in 0..w * k {
            let i = ((y / k) * w + x / k) * 3;
            out.extend_from_slice(&rgb[i..i + 3]);
        }
    }
    out
}

/// Panels of equal size side by side: `[H, W * n, 3]`.
fn side_by_side(panels: &[&[u8]], w: usize, h: usize) -> Vec<u8> {
    let mut out = Vec::with_capacity(panels.len() * w * h * 3);
    for y in 0..h {
        for p in panels {
            out.extend_from_slice(&p[y * w * 3..(y + 1) * w * 3]);
        }
    }
    out
}

/// The world-model half of the demo: predicts the video of a built-in
/// synthetic pick-and-place (unseen camera) from its first frame and masks.
fn predict(args: &DemoArgs, tmp: &Path) -> Result<()> {
    let t0 = Instant::now();
    let dir = args.model.clone().unwrap_or_else(default_model_dir);
    let (backbone, weights) = (dir.join("backbone"), dir.join("bridgev2w.safetensors"));
    if !backbone.is_dir() || !weights.is_file() {
        bail!(
            "demo model {}: expected backbone/ (a diffusers CogVideoX I2V folder) and bridgev2w.safetensors; \
             pass --model DIR, or --no-predict for masks only",
            dir.display()
        );
    }
    let model = BridgeV2W::load(
        &backbone,
        Some(&weights),
        None,
        BridgeV2WConfig::paper(),
        ComputeDevice::auto(),
        Precision::F32,
    )
    .with_context(|| format!("loading the demo model from {}", dir.display()))?;
    let (h, w) = model.resolution();
    let frames = model.clip_frames();
    // The built-in scene: a pick-and-place of the synthetic world, seen from
    // a camera region the model never trained on.
    let world = World::new(&SynthConfig {
        frames: 2 * frames - 1,
        width: w as u32,
        height: h as u32,
        seed: 2026,
        tasks: vec![Task::PickPlace],
        episodes_per_split: [0, 0, 1, 0],
        ..SynthConfig::default()
    })?;
    let episode = world.generate(Split::UnseenCamera, 0, Task::PickPlace)?;
    let image = Image {
        height: h,
        width: w,
        data: episode.rgb[0]
            .iter()
            .map(|&v| f32::from(v) / 255.0)
            .collect(),
    };
    let masks = MaskVideo {
        frames,
        height: h,
        width: w,
        data: episode.masks[..frames].concat(),
    };
    let opts = PredictOptions {
        sample: SampleOptions {
            steps: args.steps,
            guidance_scale: 1.0,
            dynamic_cfg: false,
            seed: args.seed,
            first_frame: args.first_frame,
        },
    };
    let video = model.predict(&image, &masks, &opts)?;
    let px = h * w * 3;
    let pred: Vec<Vec<u8>> = video
        .data
        .chunks(px)
        .map(|f| {
            f.iter()
                .map(|v| (v * 255.0).round().clamp(0.0, 255.0) as u8)
                .collect()
        })
        .collect();
    let out = tmp;
    let mut writer = Mp4VideoWriter::new(&out.join("prediction.mp4"), w, h, 10)?;
    for (i, f) in pred.iter().enumerate() {
        writer.push(f, i == 0)?;
    }
    write_atomic(&out.join("prediction.mp4"), &writer.to_bytes()?)?;
    // first frame | masks | prediction | ground truth, 3x upscaled
    let k = 3;
    let first = upscale(&episode.rgb[0], w, h, k);
    let gif: Vec<Vec<u8>> = (0..frames)
        .map(|t| {
            let mask: Vec<u8> = episode.masks[t]
                .iter()
                .flat_map(|&m| if m != 0 { [255, 255, 255] } else { [0, 0, 0] })
                .collect();
            let mask = upscale(&mask, w, h, k);
            let p = upscale(&pred[t], w, h, k);
            let g = upscale(&episode.rgb[t], w, h, k);
            side_by_side(&[&first, &mask, &p, &g], w * k, h * k)
        })
        .collect();
    let gif_path = out.join("prediction.gif");
    write_gif(&gif_path, (4 * w * k) as u32, (h * k) as u32, &gif, 5)?;
    write_atomic(
        &out.join("prediction-actions.json"),
        serde_json::to_string(&episode.actions[..frames])?.as_bytes(),
    )?;
    // The prediction against the ground truth, next to copying the first frame.
    let to_frames = |clip: &[Vec<u8>]| -> Result<Vec<Frame>> {
        Ok(clip
            .iter()
            .map(|f| Frame::from_rgb8(w, h, f))
            .collect::<std::result::Result<_, _>>()?)
    };
    let scores = compare_with_copy(&to_frames(&pred)?, &to_frames(&episode.rgb[..frames])?)?;
    let json = |s: &ClipScore| serde_json::json!({"psnr": s.psnr, "ssim": s.ssim, "dynamic_psnr": s.dynamic_psnr});
    write_atomic(
        &out.join("prediction-scores.json"),
        serde_json::to_string_pretty(&serde_json::json!({
            "prediction": json(&scores.prediction),
            "copy_first_frame": json(&scores.copy_first_frame),
        }))?
        .as_bytes(),
    )?;
    let dynamic = |s: &ClipScore| {
        s.dynamic_psnr
            .map_or_else(|| "-".to_owned(), |v| format!("{v:.2} dB"))
    };
    println!(
        "  against the ground truth: PSNR {:.2} dB, SSIM {:.3}, dynamic-region PSNR {} (copying the first frame: {:.2} dB, {:.3}, {})",
        scores.prediction.psnr,
        scores.prediction.ssim,
        dynamic(&scores.prediction),
        scores.copy_first_frame.psnr,
        scores.copy_first_frame.ssim,
        dynamic(&scores.copy_first_frame),
    );
    println!(
        "  world model ({}): {frames} frames at {w}x{h} predicted from the first frame and the masks of a built-in pick-and-place (unseen camera), {} steps, in {:.1} s",
        dir.display(),
        args.steps,
        t0.elapsed().as_secs_f64()
    );
    println!(
        "  {0}/prediction.mp4, {0}/prediction.gif (first frame | masks | prediction | ground truth), prediction-actions.json, prediction-scores.json",
        args.out.display()
    );
    Ok(())
}

/// The built-in demo camera: 720x480, looking at the Franka's workspace
/// from the front-right, about 1.3 m away.
pub fn demo_camera() -> Result<Camera> {
    let intrinsics = Intrinsics::centered(560.0, 720, 480);
    Ok(Camera::look_at(
        intrinsics,
        Point3::new(1.3, 0.8, 0.85),
        Point3::new(0.38, 0.0, 0.36),
        Vector3::z(),
    )?)
}

/// A pick-and-place in end-effector space: from home, approach, descend,
/// grasp, lift, carry, lower, release. `[x,y,z,roll,pitch,yaw,gripper]` rows.
pub fn demo_actions(e: &Embodiment, frames: usize) -> Result<Trajectory> {
    let ee = e
        .end_effectors
        .first()
        .context("robot has no end effector")?;
    let home = e.robot.link_pose(ee.link, &e.home);
    // (x, y, z, yaw offset, gripper)
    let keys: [(f64, f64, f64, f64, f64); 8] = [
        (
            home.translation.x,
            home.translation.y,
            home.translation.z,
            0.0,
            0.0,
        ),
        (0.50, 0.15, 0.25, 0.3, 0.0),
        (0.50, 0.15, 0.13, 0.3, 0.0),
        (0.50, 0.15, 0.13, 0.3, 1.0),
        (0.50, 0.15, 0.30, 0.3, 1.0),
        (0.40, -0.20, 0.30, -0.2, 1.0),
        (0.40, -0.20, 0.15, -0.2, 1.0),
        (0.40, -0.20, 0.15, -0.2, 0.0),
    ];
    let frames = frames.max(2);
    let rows = (0..frames)
        .map(|f| {
            let s = f as f64 / (frames - 1) as f64 * (keys.len() - 1) as f64;
            let k = (s.floor() as usize).min(keys.len() - 2);
            let t = s - k as f64;
            // Smoothstep within each segment: the arm eases in and out.
            let t = t * t * (3.0 - 2.0 * t);
            let (a, b) = (keys[k], keys[k + 1]);
            let lerp = |x: f64, y: f64| x + (y - x) * t;
            let yaw = lerp(a.3, b.3);
            let mut pose = home;
            pose.translation.vector = Vector3::new(lerp(a.0, b.0), lerp(a.1, b.1), lerp(a.2, b.2));
            pose.rotation =
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw) * home.rotation;
            let mut row = xyz_rpy_from_pose(&pose).to_vec();
            row.push(lerp(a.4, b.4));
            row
        })
        .collect();
    Ok(Trajectory::new("built-in demo trajectory", rows)?)
}

/// An earlier demo's output (the files every demo writes).
fn is_earlier_demo(out: &Path) -> bool {
    ["overlay.gif", "camera.json", "actions.json", "masks.npy"]
        .iter()
        .all(|f| out.join(f).is_file())
}

pub fn run(args: &DemoArgs) -> Result<()> {
    let start = Instant::now();
    let output = OutputDir::create(&args.out, args.overwrite || is_earlier_demo(&args.out))?;
    let e = Embodiment::builtin("franka")?;
    let camera = demo_camera()?;
    let actions = demo_actions(&e, args.frames)?;
    let (joints, residuals) = actions_to_joints(
        &e.robot,
        &e.end_effectors,
        &actions,
        &e.home,
        &IkOptions::default(),
        false,
    )?;
    // Depth as well: the overlay shades the links by it.
    let frames = render_with_progress(&e, &camera, &joints, true);
    let out = output.path();
    let written = write_outputs(
        out,
        &e.robot,
        &frames,
        WriteOptions {
            pngs: true,
            depth: false,
        },
    )?;
    write_ik_report(out, &residuals)?;
    write_atomic(&out.join("camera.json"), camera.to_json().as_bytes())?;
    write_atomic(
        &out.join("actions.json"),
        serde_json::to_string(&actions.rows)?.as_bytes(),
    )?;
    let background = floor_background(&camera);
    let rgb: Vec<Vec<u8>> = frames.par_iter().map(|f| overlay(f, &background)).collect();
    let gif = out.join("overlay.gif");
    write_gif(
        &gif,
        camera.intrinsics.width,
        camera.intrinsics.height,
        &rgb,
        10,
    )?;
    let still = out.join("overlay.png");
    let mid = &rgb[rgb.len() / 2];
    let png = bridgev2w_embodiment::png::encode_rgb8(
        camera.intrinsics.width,
        camera.intrinsics.height,
        mid,
    );
    write_atomic(&still, &png)?;
    report_empty(&written.empty_frames, frames.len());
    let max_res_mm = residuals
        .iter()
        .map(|r| r.position_error_m)
        .fold(0.0, f64::max)
        * 1e3;
    if !args.no_predict {
        predict(args, out)?;
    }
    output.commit()?;
    let out = args.out.as_path();
    let (gif, still) = (out.join("overlay.gif"), out.join("overlay.png"));
    println!(
        "demo: {} frames of the Franka pick-and-place at 720x480 (IK max residual {max_res_mm:.4} mm) in {:.2} s",
        frames.len(),
        start.elapsed().as_secs_f64()
    );
    println!(
        "  {}/masks.npy, labels.npy, labels.json, frames/*.png",
        out.display()
    );
    println!(
        "  {}, {}  (colour overlay: animation, middle frame)",
        gif.display(),
        still.display()
    );
    println!(
        "  {}/actions.json + camera.json: re-render with",
        out.display()
    );
    println!(
        "  bridgev2w masks --robot franka --camera {0}/camera.json --actions {0}/actions.json --out OUT",
        out.display()
    );
    Ok(())
}
