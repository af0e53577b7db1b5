//! The sizes of the planning experiments, checked before anything of that
//! size is allocated: each against its stated maximum (the synthetic
//! world's for its images, episodes and task instances, the world model's
//! for clips and batches, [`MAX_CEM_SAMPLES`] for candidates), and the
//! candidates of one CEM iteration against the machine's memory
//! ([`check_candidates_memory`]). Errors name the flag, its value and the
//! maximum.

use super::{LoadedModel, ModelOptions, PlanOptions};
use crate::Result;
use bridgev2w_data::synth::{MAX_EPISODES, MAX_FRAMES, MAX_SIDE};
use bridgev2w_io::memory::{at_most, bytes, check_fits};
use bridgev2w_world_model::bridge::{check_predict_batch, MAX_CLIP_FRAMES};

/// The most candidate action sequences a CEM iteration evaluates (`plan
/// --samples`, `plan-fidelity --candidates`): 1024 times the paper's 64.
pub const MAX_CEM_SAMPLES: usize = 65_536;

/// What lowers the memory of a CEM iteration's candidates.
const CANDIDATES_MEMORY_ADVICE: &str = "Lower --samples (or --candidates), --max-batch, --clip-frames or the image size (--width/--height with the perfect model)";

impl ModelOptions {
    /// Checks the sizes: the perfect model's image within the synthetic
    /// world's [`MAX_SIDE`], `--clip-frames` within the world model's
    /// [`MAX_CLIP_FRAMES`], `--max-batch` within
    /// [`bridgev2w_world_model::bridge::MAX_PREDICT_BATCH`].
    pub fn check_sizes(&self) -> Result<()> {
        at_most("--width", self.width.into(), MAX_SIDE.into(), "pixels")?;
        at_most("--height", self.height.into(), MAX_SIDE.into(), "pixels")?;
        if let Some(frames) = self.clip_frames {
            at_most(
                "--clip-frames",
                frames as u64,
                MAX_CLIP_FRAMES as u64,
                "frames",
            )?;
        }
        if let Some(n) = self.max_batch {
            check_predict_batch("--max-batch", n)?;
        }
        Ok(())
    }
}

impl PlanOptions {
    /// Checks the sizes of `bridgev2w plan`: the model's
    /// ([`ModelOptions::check_sizes`]), `--trials` within the synthetic
    /// world's [`MAX_EPISODES`] task instances, `--samples` within
    /// [`MAX_CEM_SAMPLES`], `--episode-frames` within its [`MAX_FRAMES`],
    /// and a planned clip (`--horizon` x `--frames-per-action` + 1) within
    /// [`MAX_CLIP_FRAMES`].
    pub fn check_sizes(&self) -> Result<()> {
        self.model.check_sizes()?;
        check_trials("--trials", self.trials)?;
        check_candidates("--samples", self.cem.samples)?;
        check_episode_frames(self.episode_frames)?;
        let clip = self
            .cem
            .horizon
            .saturating_mul(self.frames_per_action)
            .saturating_add(1);
        at_most(
            &format!(
                "--horizon {} x --frames-per-action {} + 1",
                self.cem.horizon, self.frames_per_action
            ),
            clip as u64,
            MAX_CLIP_FRAMES as u64,
            "clip frames",
        )?;
        Ok(())
    }
}

/// `trials` (named `name`) within [`MAX_EPISODES`], the task instances a
/// split may have.
pub fn check_trials(name: &str, trials: usize) -> Result<()> {
    at_most(name, trials as u64, MAX_EPISODES as u64, "trials")?;
    Ok(())
}

/// `candidates` (named `name`) within [`MAX_CEM_SAMPLES`].
pub fn check_candidates(name: &str, candidates: usize) -> Result<()> {
    at_most(
        name,
        candidates as u64,
        MAX_CEM_SAMPLES as u64,
        "candidates",
    )?;
    Ok(())
}

/// `--episode-frames` within the synthetic world's [`MAX_FRAMES`].
pub fn check_episode_frames(frames: usize) -> Result<()> {
    at_most(
        "--episode-frames",
        frames as u64,
        MAX_FRAMES as u64,
        "frames",
    )?;
    Ok(())
}

/// A floor of the memory of evaluating `candidates` action sequences at
/// once with `loaded`, in bytes. The perfect model: each candidate's
/// observed frame (float RGB, 12 bytes a pixel). A diffusion model: each
/// candidate's masks (2 bytes a pixel of every clip frame: rendered and
/// batched), its first frame and its predicted clip (12 bytes a pixel of
/// every frame), and [`bridgev2w_world_model::bridge::BridgeV2W::predict_bytes`]
/// of one model call (`--max-batch` candidates, all by default; its device
/// part only on a CPU).
pub fn candidates_bytes(loaded: &LoadedModel, candidates: usize) -> u64 {
    let c = candidates as u64;
    match loaded {
        LoadedModel::Perfect { width, height, .. } => {
            bytes(&[c, u64::from(*width), u64::from(*height), 12])
        }
        LoadedModel::Diffusion {
            model, max_batch, ..
        } => {
            let cfg = model.config();
            let pixels = bytes(&[cfg.height as u64, cfg.width as u64]);
            let clips = bytes(&[c, cfg.frames as u64, pixels, 2 + 12]);
            let first = bytes(&[c, pixels, 12]);
            let call = model.predict_bytes(max_batch.map_or(candidates, |m| m.min(candidates)));
            let device = if model.device().is_cuda() {
                0
            } else {
                call.device
            };
            clips
                .saturating_add(first)
                .saturating_add(call.host)
                .saturating_add(device)
        }
    }
}

/// Refuses `candidates` action sequences per model call (named `name`)
/// whose [`candidates_bytes`] exceed the machine's memory, with the
/// estimate, before the first trial.
pub fn check_candidates_memory(loaded: &LoadedModel, name: &str, candidates: usize) -> Result<()> {
    let (h, w) = loaded.resolution();
    check_fits(
        &format!("evaluating {candidates} candidates ({name}) of {h}x{w} pixels at once"),
        candidates_bytes(loaded, candidates),
        CANDIDATES_MEMORY_ADVICE,
    )?;
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use bridgev2w_data::synth::Task;

    #[test]
    fn plan_sizes_beyond_their_maximum_are_refused_naming_the_flag() {
        let ok = PlanOptions::new(Task::Reach);
        assert!(ok.check_sizes().is_ok());
        let refused = |o: PlanOptions, needle: &str| {
            let e = o.check_sizes().unwrap_err().to_string();
            assert!(e.contains(needle), "{e}");
        };
        let mut o = ok.clone();
        o.cem.samples = MAX_CEM_SAMPLES + 1;
        refused(o, "--samples 65537: at most 65536 candidates");
        let mut o = ok.clone();
        o.trials = MAX_EPISODES + 1;
        refused(o, "--trials 100001: at most 100000");
        let mut o = ok.clone();
        o.model.width = 100_000;
        refused(o, "--width 100000: at most 4096 pixels");
        let mut o = ok.clone();
        o.model.clip_frames = Some(1 << 40);
        refused(o, "--clip-frames 1099511627776: at most 1024");
        let mut o = ok.clone();
        o.model.max_batch = Some(0);
        refused(o, "--max-batch");
        let mut o = ok.clone();
        o.episode_frames = MAX_FRAMES + 1;
        refused(o, "--episode-frames 10001");
        let mut o = ok.clone();
        o.cem.horizon = usize::MAX;
        refused(o, "--horizon");
    }

    #[test]
    fn candidates_beyond_the_machine_are_refused_with_the_estimate() {
        let small = LoadedModel::Perfect {
            width: 96,
            height: 64,
            clip_frames: 9,
            robot: "franka".into(),
        };
        assert_eq!(candidates_bytes(&small, 64), 64 * 96 * 64 * 12);
        assert!(check_candidates_memory(&small, "--samples", 64).is_ok());
        let huge = LoadedModel::Perfect {
            width: MAX_SIDE,
            height: MAX_SIDE,
            clip_frames: 9,
            robot: "franka".into(),
        };
        let r = check_candidates_memory(&huge, "--samples", MAX_CEM_SAMPLES);
        if bridgev2w_io::memory::available_bytes().is_some() {
            let e = r.unwrap_err().to_string();
            assert!(
                e.starts_with("evaluating 65536 candidates (--samples) of 4096x4096 pixels at once needs at least 12288.0 GiB"),
                "{e}"
            );
        }
    }
}
