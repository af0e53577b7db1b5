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
    Ok(x0_squared_error(z0, z_t, v_pred, alpha_bar)?.mean(Kind::Float))
}

/// `(z0 - x0_hat)^2` per element, the shapes checked.
fn x0_squared_error(
    z0: &Tensor,
    z_t: &Tensor,
    v_pred: &Tensor,
    alpha_bar: &Tensor,
) -> Result<Tensor> {
    same_shape("diffusion loss (z0, z_t)", z0, z_t)?;
    same_shape("diffusion loss (z0, v_pred)", z0, v_pred)?;
    Ok((z0 - predicted_x0(z_t, v_pred, alpha_bar)).square())
}

/// [`diffusion_loss`] with a weight per latent pixel: `mean(w (z0 - x0_hat)^2)`
/// with `weights` broadcasting over the latents (e.g. `[B, t, 1, h, w]` from
/// [`motion_weights`]). All-ones weights give [`diffusion_loss`].
pub fn weighted_diffusion_loss(
    z0: &Tensor,
    z_t: &Tensor,
    v_pred: &Tensor,
    alpha_bar: &Tensor,
    weights: &Tensor,
) -> Result<Tensor> {
    Ok((x0_squared_error(z0, z_t, v_pred, alpha_bar)? * weights).mean(Kind::Float))
}

/// Loss weights `[B, t, 1, h, w]` for latents of `latent` = `[B, t, C, h, w]`:
/// `1 + weight` on the latent pixels the robot covers, 1 elsewhere. `masks`
/// are the mask videos `[B, 3, T, H, W]` in {-1, 1}; a pixel is the robot's
/// in frame `f` when any channel is > 0 there, or in the first frame (the
/// pixels it leaves change too). The silhouettes are max-pooled to the latent
/// grid (`T -> t`, `H x W -> h x w`) and dilated by one latent pixel.
pub fn motion_weights(masks: &Tensor, latent: &[i64], weight: f64) -> Result<Tensor> {
    let ms = masks.size();
    if ms.len() != 5 || latent.len() != 5 || ms[0] != latent[0] {
        return Err(TrainError::input(
            "motion weights",
            format!(
                "masks {ms:?} and latents {latent:?}: expected [B, 3, T, H, W] and [B, t, C, h, w]"
            ),
        ));
    }
    let (t, h, w) = (latent[1], latent[3], latent[4]);
    let m = bridgev2w_world_model::static_scene::robot_silhouettes(masks); // [B, 1, T, H, W]
    let m = m.maximum(&m.narrow(2, 0, 1)); // with the first frame's silhouette
    let (m, _) = m.adaptive_max_pool3d([t, h, w]); // [B, 1, t, h, w]
    let m = m.max_pool3d([1, 3, 3], [1, 1, 1], [0, 1, 1], [1, 1, 1], false);
    let m = m.permute([0, 2, 1, 3, 4]); // [B, t, 1, h, w]
    Ok(m * weight + 1.0)
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
    fn motion_weights_cover_the_silhouettes_of_the_frame_and_the_first_frame() {
        // One clip of 3 frames, 8 x 8 pixels, latents at half the size.
        let masks = Tensor::full([1, 3, 3, 8, 8], -1.0, (Kind::Float, Device::Cpu));
        // Frame 0: the robot at pixel (0, 0); frame 2: at pixel (7, 7), one channel only.
        let _ = masks
            .get(0)
            .narrow(1, 0, 1)
            .narrow(2, 0, 1)
            .narrow(3, 0, 1)
            .fill_(1.0);
        let _ = masks
            .get(0)
            .narrow(0, 1, 1)
            .narrow(1, 2, 1)
            .narrow(2, 7, 1)
            .narrow(3, 7, 1)
            .fill_(1.0);
        let w = motion_weights(&masks, &[1, 3, 4, 4, 4], 3.0).unwrap();
        assert_eq!(w.size(), vec![1, 3, 1, 4, 4]);
        let at = |f: i64, y: i64, x: i64| w.double_value(&[0, f, 0, y, x]);
        // The first frame's cell (0, 0) and its one-cell dilation, in every frame.
        for f in 0..3 {
            for (y, x) in [(0, 0), (1, 1), (0, 1)] {
                assert_eq!(at(f, y, x), 4.0, "frame {f} ({y}, {x})");
            }
            assert_eq!(at(f, 2, 0), 1.0, "frame {f} (2, 0)");
        }
        // Frame 2's own cell (3, 3) and its dilation, only in frame 2.
        assert_eq!(at(2, 3, 3), 4.0);
        assert_eq!(at(2, 2, 2), 4.0);
        assert_eq!(at(1, 3, 3), 1.0);
        assert_eq!(at(0, 2, 2), 1.0);
        // Weighted count: frame 0 and 1 four cells, frame 2 4 + 4 cells, at weight 3.
        let total = w.sum(Kind::Float).double_value(&[]);
        assert_eq!(total, 48.0 + 3.0 * (4.0 + 4.0 + 8.0));
        assert!(motion_weights(&masks, &[1, 3, 4, 4], 3.0).is_err());
    }

    #[test]
    fn weighted_diffusion_loss_closed_form() {
        let z0 = Tensor::from_slice(&[1.0f32, 2.0]).view([1, 1, 2, 1, 1]);
        let zt = Tensor::from_slice(&[0.0f32, 0.0]).view([1, 1, 2, 1, 1]);
        let v = Tensor::from_slice(&[-1.0f32, 0.0]).view([1, 1, 2, 1, 1]);
        let a = Tensor::from_slice(&[0.75f32]).view([1, 1, 1, 1, 1]);
        // x0_hat = -sqrt(0.25) v = [0.5, 0]: errors 0.25 and 4.
        let w = Tensor::from_slice(&[3.0f32]).view([1, 1, 1, 1, 1]);
        let l = weighted_diffusion_loss(&z0, &zt, &v, &a, &w).unwrap();
        assert!((l.double_value(&[]) - 3.0 * (0.25 + 4.0) / 2.0).abs() < 1e-6);
        let plain = diffusion_loss(&z0, &zt, &v, &a).unwrap();
        let ones = weighted_diffusion_loss(&z0, &zt, &v, &a, &w.ones_like()).unwrap();
        assert_eq!(plain.double_value(&[]), ones.double_value(&[]));
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
