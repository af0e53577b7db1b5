//! Checkpoint I/O: atomic, exactly resumable checkpoints (weights, trainable state,
//! optimizer, moving averages, `state.json`), resuming from them, and the trained
//! backbone of the `vae` and `prior` stages.

use super::{io_err, Trainer};
use crate::config::{Stage, TrainConfig, VaeParts};
use crate::ema::RunWeights;
use crate::run_dir::ExistingRun;
use crate::{Result, TrainError};
use bridgev2w_io::output::{OutputDir, OutputError};
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
        replace_folder(dir, &|tmp| self.write_backbone(tmp))
    }

    /// [`Self::save_trained_backbone`]'s files, into `tmp`.
    fn write_backbone(&self, tmp: &Path) -> Result<()> {
        self.model.save_backbone(tmp)?;
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
        Ok(())
    }

    /// The checkpoint folder of `step` under the run's output.
    pub fn checkpoint_dir(&self, step: usize) -> PathBuf {
        self.cfg
            .train
            .out
            .join("checkpoints")
            .join(checkpoint_name(step))
    }

    /// Writes `checkpoints/step-NNNNNNNN/` (weights, trainable state, optimizer,
    /// `state.json`) into a temporary folder, renames it into place, then
    /// updates `checkpoints/latest`; prunes old checkpoints.
    pub fn save_checkpoint(&self) -> Result<PathBuf> {
        let root = self.cfg.train.out.join("checkpoints");
        let dir = write_checkpoint(&root, self.step, &|tmp| {
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
            write_atomic(&tmp.join("state.json"), state.to_string().as_bytes())
        })?;
        prune_checkpoints(&root, self.step, self.cfg.train.keep_checkpoints)?;
        Ok(dir)
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
        check_name_matches_step(&dir, step)?;
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
/// `checkpoints/latest` names one (a checkpoint name, `step-NNNNNNNN`: never
/// a path out of `checkpoints/`).
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
    let name = name.trim();
    if step_of_name(name).is_none() {
        return Err(TrainError::input(
            latest.display().to_string(),
            format!(
                "names {:?}: expected a checkpoint folder name step-NNNNNNNN (as the trainer writes it)",
                name.chars().take(64).collect::<String>()
            ),
        ));
    }
    Ok(dir.join("checkpoints").join(name))
}

/// The folder name of step `step`'s checkpoint under `checkpoints/`.
fn checkpoint_name(step: usize) -> String {
    format!("step-{step:08}")
}

/// The step of a checkpoint folder's name as [`checkpoint_name`] writes it;
/// `None` for any other name.
fn step_of_name(name: &str) -> Option<usize> {
    let step: usize = name.strip_prefix("step-")?.parse().ok()?;
    (checkpoint_name(step) == name).then_some(step)
}

/// Whether `dir` is a checkpoint folder (a folder holding `state.json`).
fn is_checkpoint(dir: &Path) -> bool {
    dir.symlink_metadata().is_ok_and(|m| m.is_dir())
        && dir
            .join("state.json")
            .symlink_metadata()
            .is_ok_and(|m| m.is_file())
}

/// Refuses a checkpoint folder whose name says another step than its
/// `state.json` (a folder renamed or copied by hand: resuming it would
/// continue from another step than the one asked for). A folder not named
/// `step-NNNNNNNN` says no step.
fn check_name_matches_step(dir: &Path, step: u64) -> Result<()> {
    let Some(named) = dir
        .file_name()
        .and_then(|n| n.to_str())
        .and_then(step_of_name)
    else {
        return Ok(());
    };
    if named as u64 == step {
        return Ok(());
    }
    Err(TrainError::input(
        dir.join("state.json").display().to_string(),
        format!(
            "field `step` is {step}, but the checkpoint folder {} is named for step {named}: \
             a checkpoint renamed or copied by hand? Resume from a folder whose name and \
             state.json agree",
            dir.display()
        ),
    ))
}

/// Writes step `step`'s checkpoint `root/step-NNNNNNNN` with `write` (given
/// the folder to write into), then points `root/latest` at it. The folder is
/// written in a temporary folder of this run's own
/// (`.step-NNNNNNNN.bridgev2w-tmp-<pid>-<random>`, [`replace_folder`])
/// and renamed into place; an earlier checkpoint of that step
/// (a run resumed from an earlier one writes it again) is replaced, but a
/// folder of that name that is not a checkpoint is refused, not removed.
fn write_checkpoint(
    root: &Path,
    step: usize,
    write: &dyn Fn(&Path) -> Result<()>,
) -> Result<PathBuf> {
    std::fs::create_dir_all(root).map_err(|e| io_err(root, e))?;
    let name = checkpoint_name(step);
    let dir = root.join(&name);
    if dir.symlink_metadata().is_ok() && !is_checkpoint(&dir) {
        return Err(TrainError::input(
            dir.display().to_string(),
            "exists and is not a checkpoint (no state.json): it is left alone; move it away to \
             checkpoint this step",
        ));
    }
    replace_folder(&dir, write)?;
    write_atomic(&root.join("latest"), name.as_bytes())?;
    Ok(dir)
}

/// Writes the folder `dir` with `write` (given the folder to write into):
/// into a temporary folder of this run's own
/// (`.NAME.bridgev2w-tmp-<pid>-<random>`, marked; removed if `write`
/// fails), renamed over `dir` at the end ([`OutputDir`]). A folder of anyone
/// else's beside `dir` is never written into or removed, whatever its name.
fn replace_folder(dir: &Path, write: &dyn Fn(&Path) -> Result<()>) -> Result<()> {
    let output = OutputDir::create(dir, true).map_err(output_err)?;
    write(output.path())?;
    output.commit().map_err(output_err)?;
    Ok(())
}

/// Keeps the newest `keep` checkpoints up to step `current` (the one just
/// written among them, never removed); checkpoints of later steps (a run
/// resumed from an earlier one) are left for the run to replace. Only
/// checkpoint folders the trainer names (`step-NNNNNNNN` holding
/// `state.json`) are counted or removed; anything else in `root` stays.
/// `keep = 0` keeps all.
fn prune_checkpoints(root: &Path, current: usize, keep: usize) -> Result<()> {
    if keep == 0 {
        return Ok(());
    }
    let mut steps: Vec<(usize, PathBuf)> = std::fs::read_dir(root)
        .map_err(|e| io_err(root, e))?
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let step = e.file_name().to_str().and_then(step_of_name)?;
            let path = e.path();
            (step <= current && is_checkpoint(&path)).then_some((step, path))
        })
        .collect();
    steps.sort();
    let excess = steps.len().saturating_sub(keep);
    for (step, d) in steps.into_iter().take(excess) {
        if step == current {
            continue;
        }
        std::fs::remove_dir_all(&d).map_err(|e| io_err(&d, e))?;
    }
    Ok(())
}

/// An error of the run's own output folders (a checkpoint, the backbone).
fn output_err(e: OutputError) -> TrainError {
    TrainError::input("train.out", e.to_string())
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

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn names(dir: &Path) -> Vec<String> {
        let mut n: Vec<_> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        n.sort();
        n
    }

    /// Writes a checkpoint of `step` whose state.json says `step`.
    fn checkpoint(root: &Path, step: usize) -> PathBuf {
        write_checkpoint(root, step, &|tmp| {
            write_atomic(
                &tmp.join("state.json"),
                format!("{{\"step\":{step}}}").as_bytes(),
            )
        })
        .unwrap()
    }

    /// The checkpoint's and the backbone's temporary folders were
    /// `.step-NNNNNNNN.tmp` and `<dir>.tmp`, removed first if they existed
    /// (issue 69): a user's folders of those names now survive.
    #[test]
    fn user_folders_named_like_the_old_temporary_names_survive() {
        let tmp = tempfile::tempdir().unwrap();
        let root = tmp.path().join("checkpoints");
        let users = [".step-00000100.tmp", "backbone.tmp"];
        for n in users {
            std::fs::create_dir_all(root.join(n)).unwrap();
            std::fs::write(root.join(n).join("mine.txt"), n).unwrap();
        }
        let dir = checkpoint(&root, 100);
        assert_eq!(dir, root.join("step-00000100"));
        // Written again (a resumed run): the checkpoint is replaced.
        write_checkpoint(&root, 100, &|tmp| {
            write_atomic(&tmp.join("state.json"), b"{\"step\":100,\"again\":1}")
        })
        .unwrap();
        assert!(std::fs::read_to_string(dir.join("state.json"))
            .unwrap()
            .contains("again"));
        assert_eq!(names(&dir), ["state.json"], "no marker left");
        replace_folder(&root.join("backbone"), &|tmp| {
            write_atomic(&tmp.join("model_index.json"), b"{}")
        })
        .unwrap();
        // A write that fails leaves nothing of its own behind.
        let e = replace_folder(&root.join("backbone"), &|tmp| {
            write_atomic(&tmp.join("half.json"), b"{")?;
            Err(TrainError::input("test", "failed midway"))
        })
        .unwrap_err();
        assert!(e.to_string().contains("failed midway"), "{e}");
        assert_eq!(names(&root.join("backbone")), ["model_index.json"]);
        for n in users {
            assert_eq!(
                std::fs::read_to_string(root.join(n).join("mine.txt")).unwrap(),
                n
            );
        }
        assert_eq!(
            names(&root),
            [users[0], "backbone", users[1], "latest", "step-00000100"]
        );
        assert_eq!(
            std::fs::read_to_string(root.join("latest")).unwrap(),
            "step-00000100"
        );
    }

    #[test]
    fn a_folder_of_a_checkpoint_name_that_is_no_checkpoint_is_refused_not_removed() {
        let tmp = tempfile::tempdir().unwrap();
        let root = tmp.path().join("checkpoints");
        std::fs::create_dir_all(root.join("step-00000200")).unwrap();
        std::fs::write(root.join("step-00000200/notes.txt"), "mine").unwrap();
        let e = write_checkpoint(&root, 200, &|_| Ok(()))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("step-00000200") && e.contains("not a checkpoint"),
            "{e}"
        );
        assert_eq!(names(&root.join("step-00000200")), ["notes.txt"]);
        assert_eq!(names(&root), ["step-00000200"]);
    }

    #[test]
    fn pruning_removes_only_older_checkpoints_of_the_trainer_s_naming() {
        let tmp = tempfile::tempdir().unwrap();
        let root = tmp.path().join("checkpoints");
        for step in 1..=6 {
            checkpoint(&root, step);
        }
        // Not the trainer's: another name, or no state.json.
        for n in ["step-3", "step-00000002-best", "step-00000000", "+step"] {
            std::fs::create_dir_all(root.join(n)).unwrap();
        }
        std::fs::write(root.join("step-3/state.json"), "{}").unwrap();
        std::fs::write(root.join("step-00000002-best/state.json"), "{}").unwrap();
        prune_checkpoints(&root, 5, 2).unwrap();
        assert_eq!(
            names(&root),
            [
                "+step",
                "latest",
                "step-00000000",
                "step-00000002-best",
                "step-00000004",
                "step-00000005",
                "step-00000006",
                "step-3"
            ]
        );
        // The one just written is kept whatever `keep` says; 0 keeps all.
        prune_checkpoints(&root, 5, 1).unwrap();
        assert!(root.join("step-00000005/state.json").is_file());
        assert!(!root.join("step-00000004").exists());
        prune_checkpoints(&root, 6, 0).unwrap();
        assert!(root.join("step-00000005").exists());
        // Steps past 8 digits sort by number, not by name.
        checkpoint(&root, 100_000_000);
        prune_checkpoints(&root, 100_000_000, 1).unwrap();
        assert!(root.join("step-100000000").exists());
        assert!(!root.join("step-00000006").exists());
    }

    /// `checkpoint-200` whose state.json says step 100 (issue 69): refused on
    /// resume, naming the folder, the field and both values.
    #[test]
    fn a_checkpoint_whose_state_disagrees_with_its_name_is_refused() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("step-00000200");
        let e = check_name_matches_step(&dir, 100).unwrap_err().to_string();
        assert!(
            e.contains(&*dir.to_string_lossy())
                && e.contains("state.json")
                && e.contains("`step` is 100")
                && e.contains("named for step 200"),
            "{e}"
        );
        check_name_matches_step(&dir, 200).unwrap();
        // A folder named otherwise says no step.
        check_name_matches_step(&tmp.path().join("my-checkpoint"), 100).unwrap();
        check_name_matches_step(&tmp.path().join("step-200"), 100).unwrap();
    }

    #[test]
    fn latest_must_name_a_checkpoint_not_a_path() {
        let tmp = tempfile::tempdir().unwrap();
        let root = tmp.path().join("checkpoints");
        checkpoint(&root, 3);
        assert_eq!(
            resolve_checkpoint(tmp.path()).unwrap(),
            root.join("step-00000003")
        );
        for bad in ["../../elsewhere", "/etc", "step-00000003/.."] {
            std::fs::write(root.join("latest"), bad).unwrap();
            let e = resolve_checkpoint(tmp.path()).unwrap_err().to_string();
            assert!(e.contains("latest") && e.contains(bad), "{e}");
        }
    }
}
