//! The diffusion and dynamics-consistency losses of the paper.
//!
//! Squared norms are averaged over their elements (the paper's `|| . ||_2^2`
//! divided by the element count), so loss scales do not depend on the
//! latent size; the relative weights `lambda_dyn`, `lambda_flow` apply on top.

use crate::{Result, TrainError};
use tch::{Kind, Tensor};

/// The clean latents implied by a velocity prediction:
/// `x0_hat = sqrt(a) z_t - sqrt(1 - a) v`, with `alpha_bar` broadcasting over
/// the sample (e.g. `[B, 1, 1, 1, 1]`).
pub fn predicted_x0(z_t: &Tensor, v_pred: &Tensor, alpha_bar: &Tensor) -> Tensor {
    alpha_bar.sqrt() * z_t - (-alpha_bar + 1.0).sqrt() * v_pred
}

fn same_shape(what: &str, a: &Tensor, b: &Tensor) -> Result<()> {
    if a.size() != b.size() {
        return Err(TrainError::input(
            what,
            format!("shapes {:?} and {:?} differ", a.size(), b.size()),
        ));
    }
    Ok(())
}

/// The paper's v-prediction diffusion loss:
/// `mean((z0 - (sqrt(a) z_t - sqrt(1 - a) v_theta))^2)`.
pub fn diffusion_loss(
    z0: &Tensor,
    z_t: &Tensor,
    v_pred: &Tensor,
    alpha_bar: &Tensor,
) -> Result<Tensor> {
    same_shape("diffusion loss (z0, z_t)", z0, z_t)?;
    same_shape("diffusion loss (z0, v_pred)", z0, v_pred)?;
    let x0 = predicted_x0(z_t, v_pred, alpha_bar);
    Ok((z0 - x0).square().mean(Kind::Float))
}

/// The dynamics-consistency loss over latent frames (`[B, F, ...]`, frames on
/// dimension 1):
/// `sum_{j=1..K} 1/(F - j) sum_{t=0..F-1-j} mean(((p_{t+j} - p_t) - (g_{t+j} - g_t))^2)`.
/// Offsets `j >= F` have no pairs and are skipped.
pub fn dynamics_loss(pred: &Tensor, gt: &Tensor, k: usize) -> Result<Tensor> {
    same_shape("dynamics loss", pred, gt)?;
    let size = pred.size();
    if size.len() < 2 {
        return Err(TrainError::input(
            "dynamics loss",
            format!("shape {size:?}: expected [B, F, ...]"),
        ));
    }
    if k == 0 {
        return Err(TrainError::input(
            "dynamics loss",
            "K = 0: expected at least one offset",
        ));
    }
    let f = size[1];
    let diff = pred - gt; // the loss depends only on the error's temporal differences
                          // Accumulate in f32 (bf16/f16 inputs) or f64 when the inputs are f64.
    let acc = if pred.kind() == Kind::Double {
        Kind::Double
    } else {
        Kind::Float
    };
    let mut total = Tensor::zeros([], (acc, pred.device()));
    for j in 1..=(k as i64).min(f - 1) {
        // [B, F - j, ...]: e_{t+j} - e_t for t = 0..F-1-j
        let d = diff.narrow(1, j, f - j) - diff.narrow(1, 0, f - j);
        // mean over elements of one pair, summed over the F - j pairs, / (F - j)
        total += d.square().mean(acc);
    }
    Ok(total)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use tch::Device;

    fn randn(shape: &[i64], seed: i64) -> Tensor {
        tch::manual_seed(seed);
        Tensor::randn(shape, (Kind::Float, Device::Cpu))
    }

    #[test]
    fn diffusion_loss_zero_for_the_true_velocity_and_closed_form_otherwise() {
        let (z0, noise) = (randn(&[2, 3, 4, 5, 6], 1), randn(&[2, 3, 4, 5, 6], 2));
        let a = Tensor::from_slice(&[0.3f32, 0.8]).view([2, 1, 1, 1, 1]);
        let z_t = a.sqrt() * &z0 + (-&a + 1.0).sqrt() * &noise;
        let v = a.sqrt() * &noise - (-&a + 1.0).sqrt() * &z0;
        let l = diffusion_loss(&z0, &z_t, &v, &a).unwrap().double_value(&[]);
        assert!(l.abs() < 1e-10, "{l}");
        // v + d: x0_hat moves by -sqrt(1 - a) d, loss = mean((1 - a) d^2).
        let d = 0.5;
        let l = diffusion_loss(&z0, &z_t, &(&v + d), &a)
            .unwrap()
            .double_value(&[]);
        let expected = ((1.0 - 0.3) + (1.0 - 0.8)) / 2.0 * d * d;
        assert!((l - expected).abs() < 1e-6, "{l} vs {expected}");
        assert!(diffusion_loss(&z0, &z_t, &v.narrow(0, 0, 1), &a).is_err());
    }

    #[test]
    fn dynamics_loss_hand_computed() {
        // One element per frame: errors e = [0, 1, 3] over F = 3 frames.
        let gt = Tensor::zeros([1, 3, 1], (Kind::Float, Device::Cpu));
        let pred = Tensor::from_slice(&[0.0f32, 1.0, 3.0]).view([1, 3, 1]);
        // j = 1: pairs (1-0)^2, (3-1)^2 -> (1 + 4) / 2 = 2.5; j = 2: (3-0)^2 / 1 = 9.
        let l = dynamics_loss(&pred, &gt, 4).unwrap().double_value(&[]);
        assert!((l - 11.5).abs() < 1e-6, "{l}");
        let l1 = dynamics_loss(&pred, &gt, 1).unwrap().double_value(&[]);
        assert!((l1 - 2.5).abs() < 1e-6, "{l1}");
        // A frame-constant error (a global offset) has no dynamics error.
        let gt = randn(&[2, 5, 3, 4], 3);
        let l = dynamics_loss(&(&gt + 0.7), &gt, 4)
            .unwrap()
            .double_value(&[]);
        assert!(l.abs() < 1e-10, "{l}");
        assert!(dynamics_loss(&gt, &gt, 0).is_err());
    }

    #[test]
    fn dynamics_loss_gradient_matches_finite_differences() {
        // In f64: the loss is quadratic, so central differences are exact up
        // to rounding, which f32 makes too coarse for a tight tolerance.
        let gt = randn(&[1, 4, 3], 4).to_kind(Kind::Double);
        let pred = randn(&[1, 4, 3], 5)
            .to_kind(Kind::Double)
            .set_requires_grad(true);
        let l = dynamics_loss(&pred, &gt, 4).unwrap();
        l.backward();
        let g = pred.grad();
        let h = 1e-3;
        for i in 0..4 {
            for c in 0..3 {
                let bump = |s: f64| {
                    let p = pred.detach().copy();
                    let _ = p
                        .get(0)
                        .get(i)
                        .get(c)
                        .fill_(pred.double_value(&[0, i, c]) + s);
                    dynamics_loss(&p, &gt, 4).unwrap().double_value(&[])
                };
                let fd = (bump(h) - bump(-h)) / (2.0 * h);
                let an = g.double_value(&[0, i, c]);
                assert!(
                    (fd - an).abs() < 1e-6 * an.abs().max(1e-2),
                    "[{i},{c}] {fd} vs {an}"
                );
            }
        }
    }
}
