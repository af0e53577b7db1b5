//! A learned robot segmenter for Mask-IoU on generated frames (the paper
//! segments with Grounded SAM, which cannot be downloaded here): a small
//! dilated CNN trained with binary cross-entropy on the training split's
//! frames and ground-truth masks. Unlike a colour classifier
//! ([`bridgev2w_eval::segment::ColorSegmenter`]) it sees shape and shading,
//! so grey table tops and grey links are told apart.

use crate::data::ClipDataset;
use crate::{Result, TrainError};
use bridgev2w_eval::segment::RobotSegmenter;
use bridgev2w_io::frame::RgbFrame;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tch::nn::{self, Module, OptimizerConfig};
use tch::{Device, Kind, Tensor};

/// Which robot segmenter scores Mask-IoU (`eval-run --segmenter`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SegmenterKind {
    /// A small dilated CNN ([`CnnSegmenter`]), shape-aware.
    Cnn,
    /// A colour classifier (`evaluate::color_segmenter`).
    Color,
}

bridgev2w_world_model::named_enum!(SegmenterKind, TrainError, TrainError::input, "segmenter", {
    Cnn => "cnn",
    Color => "color",
});

/// Training settings of [`CnnSegmenter::fit`].
#[derive(Debug, Clone, PartialEq)]
pub struct SegmenterOptions {
    /// Adam steps.
    pub steps: usize,
    /// Frames per step.
    pub batch: usize,
    /// Learning rate.
    pub lr: f64,
    /// Seed of the initial weights and the frame draws.
    pub seed: u64,
}

impl Default for SegmenterOptions {
    fn default() -> Self {
        Self {
            steps: 400,
            batch: 16,
            lr: 3e-3,
            seed: 0,
        }
    }
}

/// Conv 3x3 (dilations 1, 2, 4, 8; receptive field 31 px), 16 channels,
/// ReLU, then a 1x1 logit. Runs on the CPU.
#[derive(Debug)]
pub struct CnnSegmenter {
    _vs: nn::VarStore,
    net: nn::Sequential,
    /// Mean binary cross-entropy over the last 20 training steps.
    pub final_loss: f64,
}

fn net(p: &nn::Path) -> nn::Sequential {
    let mut s = nn::seq();
    let mut c_in = 3;
    for (i, d) in [1, 2, 4, 8].into_iter().enumerate() {
        let cfg = nn::ConvConfig {
            padding: d,
            dilation: d,
            ..Default::default()
        };
        s = s
            .add(nn::conv2d(p / format!("conv{i}"), c_in, 16, 3, cfg))
            .add_fn(|x| x.relu());
        c_in = 16;
    }
    s.add(nn::conv2d(p / "logit", 16, 1, 1, Default::default()))
}

/// `[H, W, 3]` RGB8 frames to `[N, 3, H, W]` in [-1, 1].
fn to_input(frames: &[&[u8]], h: usize, w: usize) -> Tensor {
    let data: Vec<u8> = frames.concat();
    Tensor::from_slice(&data)
        .view([frames.len() as i64, h as i64, w as i64, 3])
        .permute([0, 3, 1, 2]) // [N, H, W, 3] -> [N, 3, H, W]
        .to_kind(Kind::Float)
        / 127.5
        - 1.0
}

impl CnnSegmenter {
    /// Trains on every frame of `data`'s episodes with masks; `None` when no
    /// episode has masks.
    pub fn fit(data: &ClipDataset, opts: &SegmenterOptions) -> Result<Option<Self>> {
        let masked = data.masked_frames();
        let Some(first) = masked.first() else {
            return Ok(None);
        };
        let frames: Vec<(&[u8], &[u8])> = masked.iter().map(|f| (f.rgb, f.mask)).collect();
        Self::fit_frames(&frames, first.height, first.width, opts).map(Some)
    }

    /// Trains on `(rgb8 [H, W, 3], mask [H, W])` frame pairs (mask non-zero =
    /// robot), all `height` x `width`.
    pub fn fit_frames(
        frames: &[(&[u8], &[u8])],
        height: usize,
        width: usize,
        opts: &SegmenterOptions,
    ) -> Result<Self> {
        let (h, w) = (height, width);
        let px = h * w;
        if frames.is_empty() {
            return Err(TrainError::input("segmenter", "no frames to train on"));
        }
        if let Some(i) = frames
            .iter()
            .position(|(rgb, m)| rgb.len() != px * 3 || m.len() != px)
        {
            return Err(TrainError::input(
                "segmenter",
                format!(
                    "frame {i}: {} RGB bytes and {} mask values, expected {} and {px} ({w}x{h})",
                    frames[i].0.len(),
                    frames[i].1.len(),
                    px * 3
                ),
            ));
        }
        tch::manual_seed(opts.seed as i64);
        let vs = nn::VarStore::new(Device::Cpu);
        let net = net(&vs.root());
        let mut opt = nn::Adam::default()
            .build(&vs, opts.lr)
            .map_err(|e| TrainError::input("segmenter", e.to_string()))?;
        let mut rng = ChaCha8Rng::seed_from_u64(opts.seed);
        // Robot pixels are few: weight them by sqrt(background / robot).
        let robot: usize = frames
            .iter()
            .map(|(_, m)| m.iter().filter(|&&v| v != 0).count())
            .sum();
        let total = frames.len() * px;
        let pos_weight = ((total - robot) as f64 / robot.max(1) as f64)
            .sqrt()
            .clamp(1.0, 10.0);
        let pos_weight = Tensor::from_slice(&[pos_weight as f32]);
        let mut recent = Vec::new();
        for _ in 0..opts.steps {
            let pick: Vec<usize> = (0..opts.batch.max(1))
                .map(|_| rng.gen_range(0..frames.len()))
                .collect();
            let rgb: Vec<&[u8]> = pick.iter().map(|&i| frames[i].0).collect();
            let masks: Vec<u8> = pick
                .iter()
                .flat_map(|&i| frames[i].1.iter().map(|&v| u8::from(v != 0)))
                .collect();
            // [N, 1, H, W] targets in {0, 1}
            let target = Tensor::from_slice(&masks)
                .view([pick.len() as i64, 1, h as i64, w as i64])
                .to_kind(Kind::Float);
            let logits = net.forward(&to_input(&rgb, h, w));
            let loss = logits.binary_cross_entropy_with_logits::<&Tensor>(
                &target,
                None,
                Some(&pos_weight),
                tch::Reduction::Mean,
            );
            opt.backward_step(&loss);
            recent.push(loss.double_value(&[]));
        }
        let tail = &recent[recent.len().saturating_sub(20)..];
        let final_loss = tail.iter().sum::<f64>() / tail.len().max(1) as f64;
        Ok(Self {
            _vs: vs,
            net,
            final_loss,
        })
    }
}

impl RobotSegmenter for CnnSegmenter {
    fn segment(&self, frame: &RgbFrame) -> bridgev2w_eval::Result<Vec<u8>> {
        let rgb = frame.to_rgb8();
        let logits = tch::no_grad(|| {
            self.net
                .forward(&to_input(&[&rgb], frame.height, frame.width))
        });
        let m = logits.gt(0.0).to_kind(Kind::Uint8).flatten(0, -1);
        Vec::<u8>::try_from(m)
            .map_err(|e| bridgev2w_eval::MetricError::Invalid(format!("segmenter output: {e}")))
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use bridgev2w_eval::segment::ColorSegmenter;
    use bridgev2w_eval::video::mask_iou;

    #[test]
    fn segmenter_kinds_by_name() {
        assert_eq!(
            "color".parse::<SegmenterKind>().ok(),
            Some(SegmenterKind::Color)
        );
        assert_eq!(SegmenterKind::Cnn.to_string(), "cnn");
        let e = "sam"
            .parse::<SegmenterKind>()
            .map(|_| ())
            .map_err(|e| e.to_string());
        assert!(
            matches!(&e, Err(m) if m.contains("segmenter") && m.contains("cnn, color")),
            "{e:?}"
        );
    }

    /// A frame where colour cannot tell the robot apart: the background is a
    /// 2-px checker of two greys, the "robot" a solid rectangle of the
    /// lighter one at a random place.
    fn frame(rng: &mut ChaCha8Rng, h: usize, w: usize) -> (Vec<u8>, Vec<u8>) {
        let (y0, x0) = (rng.gen_range(0..h - 12), rng.gen_range(0..w - 16));
        let (rh, rw) = (rng.gen_range(6..12), rng.gen_range(8..16));
        let mut rgb = Vec::with_capacity(h * w * 3);
        let mut mask = Vec::with_capacity(h * w);
        for y in 0..h {
            for x in 0..w {
                let robot = (y0..y0 + rh).contains(&y) && (x0..x0 + rw).contains(&x);
                let light = robot || (y / 2 + x / 2) % 2 == 0;
                let v = if light { 170 } else { 90 };
                rgb.extend_from_slice(&[v, v, v]);
                mask.push(u8::from(robot));
            }
        }
        (rgb, mask)
    }

    #[test]
    fn learns_shape_where_colour_is_ambiguous_and_is_deterministic() {
        let (h, w) = (32, 48);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let train: Vec<(Vec<u8>, Vec<u8>)> = (0..24).map(|_| frame(&mut rng, h, w)).collect();
        let pairs: Vec<(&[u8], &[u8])> = train.iter().map(|(a, b)| (&a[..], &b[..])).collect();
        let opts = SegmenterOptions {
            steps: 150,
            batch: 8,
            ..SegmenterOptions::default()
        };
        let cnn = CnnSegmenter::fit_frames(&pairs, h, w, &opts).unwrap();
        let mut colour = ColorSegmenter::new(5).unwrap();
        for (rgb, m) in &train {
            colour
                .observe(&RgbFrame::from_rgb8(w, h, rgb).unwrap(), m)
                .unwrap();
        }
        let (rgb, mask) = frame(&mut rng, h, w);
        let f = RgbFrame::from_rgb8(w, h, &rgb).unwrap();
        let cnn_iou = mask_iou(&cnn.segment(&f).unwrap(), &mask).unwrap();
        let colour_iou = mask_iou(&RobotSegmenter::segment(&colour, &f).unwrap(), &mask).unwrap();
        assert!(cnn_iou > 0.8, "CNN IoU {cnn_iou} (BCE {})", cnn.final_loss);
        assert!(colour_iou < 0.5, "colour IoU {colour_iou}");
        let again = CnnSegmenter::fit_frames(&pairs, h, w, &opts).unwrap();
        assert_eq!(again.segment(&f).unwrap(), cnn.segment(&f).unwrap());
        let e = CnnSegmenter::fit_frames(&[(&rgb[..3], &mask[..])], h, w, &opts).unwrap_err();
        assert!(e.to_string().contains("frame 0: 3 RGB bytes"), "{e}");
    }
}
