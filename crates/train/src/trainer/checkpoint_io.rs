//! Checkpoint I/O: atomic, exactly resumable checkpoints (weights, trainable state,
//! optimizer, moving averages, `state.json`), resuming from them, and the trained
//! backbone of the `vae` and `prior` stages.

use super::{io_err, Trainer};
use crate::config::{Stage, TrainConfig, VaeParts};
use crate::ema::RunWeights;
use crate::run_dir::ExistingRun;
use crate::{Result, TrainError};
use std::path::{Path, PathBuf};
use tch::{Kind, Tensor};

impl Trainer {
    /// Loads a run's model: its configuration, the run folder's latest
    /// checkpoint (or a checkpoint folder), and `weights`. Also says whether
    /// the moving averages are in use.
    pub fn load_run(config: &Path, run: &Path, weights: RunWeights) -> Result<(Trainer, bool)> {
        let cfg = TrainConfig::from_file(config)?;
        let mut trainer = Trainer::new(cfg).map_err(TrainError::context(format!(
            "setting up the model of {}",
            config.display()
        )))?;
        trainer.resume(run).map_err(TrainError::context(format!(
            "loading the run {}",
            run.display()
        )))?;
        let averaged = weights == RunWeights::Averaged && trainer.use_averaged_weights();
        Ok((trainer, averaged))
    }

    /// Writes the backbone (diffusers folder) after a `vae` or `prior` stage.
    /// After `vae`, the latent `scaling_factor` is re-estimated as
    /// `1 / std` of posterior means over up to 8 training batches, so the
    /// diffusion stages see latents of unit scale (as Stable Diffusion and
    /// CogVideoX set it); a decoder-only stage (`vae_parts = "decoder"`)
    /// keeps the loaded scale with the encoder. Written to a temporary
    /// folder, then renamed.
    pub fn save_trained_backbone(&self, dir: &Path) -> Result<()> {
        let tmp = PathBuf::from(format!("{}.tmp", dir.display()));
        if tmp.exists() {
            std::fs::remove_dir_all(&tmp).map_err(|e| io_err(&tmp, e))?;
        }
        self.model.save_backbone(&tmp)?;
        if self.cfg.train.stage == Stage::Vae && self.cfg.train.vae_parts == VaeParts::All {
            let mut sum = 0f64;
            let mut sq = 0f64;
            let mut n = 0f64;
            for step in 0..self.steps_per_epoch().min(8) {
                let b = self.global_batch(step)?;
                let z = tch::no_grad(|| self.model.vae.encode(&b.video))?
                    .mode()
                    .to_kind(Kind::Double);
                sum += z.sum(Kind::Double).double_value(&[]);
                sq += (&z * &z).sum(Kind::Double).double_value(&[]);
                n += z.numel() as f64;
            }
            let std = (sq / n - (sum / n).powi(2)).max(1e-12).sqrt();
            let path = tmp.join("vae/config.json");
            let text = std::fs::read_to_string(&path).map_err(|e| io_err(&path, e))?;
            let mut v: serde_json::Value = serde_json::from_str(&text)
                .map_err(|e| TrainError::input(path.display().to_string(), e.to_string()))?;
            v["scaling_factor"] = serde_json::json!(1.0 / std);
            write_atomic(&path, v.to_string().as_bytes())?;
        }
        if dir.exists() {
            std::fs::remove_dir_all(dir).map_err(|e| io_err(dir, e))?;
        }
        std::fs::rename(&tmp, dir).map_err(|e| io_err(dir, e))
    }

    /// The checkpoint folder of `step` under the run's output.
    pub fn checkpoint_dir(&self, step: usize) -> PathBuf {
        self.cfg
            .train
            .out
            .join("checkpoints")
            .join(format!("step-{step:08}"))
    }

    /// Writes `checkpoints/step-NNNNNNNN/` (weights, trainable state, optimizer,
    /// `state.json`) into a temporary folder, renames it into place, then
    /// updates `checkpoints/latest`; prunes old checkpoints.
    pub fn save_checkpoint(&self) -> Result<PathBuf> {
        let root = self.cfg.train.out.join("checkpoints");
        std::fs::create_dir_all(&root).map_err(|e| io_err(&root, e))?;
        let name = format!("step-{:08}", self.step);
        let final_dir = root.join(&name);
        let tmp = root.join(format!(".{name}.tmp"));
        if tmp.exists() {
            std::fs::remove_dir_all(&tmp).map_err(|e| io_err(&tmp, e))?;
        }
        std::fs::create_dir_all(&tmp).map_err(|e| io_err(&tmp, e))?;
        self.model.save_weights(&tmp.join("weights.safetensors"))?;
        save_named(self.trainable_state(), &tmp.join("trainable.safetensors"))?;
        save_named(self.opt.state(), &tmp.join("optimizer.safetensors"))?;
        if let Some(ema) = &self.ema {
            save_named(ema.state(), &tmp.join("ema.safetensors"))?;
        }
        let state = serde_json::json!({
            "step": self.step,
            "seed": self.cfg.train.seed,
            "epoch": self.step / self.steps_per_epoch(),
            "rng": "derived from (seed, step): no generator state to store",
            "flow_estimator": self.estimator.name(),
        });
        write_atomic(&tmp.join("state.json"), state.to_string().as_bytes())?;
        if final_dir.exists() {
            std::fs::remove_dir_all(&final_dir).map_err(|e| io_err(&final_dir, e))?;
        }
        std::fs::rename(&tmp, &final_dir).map_err(|e| io_err(&final_dir, e))?;
        write_atomic(&root.join("latest"), name.as_bytes())?;
        self.prune_checkpoints(&root)?;
        Ok(final_dir)
    }

    /// Keeps the newest `keep_checkpoints` checkpoints up to the current step
    /// (the one just written among them); checkpoints of later steps (a run
    /// resumed from an earlier one) are left for the run to replace.
    fn prune_checkpoints(&self, root: &Path) -> Result<()> {
        let keep = self.cfg.train.keep_checkpoints;
        if keep == 0 {
            return Ok(());
        }
        let current = format!("step-{:08}", self.step);
        let mut dirs: Vec<PathBuf> = std::fs::read_dir(root)
            .map_err(|e| io_err(root, e))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.is_dir()
                    && p.file_name()
                        .and_then(|n| n.to_str())
                        .is_some_and(|n| n.starts_with("step-") && *n <= *current)
            })
            .collect();
        dirs.sort();
        while dirs.len() > keep {
            let d = dirs.remove(0);
            std::fs::remove_dir_all(&d).map_err(|e| io_err(&d, e))?;
        }
        Ok(())
    }

    /// Everything the run changes: trainable parameters and the action
    /// MLP's normalisation, by prefixed name.
    fn trainable_state(&self) -> Vec<(String, Tensor)> {
        let mut named: Vec<(String, Tensor)> = self
            .opt
            .params()
            .iter()
            .map(|(n, t)| (n.clone(), t.shallow_clone()))
            .collect();
        if let Some(vs) = &self.action_vs {
            for (name, t) in vs.variables() {
                if !t.requires_grad() {
                    named.push((format!("action.{name}"), t));
                }
            }
        }
        named
    }

    /// Puts the moving averages (`train.ema_decay > 0`) into the trainable
    /// variables, for evaluating or exporting them; `false` (nothing done)
    /// for a run without averages. Training on afterwards would continue
    /// from the averages, not from the raw parameters.
    pub fn use_averaged_weights(&mut self) -> bool {
        match &self.ema {
            Some(ema) => {
                ema.copy_into(self.opt.params());
                true
            }
            None => false,
        }
    }

    /// Resumes from a checkpoint folder, or from a run folder's latest checkpoint.
    pub fn resume(&mut self, dir: &Path) -> Result<()> {
        let dir = resolve_checkpoint(dir)?;
        let state_path = dir.join("state.json");
        let text = std::fs::read_to_string(&state_path).map_err(|e| io_err(&state_path, e))?;
        let state: serde_json::Value = serde_json::from_str(&text)
            .map_err(|e| TrainError::input(state_path.display().to_string(), e.to_string()))?;
        let step = state["step"].as_u64().ok_or_else(|| {
            TrainError::input(state_path.display().to_string(), "no integer `step`")
        })?;
        // A checkpoint may lie beyond this config's steps (evaluating a run
        // that was extended with --max-steps), but not beyond any run.
        if step > crate::config::MAX_STEPS as u64 {
            return Err(TrainError::input(
                state_path.display().to_string(),
                format!(
                    "step {step} is beyond any run (at most {} steps): a corrupt state.json?",
                    crate::config::MAX_STEPS
                ),
            ));
        }
        let step = step as usize;
        if state["seed"].as_u64() != Some(self.cfg.train.seed) {
            return Err(TrainError::input(
                state_path.display().to_string(),
                format!(
                    "seed {} but the config says {}: resuming would not repeat the run",
                    state["seed"], self.cfg.train.seed
                ),
            ));
        }
        let path = dir.join("trainable.safetensors");
        let saved = bridgev2w_world_model::weights::read_safetensors(&path)?;
        crate::checkpoint::copy_named_into(&self.trainable_state(), saved, &path)?;
        // The adapters' untrained variables (e.g. the unused branch of the
        // action ablation) come from the weights file.
        self.model.load_weights(&dir.join("weights.safetensors"))?;
        let opt_path = dir.join("optimizer.safetensors");
        self.opt
            .load_state(bridgev2w_world_model::weights::read_safetensors(&opt_path)?)?;
        if let Some(ema) = &mut self.ema {
            let path = dir.join("ema.safetensors");
            if !path.is_file() {
                return Err(TrainError::input(
                    path.display().to_string(),
                    format!(
                        "missing: the config averages the weights (train.ema_decay = {}) but \
                         this checkpoint has no averages",
                        self.cfg.train.ema_decay
                    ),
                ));
            }
            ema.load(
                bridgev2w_world_model::weights::read_safetensors(&path)?,
                &path,
            )?;
        }
        self.step = step;
        self.existing_run = ExistingRun::Continue;
        Ok(())
    }
}

/// A checkpoint folder (holding `state.json`), or a run folder whose
/// `checkpoints/latest` names one.
pub fn resolve_checkpoint(dir: &Path) -> Result<PathBuf> {
    if dir.join("state.json").is_file() {
        return Ok(dir.to_path_buf());
    }
    let latest = dir.join("checkpoints").join("latest");
    let name = std::fs::read_to_string(&latest).map_err(|e| {
        TrainError::input(
            format!("--resume {}", dir.display()),
            format!(
                "neither a checkpoint (state.json) nor a run folder with checkpoints/latest: {e}"
            ),
        )
    })?;
    Ok(dir.join("checkpoints").join(name.trim()))
}

/// Writes `bytes` to `path` through a synced temporary file and a rename.
pub(super) fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    bridgev2w_io::atomic::write_atomic_io(path, bytes).map_err(|e| io_err(path, e))
}

pub(super) fn save_named(mut named: Vec<(String, Tensor)>, path: &Path) -> Result<()> {
    named.sort_by(|a, b| a.0.cmp(&b.0));
    let named: Vec<(String, Tensor)> = named
        .into_iter()
        .map(|(n, t)| (n, t.detach().to_device(tch::Device::Cpu).contiguous()))
        .collect();
    Tensor::write_safetensors(&named, path)?;
    Ok(())
}
