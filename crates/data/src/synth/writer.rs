//! Writing the generated episodes as a LeRobot v3.0 dataset with the
//! synthetic extras (`meta/synth.json`).

use super::{plan, Contact, Episode, SynthConfig, SynthError, World};
use rayon::prelude::*;
use serde::Serialize;

/// Errors of [`write_dataset`].
#[derive(Debug, thiserror::Error)]
pub enum WriteDatasetError {
    /// Generating an episode failed.
    #[error(transparent)]
    Synth(#[from] SynthError),
    /// Writing the dataset failed.
    #[error(transparent)]
    Dataset(#[from] crate::lerobot::DatasetError),
    /// The output exists.
    #[error("{0}: already exists; choose another --out or remove it")]
    Exists(std::path::PathBuf),
    /// Creating or committing the output folder failed.
    #[error(transparent)]
    Output(#[from] bridgev2w_io::output::OutputError),
    /// File-system failure.
    #[error("{path}: {source}")]
    Io {
        /// Path.
        path: std::path::PathBuf,
        /// Cause.
        source: std::io::Error,
    },
}

/// What [`write_dataset`] wrote.
#[derive(Debug, Clone, Serialize)]
pub struct DatasetSummary {
    /// The dataset directory.
    pub out: std::path::PathBuf,
    /// Episodes per split name.
    pub episodes_per_split: std::collections::BTreeMap<String, usize>,
    /// Episodes per task name.
    pub episodes_per_task: std::collections::BTreeMap<String, usize>,
    /// Total frames.
    pub total_frames: usize,
    /// Object-moving contacts (push, grasp) over all episodes.
    pub contact_events: usize,
    /// Perturbed demonstrations ([`super::Perturbation`]).
    pub perturbed: usize,
    /// Of those, the ones that fail the task.
    pub perturbed_failed: usize,
    /// `--engine mujoco`: episodes dropped because MuJoCo's physics went
    /// unstable (never written), and the first one's reason.
    pub dropped_unstable: usize,
    /// The first dropped episode and why.
    pub first_unstable: Option<String>,
    /// `--engine mujoco`: over the written episodes, the mean of their mean
    /// per-frame IoU of this project's masks against MuJoCo's segmentation,
    /// and the lowest frame's.
    pub mujoco_mask_iou: Option<(f64, f64)>,
    /// `--engine mujoco`: written episodes whose MuJoCo run ends as the
    /// home-made world's run of the same actions (within 3 cm).
    pub mujoco_as_planned: usize,
}

impl DatasetSummary {
    /// What `synth` prints: the folder, counts per split and task, contacts,
    /// perturbed demonstrations, and with MuJoCo the masks' check and the
    /// episodes dropped.
    pub fn report(&self, config: &SynthConfig) -> String {
        let written: usize = self.episodes_per_split.values().sum();
        let mut text = format!(
            "wrote {} (LeRobot v3.0): {written} episodes, {} frames of {}x{} at {} fps, robot {}, engine {}\n",
            self.out.display(),
            self.total_frames,
            config.width,
            config.height,
            config.fps,
            config.robot,
            config.engine
        );
        for (split, k) in &self.episodes_per_split {
            text.push_str(&format!("  split {split}: {k} episodes\n"));
        }
        for (task, k) in &self.episodes_per_task {
            text.push_str(&format!("  task {task}: {k} episodes\n"));
        }
        text.push_str(&format!(
            "  object contacts (push/grasp frames): {}\n",
            self.contact_events
        ));
        if self.perturbed > 0 {
            text.push_str(&format!(
                "  perturbed demonstrations (train): {}, of which {} fail the task\n",
                self.perturbed, self.perturbed_failed
            ));
        }
        if let Some((mean, min)) = self.mujoco_mask_iou {
            text.push_str(&format!(
                "  masks vs MuJoCo's segmentation of the robot: IoU mean {mean:.4}, lowest frame {min:.4}\n  ended as the home-made world's run of the same actions (within 3 cm): {} of {written}\n",
                self.mujoco_as_planned
            ));
        }
        if self.dropped_unstable > 0 {
            text.push_str(&format!(
                "  dropped: {} episode(s) whose physics went unstable (first: {})\n",
                self.dropped_unstable,
                self.first_unstable.as_deref().unwrap_or("?")
            ));
        }
        text
    }
}

/// The camera's video key in the dataset.
pub const VIDEO_KEY: &str = "observation.images.main";

/// Generates the configured episodes and writes them as a LeRobot v3.0
/// dataset at `out` (first into a temporary folder beside it, renamed when complete).
/// Episodes are rendered in parallel batches and written in plan order, so
/// the bytes do not depend on the thread count. `on_episode` is called after
/// each generated episode.
pub fn write_dataset(
    config: &SynthConfig,
    out: &std::path::Path,
    on_episode: &(dyn Fn() + Sync),
) -> Result<DatasetSummary, WriteDatasetError> {
    use crate::lerobot::{LeRobotV3Writer, WriterEpisode};
    use bridgev2w_io::output::{OutputDir, OutputError};
    let world = World::new(config)?;
    let engine = match config.engine {
        super::Engine::Builtin => None,
        super::Engine::Mujoco => Some(super::mujoco::MujocoEngine::new(
            &config.robot,
            super::mujoco::find_python()?,
        )?),
    };
    // Removed again if anything below fails.
    let output = OutputDir::create(out, false).map_err(|e| match e {
        OutputError::Exists { path } => WriteDatasetError::Exists(path),
        other => WriteDatasetError::Output(other),
    })?;
    let tmp = output.path().to_path_buf();
    let robot = &world.embodiment.robot;
    let state_names: Vec<String> = robot.dof_names().iter().map(|s| s.to_string()).collect();
    let mut action_names = Vec::new();
    for ee in &world.embodiment.end_effectors {
        for c in ["x", "y", "z", "roll", "pitch", "yaw", "gripper"] {
            action_names.push(format!("{}.{c}", ee.arm));
        }
    }
    let mut writer = LeRobotV3Writer::new(
        &tmp,
        &config.robot,
        config.fps,
        VIDEO_KEY,
        (config.width as usize, config.height as usize),
        state_names,
        action_names,
    )?;
    let plan = plan(config);
    let batch = (2 * rayon::current_num_threads()).max(4);
    let mut summary = DatasetSummary {
        out: out.to_path_buf(),
        episodes_per_split: Default::default(),
        episodes_per_task: Default::default(),
        total_frames: 0,
        contact_events: 0,
        perturbed: 0,
        perturbed_failed: 0,
        dropped_unstable: 0,
        first_unstable: None,
        mujoco_mask_iou: None,
        mujoco_as_planned: 0,
    };
    let mut ious: Vec<(f64, f64)> = Vec::new();
    let mut metas = Vec::new();
    for chunk in plan.chunks(batch) {
        let episodes: Vec<Result<Episode, String>> = chunk
            .par_iter()
            .map(|&(split, i, task)| {
                let e = world.generate(split, i, task)?;
                let e = match &engine {
                    None => Ok(e),
                    Some(engine) => match engine.simulate(&world, e)? {
                        super::mujoco::Simulated::Stable(e) => Ok(*e),
                        super::mujoco::Simulated::Unstable { reason } => {
                            Err(format!("episode {i} of split {}: {reason}", split.name()))
                        }
                    },
                };
                on_episode();
                Ok::<_, SynthError>(e)
            })
            .collect::<Result<_, _>>()?;
        let (episodes, dropped): (Vec<_>, Vec<_>) = episodes.into_iter().partition(Result::is_ok);
        summary.dropped_unstable += dropped.len();
        if summary.first_unstable.is_none() {
            summary.first_unstable = dropped.into_iter().find_map(Result::err);
        }
        let episodes: Vec<Episode> = episodes.into_iter().flatten().collect();
        summary.mujoco_as_planned += episodes
            .iter()
            .filter(|e| e.meta.mujoco.as_ref().is_some_and(|m| m.as_planned))
            .count();
        ious.extend(
            episodes
                .iter()
                .filter_map(|e| e.meta.mujoco.as_ref())
                .map(|m| (m.mask_iou_mean, m.mask_iou_min)),
        );
        for e in &episodes {
            let f32s = |rows: &[Vec<f64>]| -> Vec<Vec<f32>> {
                rows.iter()
                    .map(|r| r.iter().map(|&v| v as f32).collect())
                    .collect()
            };
            let index = writer.add_episode(WriterEpisode {
                task: e.meta.task.description(),
                split: Some(e.meta.split.name()),
                states: f32s(&e.joints),
                actions: f32s(&e.actions),
                rgb: &e.rgb,
                masks: Some(&e.masks),
                labels: Some(&e.labels),
                camera: Some(&e.camera),
            })?;
            if let Some(frames) = &e.mujoco_masks {
                let (h, w) = (config.height as usize, config.width as usize);
                let path = tmp.join(format!("mujoco_masks/episode_{index:06}.npy"));
                let flat: Vec<u8> = frames.concat();
                std::fs::create_dir_all(tmp.join("mujoco_masks"))
                    .and_then(|()| {
                        bridgev2w_io::npy::write_npy(&path, &[frames.len(), h, w], &flat)
                            .map_err(std::io::Error::other)
                    })
                    .map_err(|source| WriteDatasetError::Io {
                        path: path.clone(),
                        source,
                    })?;
            }
            *summary
                .episodes_per_split
                .entry(e.meta.split.name().into())
                .or_default() += 1;
            *summary
                .episodes_per_task
                .entry(e.meta.task.name().into())
                .or_default() += 1;
            summary.total_frames += e.rgb.len();
            if let Some(p) = &e.meta.perturbation {
                summary.perturbed += 1;
                summary.perturbed_failed += usize::from(!p.success);
            }
            summary.contact_events += e
                .contacts
                .iter()
                .flatten()
                .filter(|c| matches!(c, Contact::Pushed | Contact::Grasped))
                .count();
            let mut m = serde_json::to_value(&e.meta).unwrap_or_default();
            if let Some(o) = m.as_object_mut() {
                o.insert("episode_index".into(), serde_json::json!(index));
            }
            metas.push(m);
        }
    }
    if metas.is_empty() && summary.dropped_unstable > 0 {
        return Err(SynthError::Engine(format!(
            "every episode's physics went unstable, nothing to write (first: {})",
            summary.first_unstable.as_deref().unwrap_or("?")
        ))
        .into());
    }
    if !ious.is_empty() {
        summary.mujoco_mask_iou = Some((
            ious.iter().map(|p| p.0).sum::<f64>() / ious.len() as f64,
            ious.iter().map(|p| p.1).fold(1.0, f64::min),
        ));
    }
    let specs = serde_json::to_value(&world.specs).unwrap_or_default();
    // The links the actions are poses of (the TCPs), as `convert` names
    // its flanges: datasets of different frames are told apart.
    let ee_frame: Vec<String> = world
        .embodiment
        .end_effectors
        .iter()
        .map(|ee| world.embodiment.robot.links[ee.link].name.clone())
        .collect();
    writer.finish(serde_json::json!({
        "synth_splits": specs.clone(),
        "bridgev2w_source": {"format": "synth", "ee_frame": ee_frame},
    }))?;
    let synth_path = tmp.join("meta/synth.json");
    let synth = serde_json::json!({
        "generator": "bridgev2w synth",
        "config": config,
        "scene_frame": world.frame,
        "video_key": VIDEO_KEY,
        "splits": specs,
        "episodes": metas,
    });
    let text = serde_json::to_string_pretty(&synth).unwrap_or_default();
    std::fs::write(&synth_path, text).map_err(|source| WriteDatasetError::Io {
        path: synth_path.clone(),
        source,
    })?;
    output.commit()?;
    Ok(summary)
}
