//! The flow loss: a frozen, differentiable flow estimator `F` applied to
//! consecutive frames of the predicted and the ground-truth video, and a
//! direction + magnitude discrepancy on the pixels that move.
//!
//! `L_flow = w_dir * mean_M(1 - cos(F_pred, F_gt)) + w_mag * mean_M(huber(|F_pred| - |F_gt|))`
//!
//! where `M` holds the pixels whose ground-truth or predicted flow exceeds
//! `motion_threshold_px` (static background contributes nothing; motion
//! hallucinated on a static background is penalised through the magnitude
//! term). Gradients flow into the predicted frames only.

use crate::{Result, TrainError};
use bridgev2w_world_model::nets::raft::Raft;
use tch::{Kind, Tensor};

/// A frozen optical-flow estimator, differentiable with respect to its input
/// frames.
pub trait FlowEstimator: std::fmt::Debug {
    /// Flow from `from` to `to` (`[N, 3, H, W]` in `[-1, 1]`): `[N, 2, H, W]`
    /// in pixels (x then y).
    fn flow(&self, from: &Tensor, to: &Tensor) -> Result<Tensor>;
    /// A name for logs and reports ("raft_large", "lucas_kanade", ...).
    fn name(&self) -> String;
}

/// RAFT with a fixed number of refinement iterations.
#[derive(Debug)]
pub struct RaftFlow {
    /// The frozen network.
    pub raft: Raft,
    /// Refinement iterations (torchvision's default is 12).
    pub iterations: usize,
}

/// The size RAFT runs at for `(h, w)` frames: sides multiples of 8 and at
/// least 128 (RAFT's 1/8-resolution correlation pyramid needs that), aspect
/// ratio kept; `(h, w)` itself when it already qualifies.
pub fn raft_size(h: i64, w: i64) -> (i64, i64) {
    let ok = |x: i64| x >= 128 && x % 8 == 0;
    if ok(h) && ok(w) {
        return (h, w);
    }
    let scale = (128.0 / h.min(w) as f64).max(1.0);
    let up8 = |x: f64| ((x / 8.0).ceil() as i64 * 8).max(128);
    (up8(h as f64 * scale), up8(w as f64 * scale))
}

impl FlowEstimator for RaftFlow {
    /// Frames smaller than RAFT accepts (the tiny CPU configs) are upsampled
    /// bilinearly to [`raft_size`], and the flow is resized back with its
    /// vectors rescaled to the input's pixels.
    fn flow(&self, from: &Tensor, to: &Tensor) -> Result<Tensor> {
        check_pair(from, to)?;
        let s = from.size(); // [B, 3, H, W]
        let (h, w) = (s[2], s[3]);
        let (rh, rw) = raft_size(h, w);
        if (rh, rw) == (h, w) {
            return Ok(self.raft.forward(from, to, self.iterations)?);
        }
        let up = |x: &Tensor| x.upsample_bilinear2d([rh, rw], false, None, None);
        let f = self.raft.forward(&up(from), &up(to), self.iterations)?; // [B, 2, rh, rw]
        let f = f.upsample_bilinear2d([h, w], false, None, None); // [B, 2, H, W]
        let scale = Tensor::from_slice(&[w as f32 / rw as f32, h as f32 / rh as f32])
            .to_device(f.device())
            .to_kind(f.kind())
            .view([1, 2, 1, 1]);
        Ok(f * scale)
    }

    fn name(&self) -> String {
        if self.raft.config().mask_predictor {
            "raft_large".into()
        } else {
            "raft_small".into()
        }
    }
}

/// Single-scale Lucas-Kanade on grey levels: for every pixel the 2x2 least
/// squares system of the brightness-constancy equation over a square window
/// (window-averaged normal equations), regularised by adding `lambda` to the
/// diagonal (Tikhonov) so flat regions give zero flow. Cheap
/// and differentiable; accurate for motions of about a pixel or less. The
/// stand-in estimator for CPU training runs.
#[derive(Debug, Clone, PartialEq)]
pub struct LucasKanade {
    /// Window side (odd), pixels.
    pub window: i64,
    /// Tikhonov regularisation added to the diagonal of the window-averaged
    /// normal equations (squared grey-level gradients, inputs in [-1, 1]).
    pub lambda: f64,
}

impl Default for LucasKanade {
    fn default() -> Self {
        Self {
            window: 9,
            lambda: 1e-6,
        }
    }
}

impl FlowEstimator for LucasKanade {
    fn flow(&self, from: &Tensor, to: &Tensor) -> Result<Tensor> {
        check_pair(from, to)?;
        if self.window < 1 || self.window % 2 == 0 {
            return Err(TrainError::input(
                "Lucas-Kanade",
                format!("window {}: expected an odd size >= 1", self.window),
            ));
        }
        let grey = |x: &Tensor| x.mean_dim(1, true, Kind::Float); // [N, 1, H, W]
        let (i1, i2) = (grey(from), grey(to));
        let avg = (&i1 + &i2) * 0.5;
        // Central differences with replicated borders.
        let padded = avg.pad([1, 1, 1, 1], "replicate", None::<f64>); // [N, 1, H+2, W+2]
        let (h, w) = (avg.size()[2], avg.size()[3]);
        let ix =
            (padded.narrow(2, 1, h).narrow(3, 2, w) - padded.narrow(2, 1, h).narrow(3, 0, w)) * 0.5;
        let iy =
            (padded.narrow(2, 2, h).narrow(3, 1, w) - padded.narrow(2, 0, h).narrow(3, 1, w)) * 0.5;
        let it = &i2 - &i1;
        let k = self.window;
        let pad = k / 2;
        let sum = |x: Tensor| x.avg_pool2d([k, k], [1, 1], [pad, pad], false, false, None::<i64>);
        let (a11, a12, a22) = (
            sum(&ix * &ix) + self.lambda,
            sum(&ix * &iy),
            sum(&iy * &iy) + self.lambda,
        );
        let (b1, b2) = (-sum(&ix * &it), -sum(&iy * &it));
        let det = &a11 * &a22 - &a12 * &a12;
        let u = (&a22 * &b1 - &a12 * &b2) / &det;
        let v = (&a11 * &b2 - &a12 * &b1) / &det;
        Ok(Tensor::cat(&[u, v], 1)) // [N, 2, H, W]
    }

    fn name(&self) -> String {
        format!("lucas_kanade(window={})", self.window)
    }
}

fn check_pair(a: &Tensor, b: &Tensor) -> Result<()> {
    let (sa, sb) = (a.size(), b.size());
    if sa != sb || sa.len() != 4 || sa[1] != 3 {
        return Err(TrainError::input(
            "flow estimator",
            format!("frames {sa:?} and {sb:?}: expected two [N, 3, H, W] tensors of one shape"),
        ));
    }
    Ok(())
}

/// Options of the flow discrepancy.
#[derive(Debug, Clone, PartialEq)]
pub struct FlowLossConfig {
    /// Flow magnitude (pixels) above which a pixel counts as moving.
    pub motion_threshold_px: f64,
    /// Huber transition point of the magnitude term, pixels.
    pub huber_delta_px: f64,
    /// Weight of the direction (cosine) term.
    pub direction_weight: f64,
    /// Weight of the magnitude (Huber) term.
    pub magnitude_weight: f64,
}

impl Default for FlowLossConfig {
    fn default() -> Self {
        Self {
            motion_threshold_px: 0.5,
            huber_delta_px: 1.0,
            direction_weight: 1.0,
            magnitude_weight: 1.0,
        }
    }
}

/// The direction + magnitude discrepancy of two flow fields `[N, 2, H, W]`
/// (see the module docs). Zero when no pixel moves.
pub fn flow_discrepancy(pred: &Tensor, gt: &Tensor, cfg: &FlowLossConfig) -> Result<Tensor> {
    let (sp, sg) = (pred.size(), gt.size());
    if sp != sg || sp.len() != 4 || sp[1] != 2 {
        return Err(TrainError::input(
            "flow loss",
            format!("flows {sp:?} and {sg:?}: expected two [N, 2, H, W] tensors of one shape"),
        ));
    }
    let eps = 1e-8;
    let norm = |f: &Tensor| (f.square().sum_dim_intlist(1, false, Kind::Float) + 1e-12).sqrt(); // [N, H, W]
    let (np, ng) = (norm(pred), norm(gt));
    let moving = (ng
        .ge(cfg.motion_threshold_px)
        .logical_or(&np.ge(cfg.motion_threshold_px)))
    .detach()
    .to_kind(Kind::Float);
    let count = moving.sum(Kind::Float).clamp_min(1.0);
    let dot = (pred * gt).sum_dim_intlist(1, false, Kind::Float);
    let cos = dot / (&np * &ng).clamp_min(eps);
    let direction = ((-cos + 1.0) * &moving).sum(Kind::Float) / &count;
    let magnitude = ((np - ng).huber_loss(
        &Tensor::zeros_like(&moving),
        tch::Reduction::None,
        cfg.huber_delta_px,
    ) * &moving)
        .sum(Kind::Float)
        / &count;
    Ok(direction * cfg.direction_weight + magnitude * cfg.magnitude_weight)
}

/// The flow loss between a predicted and a ground-truth video `[B, 3, T, H, W]`
/// in `[-1, 1]`: flows of every consecutive frame pair, the ground truth's
/// without gradients.
pub fn flow_loss(
    estimator: &dyn FlowEstimator,
    pred: &Tensor,
    gt: &Tensor,
    cfg: &FlowLossConfig,
) -> Result<Tensor> {
    let (sp, sg) = (pred.size(), gt.size());
    if sp != sg || sp.len() != 5 || sp[1] != 3 || sp[2] < 2 {
        return Err(TrainError::input(
            "flow loss",
            format!(
                "videos {sp:?} and {sg:?}: expected two [B, 3, T >= 2, H, W] tensors of one shape"
            ),
        ));
    }
    let (b, t, h, w) = (sp[0], sp[2], sp[3], sp[4]);
    // [B, 3, T, H, W] -> pairs [B * (T - 1), 3, H, W]
    let pairs = |v: &Tensor, start: i64| {
        v.narrow(2, start, t - 1)
            .permute([0, 2, 1, 3, 4]) // [B, T-1, 3, H, W]
            .reshape([b * (t - 1), 3, h, w])
    };
    let flow_pred = estimator.flow(&pairs(pred, 0), &pairs(pred, 1))?;
    let flow_gt = tch::no_grad(|| estimator.flow(&pairs(gt, 0), &pairs(gt, 1)))?;
    flow_discrepancy(&flow_pred, &flow_gt, cfg)
}

/// The flow-loss weight of an epoch: 0 before `e_switch`, then `lambda`.
pub fn flow_weight(epoch: usize, e_switch: usize, lambda: f64) -> f64 {
    if epoch < e_switch {
        0.0
    } else {
        lambda
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn raft_size_keeps_aspect_and_meets_raft_limits() {
        assert_eq!(raft_size(480, 720), (480, 720));
        assert_eq!(raft_size(64, 96), (128, 192));
        assert_eq!(raft_size(100, 200), (128, 256));
        assert_eq!(raft_size(130, 130), (136, 136));
    }
    use tch::Device;

    fn field(n: i64, h: i64, w: i64, f: impl Fn(i64, i64) -> (f32, f32)) -> Tensor {
        let mut data = Vec::new();
        for c in 0..2 {
            for y in 0..h {
                for x in 0..w {
                    let (u, v) = f(x, y);
                    data.push(if c == 0 { u } else { v });
                }
            }
        }
        Tensor::from_slice(&data)
            .view([1, 2, h, w])
            .repeat([n, 1, 1, 1])
    }

    #[test]
    fn discrepancy_closed_forms() {
        let cfg = FlowLossConfig::default();
        // Right half moves by (2, 0); left half static.
        let gt = field(1, 4, 8, |x, _| if x >= 4 { (2.0, 0.0) } else { (0.0, 0.0) });
        assert!(
            flow_discrepancy(&gt, &gt, &cfg)
                .unwrap()
                .double_value(&[])
                .abs()
                < 1e-5
        );
        // Opposite direction, same magnitude: direction term 2, magnitude 0.
        let l = flow_discrepancy(&(-&gt), &gt, &cfg)
            .unwrap()
            .double_value(&[]);
        assert!((l - 2.0).abs() < 1e-4, "{l}");
        // Same direction, 3.5 px instead of 2: Huber(1.5, delta 1) = 1.5 - 0.5 = 1.
        let pred = field(1, 4, 8, |x, _| if x >= 4 { (3.5, 0.0) } else { (0.0, 0.0) });
        let l = flow_discrepancy(&pred, &gt, &cfg)
            .unwrap()
            .double_value(&[]);
        assert!((l - 1.0).abs() < 1e-4, "{l}");
        // Static pixels with tiny noise do not count.
        let noisy = field(1, 4, 8, |x, y| {
            if x >= 4 {
                (2.0, 0.0)
            } else {
                (0.01 * y as f32, 0.0)
            }
        });
        let l = flow_discrepancy(&noisy, &gt, &cfg)
            .unwrap()
            .double_value(&[]);
        assert!(l.abs() < 1e-4, "{l}");
        // Nothing moves: zero, not NaN.
        let zero = field(1, 4, 8, |_, _| (0.0, 0.0));
        assert_eq!(
            flow_discrepancy(&zero, &zero, &cfg)
                .unwrap()
                .double_value(&[]),
            0.0
        );
        assert!(flow_discrepancy(&zero, &zero.narrow(3, 0, 4), &cfg).is_err());
    }

    /// A smooth image sampled at (x - dx, y - dy): its content moves by (dx, dy).
    fn smooth(h: i64, w: i64, dx: f64, dy: f64) -> Tensor {
        let mut data = Vec::new();
        for c in 0..3 {
            for y in 0..h {
                for x in 0..w {
                    let (xs, ys) = (x as f64 - dx, y as f64 - dy);
                    let v = 0.5 * (xs * 0.21 + c as f64).sin() * (ys * 0.17).cos()
                        + 0.3 * (0.13 * (xs + ys)).sin();
                    data.push(v as f32);
                }
            }
        }
        Tensor::from_slice(&data).view([1, 3, h, w])
    }

    #[test]
    fn lucas_kanade_recovers_a_subpixel_shift() {
        let lk = LucasKanade::default();
        let (a, b) = (smooth(48, 64, 0.0, 0.0), smooth(48, 64, 0.4, -0.3));
        let f = lk.flow(&a, &b).unwrap();
        // Interior mean (away from borders).
        let inner = f.narrow(2, 8, 32).narrow(3, 8, 48);
        let u = inner.get(0).get(0).mean(Kind::Float).double_value(&[]);
        let v = inner.get(0).get(1).mean(Kind::Float).double_value(&[]);
        assert!(
            (u - 0.4).abs() < 0.05 && (v + 0.3).abs() < 0.05,
            "({u}, {v})"
        );
        let e = LucasKanade {
            window: 4,
            lambda: 1e-6,
        }
        .flow(&a, &b)
        .unwrap_err()
        .to_string();
        assert!(e.contains("odd"), "{e}");
    }

    #[test]
    fn flow_loss_is_zero_on_identical_videos_and_differentiable() {
        let lk = LucasKanade::default();
        let cfg = FlowLossConfig {
            motion_threshold_px: 0.1,
            ..Default::default()
        };
        // [1, 3, 3, H, W]: content drifting right.
        let frames: Vec<Tensor> = (0..3)
            .map(|t| smooth(32, 40, 0.3 * t as f64, 0.0))
            .collect();
        let gt = Tensor::stack(&frames, 2).squeeze_dim(0).unsqueeze(0); // [1, 3, 3, H, W]
        assert_eq!(gt.size(), [1, 3, 3, 32, 40]);
        let l = flow_loss(&lk, &gt, &gt, &cfg).unwrap().double_value(&[]);
        assert!(l.abs() < 1e-5, "{l}");
        // A static prediction: the loss is positive and has gradients.
        let still = Tensor::stack(&[&frames[0], &frames[0], &frames[0]], 2)
            .squeeze_dim(0)
            .unsqueeze(0);
        let still = (still + 0.0).set_requires_grad(true);
        let moved = Tensor::stack(&[&frames[0], &frames[1], &frames[1]], 2)
            .squeeze_dim(0)
            .unsqueeze(0);
        let l = flow_loss(&lk, &moved.set_requires_grad(true), &gt, &cfg).unwrap();
        assert!(l.double_value(&[]) > 0.0);
        l.backward();
        let l2 = flow_loss(&lk, &still, &gt, &cfg).unwrap();
        assert!(l2.double_value(&[]) > 0.0);
        l2.backward();
        assert!(still.grad().abs().sum(Kind::Float).double_value(&[]) > 0.0);
        let _ = Device::Cpu;
    }

    #[test]
    fn flow_weight_switches_on_at_e_switch() {
        assert_eq!(flow_weight(0, 5, 0.05), 0.0);
        assert_eq!(flow_weight(4, 5, 0.05), 0.0);
        assert_eq!(flow_weight(5, 5, 0.05), 0.05);
    }
}
