//! Drift over long horizons (`bridgev2w eval-drift`): the expert's actions
//! of a long episode, chunk after chunk, rolled out autoregressively in the
//! world model (each chunk predicted from the model's own last frame) and
//! executed in the synthetic world; per chunk index, the predicted frame at
//! the chunk's end against the world's (PSNR, SSIM), beside copying the
//! first frame. With `keep_static_margin_px` the same rollouts are made a
//! second time with the static scene re-anchored on the first frame (the
//! lever against drift this project has beyond the paper: outside the
//! region the masks have swept, each predicted frame is the first frame).
//!
//! Mask-IoU per chunk: the robot in each predicted frame, found by a colour
//! segmenter (`bridgev2w_eval::segment::ColorSegmenter`, fitted on the
//! world's training-split episodes of the task), against the true robot
//! mask of the world's state at the chunk's end; beside it the segmenter's
//! ceiling (its Mask-IoU on the world's own frame) and copying the first
//! frame (how far the arm has moved from where it started).

use super::{LoadedModel, ModelOptions, Sampling};
use crate::synthetic::image_from_rgb8;
use crate::synthetic::{SyntheticEnv, TaskInstance};
use crate::{EeAction, PlanError, Result};
use bridgev2w_data::synth::{Split, Task, World};
use bridgev2w_embodiment::masks::render_trajectory_labels;
use bridgev2w_eval::segment::ColorSegmenter;
use bridgev2w_eval::video::{mask_iou, psnr, ssim};
use bridgev2w_io::frame::RgbFrame;

/// Training-split episodes the Mask-IoU segmenter is fitted on.
const SEGMENTER_EPISODES: usize = 4;
/// Colour levels per channel of the segmenter (as `eval-run --segmenter color`).
const SEGMENTER_BITS: u32 = 5;

/// One drift study (the flags of `bridgev2w eval-drift`).
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct DriftOptions {
    /// reach, push or pick_place: whose expert episodes are replayed.
    #[cfg_attr(feature = "clap", arg(long, value_parser = Task::parse_goal_task, default_value = "pick_place"))]
    pub task: Task,
    /// Episodes (task instances of the split).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DriftOptions::default().trials))]
    pub trials: usize,
    /// The world model.
    #[cfg_attr(feature = "clap", command(flatten))]
    pub model: ModelOptions,
    /// Chunks per rollout, each predicted from the model's own last frame
    /// (each the model's clip minus its first frame; 5: five times the clip).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DriftOptions::default().chunks))]
    pub chunks: usize,
    /// Also roll out with the static scene kept outside the swept region,
    /// dilated by this many pixels (the lever against drift), side by side.
    #[cfg_attr(
        feature = "clap",
        arg(
            id = "compare_keep_static",
            long = "compare-keep-static",
            value_name = "MARGIN_PX"
        )
    )]
    pub keep_static_margin_px: Option<u32>,
    /// Split of the task instances.
    #[cfg_attr(feature = "clap", arg(long, default_value = "test", value_parser = Split::parse_named))]
    pub split: Split,
    /// Seed of the world.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DriftOptions::default().seed))]
    pub seed: u64,
}

impl Default for DriftOptions {
    /// `pick_place`, 4 episodes of the test split, 5 chunks, the perfect model.
    fn default() -> Self {
        Self {
            task: Task::PickPlace,
            trials: 4,
            model: ModelOptions::default(),
            chunks: 5,
            keep_static_margin_px: None,
            split: Split::Test,
            seed: 0,
        }
    }
}

impl DriftOptions {
    /// The defaults of `bridgev2w eval-drift` for `task`: 4 episodes, 5 chunks.
    pub fn new(task: Task) -> Self {
        Self {
            task,
            ..Self::default()
        }
    }
}

/// Per chunk index, means over the episodes.
#[derive(Debug, Clone, PartialEq)]
pub struct DriftRow {
    /// Chunk index (1: the first chunk's end).
    pub chunk: usize,
    /// PSNR of the model's frame against the world's (dB).
    pub psnr_db: f64,
    /// SSIM of the same.
    pub ssim: f64,
    /// PSNR of the first frame against the world's (dB): copying.
    pub copy_psnr_db: f64,
    /// Mask-IoU of the robot found in the model's frame against the true mask.
    pub mask_iou: f64,
    /// Mask-IoU of the robot found in the first frame (copying).
    pub copy_mask_iou: f64,
    /// Mask-IoU of the robot found in the world's own frame: the
    /// segmenter's ceiling.
    pub truth_mask_iou: f64,
}

/// The colour segmenter of the Mask-IoU, fitted on the first
/// [`SEGMENTER_EPISODES`] training-split episodes of `task`.
fn fit_segmenter(world: &World, task: Task) -> Result<ColorSegmenter> {
    let mut seg = ColorSegmenter::new(SEGMENTER_BITS)?;
    for i in 0..SEGMENTER_EPISODES {
        let e = world.generate(Split::Train, i, task)?;
        let (w, h) = (
            e.camera.intrinsics.width as usize,
            e.camera.intrinsics.height as usize,
        );
        for (rgb, mask) in e.rgb.iter().zip(&e.masks) {
            seg.observe(&image_from_rgb8(rgb, h, w), mask)?;
        }
    }
    Ok(seg)
}

/// The true robot mask (0/1) of `env`'s current state.
fn true_mask(env: &SyntheticEnv) -> Vec<u8> {
    let labels = render_trajectory_labels(
        &env.world.embodiment.robot,
        &env.instance.expert.camera,
        std::slice::from_ref(&env.state.joints),
        &|| {},
    );
    labels
        .first()
        .map(|l| l.iter().map(|&v| u8::from(v != 0)).collect())
        .unwrap_or_default()
}

/// What [`drift_study`] measured.
#[derive(Debug, Clone, PartialEq)]
pub struct DriftReport {
    /// Actions per chunk.
    pub chunk_actions: usize,
    /// Episodes.
    pub trials: usize,
    /// The model's rows, per chunk index.
    pub plain: Vec<DriftRow>,
    /// Robot and other pixels the Mask-IoU segmenter was fitted on.
    pub segmenter_pixels: (u64, u64),
    /// With the static scene kept, when asked: its margin and rows.
    pub keep_static: Option<(u32, Vec<DriftRow>)>,
}

/// Rolls `instances`' expert actions out in `loaded` and in the world.
fn rows(
    loaded: &LoadedModel,
    world: &World,
    segmenter: &ColorSegmenter,
    instances: &[TaskInstance],
    chunk_actions: usize,
    chunks: usize,
) -> Result<Vec<DriftRow>> {
    let mut sums = vec![[0.0; 6]; chunks];
    for inst in instances {
        let actions: Vec<EeAction> = inst.expert_actions();
        let mut env = SyntheticEnv::new(world, inst.clone());
        let start = env.observe();
        let per_chunk: Vec<Vec<EeAction>> = actions
            .chunks(chunk_actions)
            .take(chunks)
            .map(<[EeAction]>::to_vec)
            .collect();
        let truth: Vec<(RgbFrame, Vec<u8>)> = per_chunk
            .iter()
            .map(|c| Ok((env.execute(c)?.image, true_mask(&env))))
            .collect::<Result<_>>()?;
        let start_robot = segmenter.segment(&start.image);
        let predicted = loaded.with_model(world, inst, &mut |m| {
            let mut obs = start.clone();
            let mut frames = Vec::new();
            for c in &per_chunk {
                obs = m
                    .rollout_batch(&obs, std::slice::from_ref(c))?
                    .pop()
                    .ok_or_else(|| PlanError::Invalid("the model returned no rollout".into()))?;
                frames.push(obs.image.clone());
            }
            Ok(frames)
        })?;
        for (k, (p, (t, mask))) in predicted.iter().zip(&truth).enumerate() {
            let scores = [
                psnr(p, t)?,
                ssim(p, t)?,
                psnr(&start.image, t)?,
                mask_iou(&segmenter.segment(p), mask)?,
                mask_iou(&start_robot, mask)?,
                mask_iou(&segmenter.segment(t), mask)?,
            ];
            for (sum, v) in sums[k].iter_mut().zip(scores) {
                *sum += v;
            }
        }
    }
    let n = instances.len() as f64;
    Ok(sums
        .iter()
        .enumerate()
        .map(|(k, s)| DriftRow {
            chunk: k + 1,
            psnr_db: s[0] / n,
            ssim: s[1] / n,
            copy_psnr_db: s[2] / n,
            mask_iou: s[3] / n,
            copy_mask_iou: s[4] / n,
            truth_mask_iou: s[5] / n,
        })
        .collect())
}

/// Runs the study; `progress` gets a line per variant.
pub fn drift_study(o: &DriftOptions, progress: &mut dyn FnMut(&str)) -> Result<DriftReport> {
    if o.trials == 0 {
        return Err(PlanError::input("--trials", "must be at least 1"));
    }
    if !(1..=50).contains(&o.chunks) {
        return Err(PlanError::input(
            "--chunks",
            format!("{}: expected 1..=50 chunks", o.chunks),
        ));
    }
    o.model.check_sizes()?;
    super::sizes::check_trials("--trials", o.trials)?;
    let loaded = LoadedModel::load(&o.model)?;
    let chunk_actions = loaded.clip_frames().saturating_sub(1).max(1);
    let episode_frames = o.chunks * chunk_actions + 1;
    super::sizes::check_episode_frames(episode_frames)?;
    let world = loaded.world(episode_frames, o.seed)?;
    let instances: Vec<TaskInstance> = (0..o.trials)
        .map(|i| TaskInstance::new(&world, o.split, i, o.task))
        .collect::<Result<_>>()?;
    let segmenter = fit_segmenter(&world, o.task)?;
    let plain = rows(
        &loaded,
        &world,
        &segmenter,
        &instances,
        chunk_actions,
        o.chunks,
    )?;
    progress(&format!(
        "drift: {} episodes x {} chunks of {chunk_actions} actions",
        o.trials, o.chunks
    ));
    let keep_static = match o.keep_static_margin_px {
        None => None,
        Some(margin) => {
            let kept = LoadedModel::load(&ModelOptions {
                sampling: Sampling {
                    keep_static_margin_px: Some(margin),
                    ..o.model.sampling
                },
                ..o.model.clone()
            })?;
            progress(&format!(
                "drift: again with the static scene kept ({margin} px)"
            ));
            Some((
                margin,
                rows(
                    &kept,
                    &world,
                    &segmenter,
                    &instances,
                    chunk_actions,
                    o.chunks,
                )?,
            ))
        }
    };
    Ok(DriftReport {
        chunk_actions,
        trials: o.trials,
        plain,
        segmenter_pixels: segmenter.counts(),
        keep_static,
    })
}

impl DriftReport {
    /// The report as a markdown table: per chunk index, the model's PSNR,
    /// SSIM and Mask-IoU against the world (and with the static scene
    /// kept), copying the first frame, and the segmenter's ceiling.
    pub fn markdown(&self) -> String {
        let mut s = format!(
            "Drift over {} chunks of {} actions ({} episodes; each chunk predicted from the model's own last frame):\n\n| chunk | actions done | PSNR (dB) | SSIM | Mask-IoU |",
            self.plain.len(),
            self.chunk_actions,
            self.trials
        );
        if let Some((m, _)) = &self.keep_static {
            s += &format!(
                " PSNR, static kept ({m} px) | SSIM, static kept | Mask-IoU, static kept |"
            );
        }
        s += " copying: PSNR (dB) | copying: Mask-IoU | Mask-IoU of the true frame |\n|---|---|---|---|---|";
        if self.keep_static.is_some() {
            s += "---|---|---|";
        }
        s += "---|---|---|\n";
        for (i, r) in self.plain.iter().enumerate() {
            s += &format!(
                "| {} | {} | {:.2} | {:.3} | {:.3} |",
                r.chunk,
                r.chunk * self.chunk_actions,
                r.psnr_db,
                r.ssim,
                r.mask_iou
            );
            if let Some((_, k)) = &self.keep_static {
                s += &format!(
                    " {:.2} | {:.3} | {:.3} |",
                    k[i].psnr_db, k[i].ssim, k[i].mask_iou
                );
            }
            s += &format!(
                " {:.2} | {:.3} | {:.3} |\n",
                r.copy_psnr_db, r.copy_mask_iou, r.truth_mask_iou
            );
        }
        let (total, robot) = self.segmenter_pixels;
        s += &format!(
            "\nMask-IoU: the robot found by a colour segmenter ({SEGMENTER_BITS} bits per channel, fitted on {SEGMENTER_EPISODES} training-split episodes of the task: {robot} robot of {total} pixels) against the true robot mask at the chunk's end; its ceiling is the last column.\n"
        );
        s
    }
}
