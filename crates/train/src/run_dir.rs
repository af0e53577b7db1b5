//! The run folder (`train.out`) as one run's property: a new run refuses a
//! folder that already holds one (unless told to start over), a resumed run
//! refuses a folder that holds a run of another configuration.
//!
//! A folder "holds a run" when it has any of the files a run writes
//! ([`RUN_FILES`]); other files in it are the user's and are never touched.
//!
//! A run holds the folder's lock (`.OUT.bridgev2w-lock` beside it,
//! [`OutputLock`]) from its claim to its end: a second trainer into the same
//! folder (a new run, `--resume` or `--overwrite`) stops, naming the first's
//! process, before it reads or changes anything there.

use crate::config::TrainConfig;
use crate::{Result, TrainError};
use bridgev2w_io::output::{check_no_overlap, OutputLock};
use std::path::Path;

/// The files and folders a run writes into `train.out`.
pub const RUN_FILES: [&str; 5] = [
    "config.toml",
    "metrics.jsonl",
    "tensorboard",
    "checkpoints",
    "final",
];

/// The `[train]` fields a resumed run may change: where it writes, how far it
/// goes, how often it checkpoints, the device it runs on and the VAE's tiles
/// (both for memory: a run that runs out of memory at the flow loss's switch
/// continues with smaller tiles), and the test hook.
const RESUMABLE_CHANGES: [&str; 9] = [
    "train.out",
    "train.max_steps",
    "train.epochs",
    "train.checkpoint_every",
    "train.preview_steps",
    "train.keep_checkpoints",
    "train.inject_nan_at_step",
    "model.device",
    "model.vae_tile",
];

/// What to do with a run folder that already holds a run.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ExistingRun {
    /// Refuse it (the default of a new run).
    #[default]
    Refuse,
    /// Continue it: the trainer resumed from a checkpoint; the folder's run
    /// must have the same configuration (but for [`RESUMABLE_CHANGES`]).
    Continue,
    /// Start over: remove the run's files ([`RUN_FILES`]) first.
    Overwrite,
}

/// The run files `out` holds.
pub fn held_run_files(out: &Path) -> Vec<&'static str> {
    RUN_FILES
        .iter()
        .copied()
        .filter(|f| out.join(f).symlink_metadata().is_ok())
        .collect()
}

/// Claims `out` for a run of `cfg`, as `existing` says: takes its lock
/// (refused, naming the process, while another run holds it), then checks
/// (or, to start over, removes) the run it holds. The run keeps the
/// returned lock to its end.
pub fn claim(out: &Path, cfg: &TrainConfig, existing: ExistingRun) -> Result<OutputLock> {
    check_outside_datasets(out, cfg)?;
    let lock = OutputLock::take(out).map_err(|e| TrainError::input("train.out", e.to_string()))?;
    check_claim(out, cfg, existing)?;
    Ok(lock)
}

/// Refuses an `out` that is, is inside or contains one of the run's
/// datasets (`data.dataset`, `data.mix[].dataset`): the run's files (and
/// `--overwrite`'s removal of them) would land among the dataset's.
pub fn check_outside_datasets(out: &Path, cfg: &TrainConfig) -> Result<()> {
    let datasets: Vec<&Path> = std::iter::once(cfg.data.dataset.as_path())
        .chain(cfg.data.mix.iter().map(|m| m.dataset.as_path()))
        .collect();
    check_no_overlap(out, &datasets).map_err(|e| TrainError::input("train.out", e.to_string()))
}

/// [`claim`]'s checks, under the lock.
fn check_claim(out: &Path, cfg: &TrainConfig, existing: ExistingRun) -> Result<()> {
    let held = held_run_files(out);
    if held.is_empty() {
        return Ok(());
    }
    match existing {
        ExistingRun::Refuse => Err(TrainError::input(
            format!("train.out {}", out.display()),
            format!(
                "already holds a run ({}): pass --resume {} to continue it, or --overwrite to replace it",
                held.join(", "),
                out.display()
            ),
        )),
        ExistingRun::Continue => check_same_run(out, cfg),
        ExistingRun::Overwrite => {
            for f in held {
                let p = out.join(f);
                let removed = if p.is_dir() {
                    std::fs::remove_dir_all(&p)
                } else {
                    std::fs::remove_file(&p)
                };
                removed.map_err(|error| TrainError::Io { path: p, error })?;
            }
            Ok(())
        }
    }
}

/// Errs when `out/config.toml` (if present) differs from `cfg` in a field
/// other than [`RESUMABLE_CHANGES`], naming the fields and both values.
fn check_same_run(out: &Path, cfg: &TrainConfig) -> Result<()> {
    let path = out.join("config.toml");
    let Ok(text) = std::fs::read_to_string(&path) else {
        return Ok(());
    };
    // Read through this version's configuration first, so that a setting
    // added since the run was made (absent there) takes its default, which
    // is the earlier behaviour; a file this version cannot read is compared
    // as written.
    let text = TrainConfig::from_toml(&text)
        .and_then(|c| c.to_toml())
        .unwrap_or(text);
    let old: toml::Table = toml::from_str(&text)
        .map_err(|e| TrainError::input(path.display().to_string(), e.to_string()))?;
    let new: toml::Table =
        toml::from_str(&cfg.to_toml()?).map_err(|e| TrainError::input("config", e.to_string()))?;
    let mut diffs = Vec::new();
    diff_tables("", &old, &new, &mut diffs);
    diffs.retain(|(key, _, _)| !RESUMABLE_CHANGES.contains(&key.as_str()));
    if diffs.is_empty() {
        return Ok(());
    }
    let list: Vec<String> = diffs
        .iter()
        .map(|(k, a, b)| format!("{k}: {a} there, {b} now"))
        .collect();
    Err(TrainError::input(
        format!("train.out {}", out.display()),
        format!(
            "holds a run of another configuration ({}): resuming would mix two runs; use another `out`, or --overwrite to replace it",
            list.join("; ")
        ),
    ))
}

/// The dotted keys whose values differ between `a` and `b` (a missing key
/// shows as `(none)`).
fn diff_tables(
    prefix: &str,
    a: &toml::Table,
    b: &toml::Table,
    out: &mut Vec<(String, String, String)>,
) {
    let mut keys: Vec<&String> = a.keys().chain(b.keys()).collect();
    keys.sort();
    keys.dedup();
    for k in keys {
        let key = if prefix.is_empty() {
            k.clone()
        } else {
            format!("{prefix}.{k}")
        };
        match (a.get(k), b.get(k)) {
            (Some(toml::Value::Table(ta)), Some(toml::Value::Table(tb))) => {
                diff_tables(&key, ta, tb, out)
            }
            (va, vb) if va != vb => {
                let show = |v: Option<&toml::Value>| v.map_or("(none)".into(), |v| v.to_string());
                out.push((key, show(va), show(vb)));
            }
            _ => {}
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn cfg(out: &Path) -> TrainConfig {
        let mut c = TrainConfig::from_toml(
            "[model]\nbackbone = \"random:tiny\"\nlora_rank = 0\n[data]\ndataset = \"d\"\n",
        )
        .unwrap();
        c.train.out = out.to_path_buf();
        c
    }

    #[test]
    fn a_new_run_refuses_a_folder_with_a_run_and_names_its_files() {
        let dir = tempfile::tempdir().unwrap();
        claim(dir.path(), &cfg(dir.path()), ExistingRun::Refuse).unwrap();
        std::fs::write(dir.path().join("notes.txt"), "mine").unwrap();
        claim(dir.path(), &cfg(dir.path()), ExistingRun::Refuse).unwrap();
        std::fs::write(dir.path().join("metrics.jsonl"), "{}\n").unwrap();
        std::fs::create_dir(dir.path().join("final")).unwrap();
        let e = claim(dir.path(), &cfg(dir.path()), ExistingRun::Refuse)
            .unwrap_err()
            .to_string();
        assert!(e.contains("metrics.jsonl, final"), "{e}");
        assert!(e.contains("--overwrite") && e.contains("--resume"), "{e}");
        assert!(dir.path().join("metrics.jsonl").exists());
    }

    /// `train` or `train --resume` into a run folder that another trainer
    /// still writes (issue 69): refused naming that trainer's pid, before
    /// anything there is changed; once it is gone, its lock is taken over.
    #[test]
    #[cfg(target_os = "linux")]
    fn a_run_folder_locked_by_a_live_trainer_is_refused_naming_its_pid() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("run");
        std::fs::create_dir(&out).unwrap();
        std::fs::write(out.join("metrics.jsonl"), "{}\n").unwrap();
        let lock = dir.path().join(".run.bridgev2w-lock");
        let mut trainer = std::process::Command::new("sleep")
            .arg("30")
            .spawn()
            .unwrap();
        let pid = trainer.id();
        std::fs::write(&lock, format!("bridgev2w output lock\npid {pid}\n")).unwrap();
        let refused: Vec<String> = [
            ExistingRun::Refuse,
            ExistingRun::Continue,
            ExistingRun::Overwrite,
        ]
        .into_iter()
        .map(|existing| match claim(&out, &cfg(&out), existing) {
            Ok(_) => "claimed".to_owned(),
            Err(e) => e.to_string(),
        })
        .collect();
        trainer.kill().unwrap();
        trainer.wait().unwrap();
        for e in &refused {
            assert!(
                e.contains("train.out") && e.contains(&format!("pid {pid}")),
                "{e}"
            );
        }
        assert!(out.join("metrics.jsonl").exists(), "nothing removed");
        // That trainer is gone: its lock is taken over, held to the end.
        let held = claim(&out, &cfg(&out), ExistingRun::Overwrite).unwrap();
        assert!(held.held() && held.path() == lock);
        assert!(held_run_files(&out).is_empty());
        // A second trainer of this process is refused while it is held.
        let e = claim(&out, &cfg(&out), ExistingRun::Continue)
            .unwrap_err()
            .to_string();
        assert!(e.contains(&format!("pid {}", std::process::id())), "{e}");
        drop(held);
        assert!(!lock.exists());
    }

    #[test]
    fn an_out_overlapping_a_dataset_is_refused_naming_both() {
        let dir = tempfile::tempdir().unwrap();
        let data = dir.path().join("data");
        let mixed = dir.path().join("human");
        std::fs::create_dir_all(data.join("meta")).unwrap();
        std::fs::write(data.join("config.toml"), "the dataset's").unwrap();
        let mut c = cfg(&data);
        c.data.dataset = data.clone();
        c.data.mix = vec![crate::config::MixSource {
            dataset: mixed.clone(),
            ..Default::default()
        }];
        for (out, input, how) in [
            (data.clone(), &data, "is the input"),
            (data.join("runs/a"), &data, "is inside the input"),
            (mixed.join("run"), &mixed, "is inside the input"),
            (dir.path().to_path_buf(), &data, "contains the input"),
        ] {
            let e = claim(&out, &c, ExistingRun::Overwrite)
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("train.out") && e.contains(how) && e.contains(&*input.to_string_lossy()),
                "{e}"
            );
        }
        let kept = std::fs::read_to_string(data.join("config.toml")).unwrap();
        assert_eq!(kept, "the dataset's");
        claim(&dir.path().join("runs/a"), &c, ExistingRun::Refuse).unwrap();
    }

    #[test]
    fn overwrite_removes_only_the_run_files() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("notes.txt"), "mine").unwrap();
        std::fs::write(dir.path().join("metrics.jsonl"), "{}\n").unwrap();
        std::fs::create_dir_all(dir.path().join("checkpoints/step-00000005")).unwrap();
        claim(dir.path(), &cfg(dir.path()), ExistingRun::Overwrite).unwrap();
        assert!(held_run_files(dir.path()).is_empty());
        assert!(dir.path().join("notes.txt").exists());
    }

    /// A run written before a setting existed (its `config.toml` without
    /// it) continues under the setting's default, and not under another
    /// value.
    #[test]
    fn a_setting_added_since_the_run_takes_its_default() {
        let dir = tempfile::tempdir().unwrap();
        let c = cfg(dir.path());
        let text = c.to_toml().unwrap();
        let older: String = text
            .lines()
            .filter(|l| !l.starts_with("vae_parts ="))
            .map(|l| format!("{l}\n"))
            .collect();
        assert_ne!(older, text, "the test needs a defaulted setting to drop");
        std::fs::write(dir.path().join("config.toml"), older).unwrap();
        let mut longer = c.clone();
        longer.train.max_steps += 100;
        claim(dir.path(), &longer, ExistingRun::Continue).unwrap();
        let mut other = c.clone();
        other.train.lr *= 2.0;
        let e = claim(dir.path(), &other, ExistingRun::Continue)
            .unwrap_err()
            .to_string();
        assert!(e.contains("train.lr"), "{e}");
    }

    #[test]
    fn continuing_checks_the_configuration_but_allows_more_steps() {
        let dir = tempfile::tempdir().unwrap();
        let c = cfg(dir.path());
        std::fs::write(dir.path().join("config.toml"), c.to_toml().unwrap()).unwrap();
        let mut longer = c.clone();
        longer.train.max_steps += 100;
        longer.train.checkpoint_every = 7;
        longer.model.vae_tile = Some("144x200".parse().unwrap());
        claim(dir.path(), &longer, ExistingRun::Continue).unwrap();
        let mut other = c.clone();
        other.train.lr *= 2.0;
        other.model.lora_rank = 4;
        let e = claim(dir.path(), &other, ExistingRun::Continue)
            .unwrap_err()
            .to_string();
        assert!(e.contains("model.lora_rank: 0 there, 4 now"), "{e}");
        assert!(e.contains("train.lr"), "{e}");
        assert!(!e.contains("max_steps"), "{e}");
    }
}
