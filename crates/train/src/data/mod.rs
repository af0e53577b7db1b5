//! The clip pipeline: one or more LeRobot datasets (`bridgev2w synth`,
//! `bridgev2w convert`, or any v2.1/v3.0 dataset with joint states and
//! calibration) held in memory (RGB frames, masks, actions), each paired with
//! its mask source (`calc` or `seg`, [`MaskKind`]) and a mixing weight.
//! An epoch is `clips_per_video` random clips of every video (the paper
//! samples 20); batches are drawn deterministically from `(seed, step)` so a
//! resumed run sees the same data.
//!
//! Here the types and what an episode holds; `open.rs` reads the sources,
//! `batches.rs` draws the clips.

use crate::{Result, TrainError};
use bridgev2w_data::clip_masks::{calc_masks, read_link_labels, seg_masks, EpisodeMasks};
use bridgev2w_data::lerobot::LeRobotDataset;
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_world_model::mask_coding::MaskCoding;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::path::{Path, PathBuf};
use tch::{Device, Kind, Tensor};

/// Where a source's masks come from.
#[derive(Debug, Clone, PartialEq)]
pub enum MaskKind {
    /// `calc`: rendered from the URDF, joint states and calibration: the
    /// dataset's `masks/episode_*.npy`, else rendered for `robot` (a built-in
    /// name or URDF path) and cached under `cache`; without either, the
    /// episodes have no masks (fine for the `mask_action = false` ablation).
    Calc {
        /// Robot to render with when the dataset carries no masks.
        robot: Option<String>,
        /// Mask cache directory.
        cache: PathBuf,
    },
    /// `seg`: PNG folders `dir/episode_XXXXXX/*.png` from a segmentation tool.
    Seg {
        /// Root of the per-episode folders.
        dir: PathBuf,
    },
}

/// One dataset of the mixture.
#[derive(Debug, Clone, PartialEq)]
pub struct SourceSpec {
    /// Dataset root.
    pub root: PathBuf,
    /// Split (all episodes when the dataset has no split column).
    pub split: String,
    /// Video key (default: the first).
    pub video_key: Option<String>,
    /// Mask source.
    pub masks: MaskKind,
    /// Mixing weight (> 0): the share of clips drawn from this source is
    /// `weight / sum(weights)`.
    pub weight: f64,
}

/// One episode in memory.
#[derive(Debug, Clone)]
pub struct Episode {
    /// Episode index in the dataset.
    pub index: i64,
    /// Frames.
    pub frames: usize,
    /// Frame height.
    pub height: usize,
    /// Frame width.
    pub width: usize,
    /// RGB8 `[T, H, W, 3]`.
    pub rgb: Vec<u8>,
    /// Masks `[T, H, W]`, when the dataset has them: 0 background, else
    /// robot; the link's label where the dataset has link labels
    /// (`labels/episode_*.npy`, see [`Episode::link_labels`]), else 1.
    pub masks: Option<Vec<u8>>,
    /// Whether `masks` holds link labels.
    pub link_labels: bool,
    /// Actions `[T, A]`.
    pub actions: Vec<f32>,
    /// Index of the source (in [`ClipDataset::sources`]) it comes from.
    pub source: usize,
}

/// A batch of clips.
#[derive(Debug)]
pub struct Batch {
    /// First frames `[B, 3, H, W]` in [-1, 1].
    pub first_frames: Tensor,
    /// Videos `[B, 3, T, H, W]` in [-1, 1].
    pub video: Tensor,
    /// Mask videos `[B, 3, T, H, W]` in [-1, 1], coded by the dataset's
    /// [`ClipDataset::mask_coding`] (zeros when the dataset has no masks).
    pub masks: Tensor,
    /// Actions `[B, T, A]`.
    pub actions: Tensor,
    /// The episodes the clips come from.
    pub episodes: Vec<i64>,
}

/// The episodes of one split, cut into clips of a fixed length and size.
#[derive(Debug, Clone)]
pub struct ClipDataset {
    /// The episodes.
    pub episodes: Vec<Episode>,
    /// Action dimension (7 per arm).
    pub action_dim: usize,
    /// Frames per clip.
    pub clip_frames: usize,
    /// Clip height (frames of another size are resized).
    pub height: usize,
    /// Clip width.
    pub width: usize,
    /// Random clips per video and epoch.
    pub clips_per_video: usize,
    /// `(name, weight)` per source.
    pub sources: Vec<(String, f64)>,
    /// How batches code the masks (the model's `mask_coding`; binary when opened).
    pub mask_coding: MaskCoding,
}

/// A well-mixed seed per (seed, epoch/step, purpose).
use bridgev2w_io::seed::derive_seed as seed_of;

/// A deterministic RNG for `(seed, step, purpose)`.
pub fn rng_for(seed: u64, step: u64, purpose: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed_of(&[seed, step, purpose]))
}

/// A deterministic 63-bit seed for `(seed, step, purpose)` (torch's generators).
pub fn seed_for(seed: u64, step: u64, purpose: u64) -> u64 {
    seed_of(&[seed, step, purpose]) >> 1
}

/// One frame of an episode that has robot masks: `(rgb8 [H, W, 3], mask
/// [H, W])` and its size.
#[derive(Debug, Clone, Copy)]
pub struct MaskedFrame<'a> {
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// Interleaved RGB.
    pub rgb: &'a [u8],
    /// Robot mask (non-zero = robot).
    pub mask: &'a [u8],
}

impl ClipDataset {
    /// Every frame of the episodes that carry robot masks, with its mask
    /// (training data for segmenters).
    pub fn masked_frames(&self) -> Vec<MaskedFrame<'_>> {
        let mut out = Vec::new();
        for e in &self.episodes {
            let Some(masks) = &e.masks else { continue };
            let px = e.width * e.height;
            for t in 0..e.frames {
                out.push(MaskedFrame {
                    width: e.width,
                    height: e.height,
                    rgb: &e.rgb[t * px * 3..(t + 1) * px * 3],
                    mask: &masks[t * px..(t + 1) * px],
                });
            }
        }
        out
    }

    /// Whether every episode has masks.
    pub fn has_masks(&self) -> bool {
        self.episodes.iter().all(|e| e.masks.is_some())
    }

    /// Per-dimension mean and standard deviation of the actions (std floored at 1e-3).
    pub fn action_stats(&self) -> (Vec<f32>, Vec<f32>) {
        let a = self.action_dim;
        let mut sum = vec![0f64; a];
        let mut sq = vec![0f64; a];
        let mut n = 0f64;
        for e in &self.episodes {
            for row in e.actions.chunks(a) {
                for (i, &v) in row.iter().enumerate() {
                    sum[i] += v as f64;
                    sq[i] += (v as f64) * (v as f64);
                }
                n += 1.0;
            }
        }
        let n = n.max(1.0);
        let mean: Vec<f32> = sum.iter().map(|s| (s / n) as f32).collect();
        let std: Vec<f32> = sum
            .iter()
            .zip(&sq)
            .map(|(s, q)| ((q / n - (s / n).powi(2)).max(0.0).sqrt().max(1e-3)) as f32)
            .collect();
        (mean, std)
    }
}

mod batches;
mod open;

#[cfg(test)]
mod tests {
    use super::open::check_mask_aspect;
    use super::*;

    fn fake(n: usize) -> ClipDataset {
        let (t, h, w) = (6usize, 4usize, 6usize);
        let episodes = (0..n)
            .map(|i| Episode {
                index: i as i64,
                frames: t,
                height: h,
                width: w,
                rgb: (0..t * h * w * 3).map(|k| (k % 251) as u8).collect(),
                masks: Some((0..t * h * w).map(|k| (k % 2) as u8).collect()),
                link_labels: false,
                actions: (0..t * 7).map(|k| k as f32).collect(),
                source: 0,
            })
            .collect();
        ClipDataset {
            episodes,
            action_dim: 7,
            clip_frames: 5,
            height: 8,
            width: 12,
            clips_per_video: 1,
            sources: vec![("fake".into(), 1.0)],
            mask_coding: MaskCoding::Binary,
        }
    }

    #[test]
    fn batches_are_deterministic_and_cover_each_epoch() {
        let d = fake(5);
        // 5 episodes, batch 2: 3 steps per epoch, every episode in each epoch.
        assert_eq!(d.steps_per_epoch(2), 3);
        let mut seen: Vec<usize> = (0..3).flat_map(|s| d.batch_episodes(7, s, 2)).collect();
        seen.truncate(5);
        seen.sort();
        assert_eq!(seen, vec![0, 1, 2, 3, 4]);
        assert_eq!(d.batch_episodes(7, 4, 2), d.batch_episodes(7, 4, 2));
        let a = d.batch(7, 4, 2, Device::Cpu).ok();
        let b = d.batch(7, 4, 2, Device::Cpu).ok();
        let (a, b) = (a.expect("batch"), b.expect("batch"));
        assert!(a.video.equal(&b.video) && a.masks.equal(&b.masks));
        assert_eq!(a.video.size(), [2, 3, 5, 8, 12]); // resized 4x6 -> 8x12
        assert_eq!(a.actions.size(), [2, 5, 7]);
        assert_eq!(a.first_frames.size(), [2, 3, 8, 12]);
        let mx = a.masks.abs().min().double_value(&[]);
        assert_eq!(mx, 1.0); // masks are exactly +-1
    }

    #[test]
    fn link_coded_batches_need_labels_and_code_each_link() {
        let mut d = fake(2);
        let err = d
            .set_mask_coding(MaskCoding::Links)
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(
            err.contains("episode 0") && err.contains("labels/episode_000000.npy"),
            "{err}"
        );
        for e in &mut d.episodes {
            // labels 0 (background), 3, 4 in turn
            e.masks = e.masks.take().map(|m| {
                m.iter()
                    .enumerate()
                    .map(|(k, &v)| if v == 0 { 0 } else { 3 + (k / 2 % 2) as u8 })
                    .collect()
            });
            e.link_labels = true;
        }
        d.set_mask_coding(MaskCoding::Links).expect("labelled");
        let b = d.clips(&[(0, 0)], Device::Cpu).expect("batch"); // [1, 3, 5, 8, 12]
        assert_eq!(b.masks.size(), [1, 3, 5, 8, 12]);
        let at = |c: i64, y: i64, x: i64| b.masks.double_value(&[0, c, 0, y, x]) as f32;
        // Source pixel (0, 0) is background, (0, 1) label 3, (0, 3) label 4,
        // each 2x2 pixels after the resize to 8x12.
        assert_eq!([at(0, 0, 0), at(1, 0, 0), at(2, 0, 0)], [-1.0, -1.0, -1.0]);
        assert_eq!([at(0, 0, 2), at(2, 0, 2)], [1.0, 1.0]);
        assert!((at(1, 0, 2) - (-1.0 + 6.0 / 15.0)).abs() < 1e-6);
        assert_eq!([at(0, 0, 6), at(2, 0, 6)], [1.0, -1.0]);
        assert!((at(1, 0, 6) - (-1.0 + 8.0 / 15.0)).abs() < 1e-6);
        // The binary coding of the same labels is the silhouette on 3 channels.
        d.set_mask_coding(MaskCoding::Binary).expect("binary");
        let b = d.clips(&[(0, 0)], Device::Cpu).expect("batch");
        for c in 0..3 {
            assert_eq!(b.masks.double_value(&[0, c, 0, 0, 6]), 1.0);
        }
    }

    #[test]
    fn an_epoch_holds_clips_per_video_clips_of_every_video() {
        let mut d = fake(5);
        d.clips_per_video = 3;
        assert_eq!(d.steps_per_epoch(2), 8); // 15 clips
        let slots = d.epoch_slots(1, 0, 15);
        for e in 0..5 {
            assert_eq!(slots.iter().filter(|&&s| s == e).count(), 3);
        }
        assert_ne!(slots, d.epoch_slots(1, 1, 15), "a new order every epoch");
        // The batches of one epoch are consecutive slices of its slots.
        let b: Vec<usize> = (0..7).flat_map(|s| d.batch_episodes(1, s, 2)).collect();
        assert_eq!(b, slots[..14].to_vec());
    }

    #[test]
    fn masks_of_another_aspect_ratio_are_refused_not_stretched() {
        let masks = |height, width| EpisodeMasks {
            frames: 1,
            height,
            width,
            data: vec![0; height * width],
        };
        // Same size, or a half-resolution segmentation: resized.
        check_mask_aspect(&masks(64, 96), (64, 96)).expect("resized");
        check_mask_aspect(&masks(32, 48), (64, 96)).expect("resized");
        // Stored [T, W, H].
        let e = check_mask_aspect(&masks(96, 64), (64, 96)).expect_err("refused");
        assert!(e.contains("96x64") && e.contains("[T, W, H]"), "{e}");
        let e = check_mask_aspect(&masks(64, 64), (64, 96)).expect_err("refused");
        assert!(
            e.contains("aspect ratio") && !e.contains("[T, W, H]"),
            "{e}"
        );
    }
}
