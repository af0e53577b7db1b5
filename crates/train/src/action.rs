//! The paper's "w/o mask action" ablation: end-effector actions, not
//! embodiment masks, condition the backbone. The action sequence (`[B, T, A]`,
//! 7-D per arm) is normalised, grouped per latent frame (the VAE's temporal
//! compression: latent frame 0 <- pixel frame 0, latent frame k <- pixel frames
//! 4k-3..4k), embedded by a two-layer MLP into one token per latent frame, and
//! added — through a zero-initialised linear projection per backbone block, as
//! the ControlNet's residuals — to every video token of that latent frame
//! after blocks `0..layers`.

use crate::{Result, TrainError};
use tch::nn::{self, Module};
use tch::{Kind, Tensor};

/// The action MLP.
#[derive(Debug)]
pub struct ActionEncoder {
    mean: Tensor,
    std: Tensor,
    fc1: nn::Linear,
    fc2: nn::Linear,
    out: Vec<nn::Linear>,
    action_dim: i64,
    group: i64,
}

impl ActionEncoder {
    /// Variables under `p`: `mean`, `std` (frozen normalisation), `fc1`, `fc2`,
    /// `out.{i}` (zero-initialised) for `layers` backbone blocks of width `inner_dim`.
    pub fn new(
        p: &nn::Path,
        action_dim: i64,
        temporal_compression: i64,
        hidden: i64,
        inner_dim: i64,
        layers: usize,
    ) -> Self {
        let group = temporal_compression.max(1);
        let zero = nn::LinearConfig {
            ws_init: nn::Init::Const(0.0),
            bs_init: Some(nn::Init::Const(0.0)),
            bias: true,
        };
        Self {
            mean: p.zeros_no_train("mean", &[action_dim]),
            std: p.ones_no_train("std", &[action_dim]),
            fc1: nn::linear(p / "fc1", group * action_dim, hidden, Default::default()),
            fc2: nn::linear(p / "fc2", hidden, inner_dim, Default::default()),
            out: (0..layers)
                .map(|i| nn::linear(p / "out" / i, inner_dim, inner_dim, zero))
                .collect(),
            action_dim,
            group,
        }
    }

    /// Sets the normalisation (per-dimension mean and std of the training actions).
    pub fn set_stats(&self, mean: &[f32], std: &[f32]) -> Result<()> {
        if mean.len() as i64 != self.action_dim || std.len() as i64 != self.action_dim {
            return Err(TrainError::input(
                "action statistics",
                format!(
                    "{} means and {} stds for {}-D actions",
                    mean.len(),
                    std.len(),
                    self.action_dim
                ),
            ));
        }
        tch::no_grad(|| {
            self.mean
                .shallow_clone()
                .copy_(&Tensor::from_slice(mean).to_device(self.mean.device()));
            self.std
                .shallow_clone()
                .copy_(&Tensor::from_slice(std).to_device(self.std.device()));
        });
        Ok(())
    }

    /// Per-block residuals `[B, t * tokens_per_frame, D]` for actions `[B, T, A]`
    /// (`T = group (t - 1) + 1`), each latent frame's embedding repeated over its
    /// `tokens_per_frame` video tokens (frame-major token order).
    pub fn residuals(&self, actions: &Tensor, tokens_per_frame: i64) -> Result<Vec<Tensor>> {
        let s = actions.size();
        if s.len() != 3 || s[2] != self.action_dim || s[1] < 1 || (s[1] - 1) % self.group != 0 {
            return Err(TrainError::input(
                "actions",
                format!(
                    "{s:?}: expected [B, {}k + 1, {}]",
                    self.group, self.action_dim
                ),
            ));
        }
        let (b, t) = (s[0], s[1]);
        let latent_frames = (t - 1) / self.group + 1;
        let a = (actions.to_kind(Kind::Float) - &self.mean) / &self.std; // [B, T, A]
        let first = a.narrow(1, 0, 1).repeat([1, self.group, 1]).reshape([
            b,
            1,
            self.group * self.action_dim,
        ]);
        let rest =
            a.narrow(1, 1, t - 1)
                .reshape([b, latent_frames - 1, self.group * self.action_dim]);
        let grouped = Tensor::cat(&[first, rest], 1); // [B, t, group * A]
        let emb = self.fc2.forward(&self.fc1.forward(&grouped).silu()); // [B, t, D]
        let d = emb.size()[2];
        Ok(self
            .out
            .iter()
            .map(|proj| {
                proj.forward(&emb) // [B, t, D]
                    .unsqueeze(2)
                    .expand([b, latent_frames, tokens_per_frame, d], false)
                    .reshape([b, latent_frames * tokens_per_frame, d])
            })
            .collect())
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use tch::Device;

    #[test]
    fn shapes_zero_start_and_per_frame_tokens() {
        let vs = nn::VarStore::new(Device::Cpu);
        let enc = ActionEncoder::new(&(vs.root() / "action_encoder"), 7, 4, 16, 8, 2);
        enc.set_stats(&[0.0; 7], &[1.0; 7]).unwrap();
        let actions = Tensor::randn([2, 9, 7], (Kind::Float, Device::Cpu));
        let r = enc.residuals(&actions, 6).unwrap();
        assert_eq!(r.len(), 2);
        assert_eq!(r[0].size(), [2, 3 * 6, 8]);
        // Zero-initialised projections: no effect at the start.
        assert_eq!(r[0].abs().sum(Kind::Float).double_value(&[]), 0.0);
        // After perturbing the projection, tokens of one latent frame agree
        // and actions of frames 5..8 only change latent frame 2.
        tch::no_grad(|| {
            for (name, mut t) in vs.variables() {
                if name.contains("out.0") {
                    let _ = t.fill_(0.1);
                }
            }
        });
        let r = enc.residuals(&actions, 6).unwrap();
        let f0 = r[0].narrow(1, 0, 6);
        assert!(f0
            .narrow(1, 0, 1)
            .expand([2, 6, 8], false)
            .allclose(&f0, 1e-6, 1e-6, false));
        let moved = actions.copy();
        let _ = moved.narrow(1, 5, 4).fill_(3.0);
        let r2 = enc.residuals(&moved, 6).unwrap();
        assert!(r2[0].narrow(1, 0, 12).equal(&r[0].narrow(1, 0, 12)));
        assert!(!r2[0].narrow(1, 12, 6).equal(&r[0].narrow(1, 12, 6)));
        assert!(enc.residuals(&actions.narrow(1, 0, 8), 6).is_err());
        assert!(enc.set_stats(&[0.0; 6], &[1.0; 7]).is_err());
    }
}
