//! Exponential moving average of the trained parameters (`train.ema_decay`).
//!
//! After every optimizer step each average moves toward its parameter:
//! `avg = d * avg + (1 - d) * param`, with the warm-up
//! `d = min(decay, (1 + step) / (10 + step))` (so the first steps, far from
//! the end of training, count little). The averages are written with every
//! checkpoint (`ema.safetensors`, the parameters' names) and restored on
//! resume, so a resumed run keeps the same averages. The run's
//! `final/weights.safetensors` (and a trained backbone) hold the averages;
//! the checkpoints' `weights.safetensors` the raw parameters a resume needs.

use crate::{Result, TrainError};
use std::path::Path;
use tch::Tensor;

/// Which weights of a run to score or export.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RunWeights {
    /// The moving averages when the run keeps them (`train.ema_decay > 0`),
    /// else the parameters.
    #[default]
    Averaged,
    /// The parameters as the optimizer left them.
    Raw,
}

bridgev2w_world_model::named_enum!(RunWeights, TrainError, TrainError::input, "weights", {
    Averaged => "averaged",
    Raw => "raw",
});

/// The averages of a list of named parameters.
#[derive(Debug)]
pub struct Ema {
    decay: f64,
    /// `(name, average)` in the order of the parameters.
    averages: Vec<(String, Tensor)>,
}

impl Ema {
    /// Averages starting at the parameters' current values (detached copies).
    pub fn new(decay: f64, params: &[(String, Tensor)]) -> Self {
        let averages = tch::no_grad(|| {
            params
                .iter()
                .map(|(n, p)| (n.clone(), p.detach().copy()))
                .collect()
        });
        Self { decay, averages }
    }

    /// The decay of the update after optimizer step `step` (0-based).
    pub fn decay_at(&self, step: usize) -> f64 {
        self.decay.min((1.0 + step as f64) / (10.0 + step as f64))
    }

    /// Moves every average toward its parameter after step `step`.
    pub fn update(&mut self, params: &[(String, Tensor)], step: usize) {
        let d = self.decay_at(step);
        tch::no_grad(|| {
            for ((_, avg), (_, p)) in self.averages.iter_mut().zip(params) {
                // avg = d * avg + (1 - d) * p, in place
                let _ = avg.lerp_(&p.to_kind(avg.kind()), 1.0 - d);
            }
        });
    }

    /// The averages by name (what a checkpoint stores).
    pub fn state(&self) -> Vec<(String, Tensor)> {
        self.averages
            .iter()
            .map(|(n, t)| (n.clone(), t.shallow_clone()))
            .collect()
    }

    /// Restores the averages from `saved` (read from `path`): every
    /// parameter's average must be there with its shape, and nothing else.
    pub fn load(&mut self, saved: Vec<(String, Tensor)>, path: &Path) -> Result<()> {
        crate::checkpoint::copy_named_into(&self.averages, saved, path)
    }

    /// Copies the averages into the parameters (for evaluation or export).
    pub fn copy_into(&self, params: &[(String, Tensor)]) {
        tch::no_grad(|| {
            for ((_, avg), (_, p)) in self.averages.iter().zip(params) {
                p.shallow_clone().copy_(avg);
            }
        });
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn param(v: &[f32]) -> Vec<(String, Tensor)> {
        vec![("w".to_string(), Tensor::from_slice(v))]
    }

    #[test]
    fn the_average_follows_the_closed_form() {
        let p = param(&[0.0, 2.0]);
        let mut ema = Ema::new(0.9, &p);
        // Step 0: d = min(0.9, 1/10) = 0.1; the parameter moved to [1, 4].
        let p1 = param(&[1.0, 4.0]);
        ema.update(&p1, 0);
        let got = Vec::<f32>::try_from(&ema.state()[0].1).unwrap();
        let want = [0.1f32 * 0.0 + 0.9 * 1.0, 0.1 * 2.0 + 0.9 * 4.0];
        for (g, w) in got.iter().zip(want) {
            assert!((g - w).abs() < 1e-6, "{got:?} vs {want:?}");
        }
        // Late steps use the configured decay.
        assert_eq!(ema.decay_at(1000), 0.9);
        ema.update(&param(&[1.0, 4.0]), 1000);
        let got = Vec::<f32>::try_from(&ema.state()[0].1).unwrap();
        let want = [0.9f32 * 0.9 + 0.1 * 1.0, 0.9 * 3.8 + 0.1 * 4.0];
        for (g, w) in got.iter().zip(want) {
            assert!((g - w).abs() < 1e-6, "{got:?} vs {want:?}");
        }
    }

    #[test]
    fn loading_names_missing_extra_and_misshapen_averages() {
        let p = param(&[0.0, 2.0]);
        let mut ema = Ema::new(0.9, &p);
        let path = Path::new("run/checkpoints/step-1/ema.safetensors");
        let e = ema.load(vec![], path).unwrap_err().to_string();
        assert!(e.contains("ema.safetensors") && e.contains("`w`"), "{e}");
        let e = ema
            .load(
                vec![("w".into(), Tensor::from_slice(&[1f32, 2.0, 3.0]))],
                path,
            )
            .unwrap_err()
            .to_string();
        assert!(e.contains("[3]") && e.contains("[2]"), "{e}");
        let e = ema
            .load(
                vec![
                    ("w".into(), Tensor::from_slice(&[1f32, 2.0])),
                    ("v".into(), Tensor::from_slice(&[1f32])),
                ],
                path,
            )
            .unwrap_err()
            .to_string();
        assert!(e.contains("unexpected `v`"), "{e}");
        ema.load(vec![("w".into(), Tensor::from_slice(&[5f32, 6.0]))], path)
            .unwrap();
        let q = param(&[0.0, 0.0]);
        ema.copy_into(&q);
        assert_eq!(Vec::<f32>::try_from(&q[0].1).unwrap(), vec![5.0, 6.0]);
    }
}
