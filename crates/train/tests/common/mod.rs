//! Helpers shared by the trainer tests: the tiny synthetic dataset, the
//! tiny training config, the lock that runs training tests one at a time
//! (libtorch's generator is process-global), and tensor readers.

#![allow(dead_code, clippy::unwrap_used)]

use bridgev2w_data::synth::{write_dataset, SynthConfig};
use bridgev2w_train::config::TrainConfig;
use bridgev2w_train::trainer::Trainer;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, MutexGuard, OnceLock};
use tch::Kind;

static LOCK: Mutex<()> = Mutex::new(());

/// Held by every test that trains (one at a time in a test binary).
pub fn lock() -> MutexGuard<'static, ()> {
    LOCK.lock().unwrap_or_else(|e| e.into_inner())
}

/// A 2-episode train split (plus one per held-out split), written once.
pub fn dataset() -> &'static Path {
    static DIR: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    &DIR.get_or_init(|| {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("synth");
        let cfg = SynthConfig {
            frames: 12,
            width: 96,
            height: 64,
            episodes_per_split: [2, 1, 1, 1],
            ..SynthConfig::default()
        };
        write_dataset(&cfg, &out, &|| {}).unwrap();
        (tmp, out)
    })
    .1
}

/// The tiny training config over `dataset()`, writing to `out`.
pub fn config(out: &Path) -> TrainConfig {
    let mut c = TrainConfig::default();
    c.model.backbone = "random:tiny".into();
    c.model.lora_rank = 4;
    c.model.lora_alpha = 4.0;
    c.model.controlnet_layers = Some(1);
    c.model.action_hidden = 32;
    c.data.dataset = dataset().to_path_buf();
    c.data.clips_per_video = 1;
    c.train.out = out.to_path_buf();
    c.train.max_steps = 6;
    c.train.warmup_steps = 2;
    c.train.lr = 1e-3;
    c.train.condition_dropout = 0.2;
    c.train.checkpoint_every = 3;
    c.train.e_switch = 100;
    c
}

/// The named tensors of a safetensors file, as f64 values.
pub fn tensors(path: &Path) -> Vec<(String, Vec<f64>)> {
    let mut t: Vec<(String, Vec<f64>)> = tch::Tensor::read_safetensors(path)
        .unwrap()
        .into_iter()
        .map(|(n, t)| {
            let v = Vec::<f64>::try_from(t.to_kind(Kind::Double).reshape(-1)).unwrap();
            (n, v)
        })
        .collect();
    t.sort_by(|a, b| a.0.cmp(&b.0));
    t
}

/// Asserts that every parameter the optimiser updates has a name starting
/// with `prefix`.
pub fn assert_trains_only(t: &Trainer, prefix: &str) {
    let others: Vec<&str> = t
        .opt
        .params()
        .iter()
        .map(|(n, _)| n.as_str())
        .filter(|n| !n.starts_with(prefix))
        .collect();
    assert!(others.is_empty(), "trained outside {prefix:?}: {others:?}");
}

/// The summed absolute gradient of the parameters whose names start with
/// `prefix` (0 for those without a gradient).
pub fn grad_abs_sum(t: &Trainer, prefix: &str) -> f64 {
    t.opt
        .params()
        .iter()
        .filter(|(n, _)| n.starts_with(prefix))
        .map(|(_, p)| {
            let g = p.grad();
            if g.defined() {
                g.abs().sum(Kind::Double).double_value(&[])
            } else {
                0.0
            }
        })
        .sum()
}

/// The summed absolute gradient of the ControlNet branch's parameters.
pub fn controlnet_grad_sum(t: &Trainer) -> f64 {
    grad_abs_sum(t, "adapters.controlnet.")
}
