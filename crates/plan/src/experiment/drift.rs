//! Drift over long horizons (`bridgev2w eval-drift`): the expert's actions
//! of a long episode, chunk after chunk, rolled out autoregressively in the
//! world model (each chunk predicted from the model's own last frame) and
//! executed in the synthetic world; per chunk index, the predicted frame at
//! the chunk's end against the world's (PSNR, SSIM), beside copying the
//! first frame. With `keep_static_margin_px` the same rollouts are made a
//! second time with the static scene re-anchored on the first frame (the
//! lever against drift this project has beyond the paper: outside the
//! region the masks have swept, each predicted frame is the first frame).

use super::{LoadedModel, ModelOptions};
use crate::synthetic::{SyntheticEnv, TaskInstance};
use crate::{EeAction, PlanError, Result};
use bridgev2w_data::synth::{Split, Task};
use bridgev2w_eval::video::{psnr, ssim};

/// One drift study.
#[derive(Debug, Clone)]
pub struct DriftOptions {
    /// The task whose expert episodes are replayed.
    pub task: Task,
    /// Episodes (task instances of the split).
    pub trials: usize,
    /// The world model.
    pub model: ModelOptions,
    /// Chunks per rollout (each the model's clip minus its first frame).
    pub chunks: usize,
    /// A second variant with the static scene kept (pixels of margin).
    pub keep_static_margin_px: Option<u32>,
    /// Split of the task instances.
    pub split: Split,
    /// Seed of the world.
    pub seed: u64,
}

impl DriftOptions {
    /// The defaults of `bridgev2w eval-drift` for `task`: 4 episodes, 5 chunks.
    pub fn new(task: Task) -> Self {
        Self {
            task,
            trials: 4,
            model: ModelOptions::default(),
            chunks: 5,
            keep_static_margin_px: None,
            split: Split::Test,
            seed: 0,
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
    /// With the static scene kept, when asked: its margin and rows.
    pub keep_static: Option<(u32, Vec<DriftRow>)>,
}

/// Rolls `instances`' expert actions out in `loaded` and in the world.
fn rows(
    loaded: &LoadedModel,
    world: &bridgev2w_data::synth::World,
    instances: &[TaskInstance],
    chunk_actions: usize,
    chunks: usize,
) -> Result<Vec<DriftRow>> {
    let mut sums = vec![(0.0, 0.0, 0.0); chunks];
    for inst in instances {
        let actions: Vec<EeAction> = inst.expert_actions();
        let mut env = SyntheticEnv::new(world, inst.clone());
        let start = env.observe();
        let per_chunk: Vec<Vec<EeAction>> = actions
            .chunks(chunk_actions)
            .take(chunks)
            .map(<[EeAction]>::to_vec)
            .collect();
        let truth = per_chunk
            .iter()
            .map(|c| env.execute(c).map(|o| o.image))
            .collect::<Result<Vec<_>>>()?;
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
        for (k, (p, t)) in predicted.iter().zip(&truth).enumerate() {
            sums[k].0 += psnr(p, t)?;
            sums[k].1 += ssim(p, t)?;
            sums[k].2 += psnr(&start.image, t)?;
        }
    }
    let n = instances.len() as f64;
    Ok(sums
        .iter()
        .enumerate()
        .map(|(k, (p, s, c))| DriftRow {
            chunk: k + 1,
            psnr_db: p / n,
            ssim: s / n,
            copy_psnr_db: c / n,
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
    let plain = rows(&loaded, &world, &instances, chunk_actions, o.chunks)?;
    progress(&format!(
        "drift: {} episodes x {} chunks of {chunk_actions} actions",
        o.trials, o.chunks
    ));
    let keep_static = match o.keep_static_margin_px {
        None => None,
        Some(margin) => {
            let kept = LoadedModel::load(&ModelOptions {
                keep_static_margin_px: Some(margin),
                ..o.model.clone()
            })?;
            progress(&format!(
                "drift: again with the static scene kept ({margin} px)"
            ));
            Some((
                margin,
                rows(&kept, &world, &instances, chunk_actions, o.chunks)?,
            ))
        }
    };
    Ok(DriftReport {
        chunk_actions,
        trials: o.trials,
        plain,
        keep_static,
    })
}

impl DriftReport {
    /// The report as a markdown table: per chunk index, the model's PSNR
    /// and SSIM against the world (and with the static scene kept), and
    /// copying the first frame.
    pub fn markdown(&self) -> String {
        let mut s = format!(
            "Drift over {} chunks of {} actions ({} episodes; each chunk predicted from the model's own last frame):\n\n| chunk | actions done | PSNR (dB) | SSIM |",
            self.plain.len(),
            self.chunk_actions,
            self.trials
        );
        if let Some((m, _)) = &self.keep_static {
            s += &format!(" PSNR, static kept ({m} px) | SSIM, static kept |");
        }
        s += " copying the first frame (dB) |\n|---|---|---|---|";
        if self.keep_static.is_some() {
            s += "---|---|";
        }
        s += "---|\n";
        for (i, r) in self.plain.iter().enumerate() {
            s += &format!(
                "| {} | {} | {:.2} | {:.3} |",
                r.chunk,
                r.chunk * self.chunk_actions,
                r.psnr_db,
                r.ssim
            );
            if let Some((_, k)) = &self.keep_static {
                s += &format!(" {:.2} | {:.3} |", k[i].psnr_db, k[i].ssim);
            }
            s += &format!(" {:.2} |\n", r.copy_psnr_db);
        }
        s
    }
}
