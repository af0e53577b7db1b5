//! The clip pipeline: one or more LeRobot datasets (`bridgev2w synth`,
//! `bridgev2w convert`, or any v2.1/v3.0 dataset with joint states and
//! calibration) held in memory (RGB frames, masks, actions), each paired with
//! its mask source (`calc` or `seg`, [`MaskKind`]) and a mixing weight.
//! An epoch is `clips_per_video` random clips of every video (the paper
//! samples 20); batches are drawn deterministically from `(seed, step)` so a
//! resumed run sees the same data.

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

    /// A single source with `calc` masks (stored ones only) and one clip per
    /// video and epoch.
    pub fn open(
        root: &Path,
        split: &str,
        video_key: Option<&str>,
        clip_frames: usize,
        height: usize,
        width: usize,
    ) -> Result<Self> {
        let spec = SourceSpec {
            root: root.to_path_buf(),
            split: split.to_string(),
            video_key: video_key.map(str::to_string),
            masks: MaskKind::Calc {
                robot: None,
                cache: root.join(".bridgev2w-mask-cache"),
            },
            weight: 1.0,
        };
        Self::open_sources(&[spec], clip_frames, height, width, 1)
    }

    /// Reads every source's episodes (see [`SourceSpec`]); all sources must
    /// share one action size.
    pub fn open_sources(
        specs: &[SourceSpec],
        clip_frames: usize,
        height: usize,
        width: usize,
        clips_per_video: usize,
    ) -> Result<Self> {
        if specs.is_empty() {
            return Err(TrainError::input("data", "no dataset given"));
        }
        if clips_per_video == 0 {
            return Err(TrainError::input(
                "data.clips_per_video",
                "0: expected >= 1",
            ));
        }
        let mut episodes = Vec::new();
        let mut sources = Vec::new();
        let mut action_dim: Option<(usize, String)> = None;
        for (s, spec) in specs.iter().enumerate() {
            if !(spec.weight.is_finite() && spec.weight > 0.0) {
                return Err(TrainError::input(
                    format!("dataset {}", spec.root.display()),
                    format!("weight {}: expected a positive number", spec.weight),
                ));
            }
            let (eps, a) = Self::read_source(spec, s, clip_frames)?;
            let name = spec.root.display().to_string();
            match &action_dim {
                Some((d, first)) if *d != a => {
                    return Err(TrainError::input(
                        format!("dataset {name}"),
                        format!("action size {a} differs from {first}'s {d}: mixed sources need one action layout"),
                    ))
                }
                Some(_) => {}
                None => action_dim = Some((a, name.clone())),
            }
            episodes.extend(eps);
            sources.push((name, spec.weight));
        }
        Ok(Self {
            episodes,
            action_dim: action_dim.map_or(0, |(a, _)| a),
            clip_frames,
            height,
            width,
            clips_per_video,
            sources,
            mask_coding: MaskCoding::Binary,
        })
    }

    /// Sets the batches' mask coding; [`MaskCoding::Links`] needs link labels
    /// in every episode (an error names the first dataset without them).
    pub fn set_mask_coding(&mut self, coding: MaskCoding) -> Result<()> {
        if coding == MaskCoding::Links {
            if let Some(e) = self.episodes.iter().find(|e| !e.link_labels) {
                let (name, _) = &self.sources[e.source];
                return Err(TrainError::input(
                    format!("dataset {name} episode {}", e.index),
                    format!("no link labels (labels/episode_{:06}.npy, which `bridgev2w synth` writes): model.mask_coding = \"links\" needs them; use \"binary\"", e.index),
                ));
            }
        }
        self.mask_coding = coding;
        Ok(())
    }

    /// The episodes of one source and their action size.
    fn read_source(
        spec: &SourceSpec,
        source: usize,
        clip_frames: usize,
    ) -> Result<(Vec<Episode>, usize)> {
        let (root, split, video_key) = (
            spec.root.as_path(),
            spec.split.as_str(),
            spec.video_key.as_deref(),
        );
        let embodiment = match &spec.masks {
            MaskKind::Calc { robot: Some(r), .. } => Some(
                Embodiment::load(r, &Default::default(), &[], &[])
                    .map_err(|e| TrainError::input("data.robot", e.to_string()))?,
            ),
            _ => None,
        };
        let ds = LeRobotDataset::open(root)
            .map_err(|e| TrainError::input(format!("dataset {}", root.display()), e.to_string()))?;
        let key = match video_key {
            Some(k) => k.to_owned(),
            None => ds.video_keys.first().cloned().ok_or_else(|| {
                TrainError::input(format!("dataset {}", root.display()), "no video keys")
            })?,
        };
        let has_splits = ds.episodes.iter().any(|e| e.split.is_some());
        let chosen: Vec<i64> = ds
            .episodes
            .iter()
            .filter(|e| !has_splits || e.split.as_deref() == Some(split))
            .map(|e| e.episode_index)
            .collect();
        if chosen.is_empty() {
            return Err(TrainError::input(
                format!("dataset {}", root.display()),
                format!("no episodes in split {split:?}"),
            ));
        }
        let derr = |e: bridgev2w_data::lerobot::DatasetError| {
            TrainError::input(format!("dataset {}", root.display()), e.to_string())
        };
        let mut episodes = Vec::with_capacity(chosen.len());
        let mut action_dim = None;
        for idx in chosen {
            let rows = ds.read_episode(idx).map_err(derr)?.frames;
            let frames = ds.read_video(idx, &key).map_err(derr)?;
            let t = frames.len();
            if t < clip_frames {
                return Err(TrainError::input(
                    format!("dataset {} episode {idx}", root.display()),
                    format!("{t} frames, shorter than a clip of {clip_frames}"),
                ));
            }
            let (h, w) = match video_shape(&ds, &key) {
                Some(hw) => hw,
                None => {
                    return Err(TrainError::input(
                        format!("dataset {}", root.display()),
                        format!("no shape for video {key:?} in meta/info.json"),
                    ))
                }
            };
            let masks: Option<EpisodeMasks> = match &spec.masks {
                MaskKind::Calc { robot, cache } => {
                    let stored = root.join(format!("masks/episode_{idx:06}.npy")).is_file();
                    if stored || robot.is_some() {
                        Some(
                            calc_masks(&ds, idx, &key, (t, w, h), embodiment.as_ref(), cache)
                                .map_err(derr)?,
                        )
                    } else {
                        None
                    }
                }
                MaskKind::Seg { dir } => Some(seg_masks(dir, idx, t).map_err(derr)?),
            };
            let mut rgb = Vec::with_capacity(t * h * w * 3);
            for (i, f) in frames.iter().enumerate() {
                if f.len() != h * w * 3 {
                    return Err(TrainError::input(
                        format!("dataset {} episode {idx} frame {i}", root.display()),
                        format!("{} bytes, expected {h}x{w}x3", f.len()),
                    ));
                }
                rgb.extend_from_slice(f);
            }
            // The dataset's link labels, where it has them, in place of 0/1.
            let (masks, link_labels) = match (masks, &spec.masks) {
                (Some(m), MaskKind::Calc { .. }) => {
                    match read_link_labels(&ds, idx, &m).map_err(derr)? {
                        Some(data) => (Some(EpisodeMasks { data, ..m }), true),
                        None => (Some(m), false),
                    }
                }
                (m, _) => (m, false),
            };
            let masks = match masks {
                Some(m) => {
                    if m.frames != t {
                        return Err(TrainError::input(
                            format!("dataset {} episode {idx} masks", root.display()),
                            format!("{} mask frames for {t} video frames", m.frames),
                        ));
                    }
                    check_mask_aspect(&m, (h, w)).map_err(|message| {
                        TrainError::input(
                            format!("dataset {} episode {idx} masks", root.display()),
                            message,
                        )
                    })?;
                    Some(resize_masks_nearest(&m, (h, w)))
                }
                None => None,
            };
            let a = rows.first().map(|r| r.action.len()).unwrap_or(0);
            if a == 0 || rows.len() != t || rows.iter().any(|r| r.action.len() != a) {
                return Err(TrainError::input(
                    format!("dataset {} episode {idx}", root.display()),
                    format!(
                        "{} action rows for {t} frames (expected one non-empty action per frame, one size)",
                        rows.len()
                    ),
                ));
            }
            if *action_dim.get_or_insert(a) != a {
                return Err(TrainError::input(
                    format!("dataset {} episode {idx}", root.display()),
                    format!("action size {a} differs from other episodes'"),
                ));
            }
            episodes.push(Episode {
                index: idx,
                frames: t,
                height: h,
                width: w,
                rgb,
                masks,
                link_labels,
                actions: rows.iter().flat_map(|r| r.action.iter().copied()).collect(),
                source,
            });
        }
        Ok((episodes, action_dim.unwrap_or(0)))
    }

    /// Whether every episode has masks.
    pub fn has_masks(&self) -> bool {
        self.episodes.iter().all(|e| e.masks.is_some())
    }

    /// Steps per epoch at `batch_size`: `clips_per_video` clips of every video.
    pub fn steps_per_epoch(&self, batch_size: usize) -> usize {
        (self.episodes.len() * self.clips_per_video)
            .div_ceil(batch_size.max(1))
            .max(1)
    }

    /// The episode of every clip slot of `epoch`. One source: each episode
    /// `clips_per_video` times, shuffled. Several: each slot draws a source
    /// by weight, then the next episode of that source's own shuffled cycle
    /// (so every source is covered evenly within its share).
    pub fn epoch_slots(&self, seed: u64, epoch: u64, slots: usize) -> Vec<usize> {
        let mut rng = rng_for(seed, epoch, 1);
        let mut cycles: Vec<Vec<usize>> = vec![Vec::new(); self.sources.len()];
        for (i, e) in self.episodes.iter().enumerate() {
            for _ in 0..self.clips_per_video {
                cycles[e.source].push(i);
            }
        }
        for c in &mut cycles {
            c.shuffle(&mut rng);
        }
        if self.sources.len() == 1 {
            let c = &cycles[0];
            return (0..slots).map(|k| c[k % c.len()]).collect();
        }
        let total: f64 = self.sources.iter().map(|s| s.1).sum();
        let mut next = vec![0usize; cycles.len()];
        (0..slots)
            .map(|_| {
                let mut u = rng.gen::<f64>() * total;
                let mut s = 0;
                while s + 1 < self.sources.len() && (u >= self.sources[s].1 || cycles[s].is_empty())
                {
                    u -= self.sources[s].1;
                    s += 1;
                }
                let c = &cycles[s];
                let e = c[next[s] % c.len()];
                next[s] += 1;
                e
            })
            .collect()
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

    /// The episodes of step `step`: a permutation per epoch from `(seed, epoch)`,
    /// consecutive `batch_size` slices of it (wrapping).
    pub fn batch_episodes(&self, seed: u64, step: usize, batch_size: usize) -> Vec<usize> {
        let spe = self.steps_per_epoch(batch_size);
        let (epoch, within) = (step / spe, step % spe);
        let order = self.epoch_slots(seed, epoch as u64, spe * batch_size);
        (0..batch_size)
            .map(|j| order[within * batch_size + j])
            .collect()
    }

    /// The batch of step `step` on `device`: episodes from [`Self::batch_episodes`],
    /// clip starts from `(seed, step)`.
    pub fn batch(
        &self,
        seed: u64,
        step: usize,
        batch_size: usize,
        device: Device,
    ) -> Result<Batch> {
        self.clips(&self.batch_clips(seed, step, batch_size), device)
    }

    /// The clips `(episode, start frame)` of step `step`'s batch.
    pub fn batch_clips(&self, seed: u64, step: usize, batch_size: usize) -> Vec<(usize, usize)> {
        let eps = self.batch_episodes(seed, step, batch_size);
        let mut rng = rng_for(seed, step as u64, 2);
        eps.iter()
            .map(|&i| {
                (
                    i,
                    rng.gen_range(0..=self.episodes[i].frames - self.clip_frames),
                )
            })
            .collect()
    }

    /// A batch of the clips `(episode, start frame)` on `device`.
    pub fn clips(&self, clips: &[(usize, usize)], device: Device) -> Result<Batch> {
        let (tf, h, w) = (
            self.clip_frames as i64,
            self.height as i64,
            self.width as i64,
        );
        let mut videos = Vec::new();
        let mut masks = Vec::new();
        let mut actions = Vec::new();
        for &(i, start) in clips {
            let e = self.episodes.get(i).ok_or_else(|| {
                TrainError::input("clip", format!("episode {i} of {}", self.episodes.len()))
            })?;
            if start + self.clip_frames > e.frames {
                return Err(TrainError::input(
                    format!("episode {} clip", e.index),
                    format!(
                        "start {start} + {} frames past its {} frames",
                        self.clip_frames, e.frames
                    ),
                ));
            }
            let (eh, ew) = (e.height as i64, e.width as i64);
            let px = eh * ew;
            let rgb =
                &e.rgb[start * (px as usize) * 3..(start + self.clip_frames) * (px as usize) * 3];
            let v = Tensor::from_slice(rgb)
                .reshape([tf, eh, ew, 3])
                .permute([0, 3, 1, 2]) // [T, 3, H, W]
                .to_kind(Kind::Float)
                / 127.5
                - 1.0;
            let v = if (eh, ew) != (h, w) {
                v.upsample_bilinear2d([h, w], false, None, None)
            } else {
                v
            };
            videos.push(v.permute([1, 0, 2, 3])); // [3, T, H, W]
            let m = match &e.masks {
                Some(data) => {
                    let m = Tensor::from_slice(
                        &data[start * px as usize..(start + self.clip_frames) * px as usize],
                    )
                    .reshape([tf, 1, eh, ew])
                    .to_kind(Kind::Float);
                    let m = if (eh, ew) != (h, w) {
                        m.upsample_nearest2d([h, w], None, None)
                    } else {
                        m
                    };
                    // labels [T, 1, H, W] -> coded channels [T, 3, H, W] -> [3, T, H, W]
                    self.mask_coding
                        .code(&m, 1)
                        .permute([1, 0, 2, 3])
                        .contiguous()
                }
                None => Tensor::zeros([3, tf, h, w], (Kind::Float, Device::Cpu)),
            };
            masks.push(m);
            let a = self.action_dim;
            actions.push(
                Tensor::from_slice(&e.actions[start * a..(start + self.clip_frames) * a])
                    .reshape([tf, a as i64]),
            );
        }
        let video = Tensor::stack(&videos, 0).to_device(device); // [B, 3, T, H, W]
        Ok(Batch {
            first_frames: video.select(2, 0),
            video,
            masks: Tensor::stack(&masks, 0).to_device(device),
            actions: Tensor::stack(&actions, 0).to_device(device),
            episodes: clips.iter().map(|&(i, _)| self.episodes[i].index).collect(),
        })
    }
}

/// Masks of another size than the video's `(h, w)` are resized, but only
/// when they have its aspect ratio (within 2 %): anything else (e.g. masks
/// stored `[T, W, H]`) would be stretched into garbage.
fn check_mask_aspect(m: &EpisodeMasks, (h, w): (usize, usize)) -> std::result::Result<(), String> {
    if (m.height, m.width) == (h, w) {
        return Ok(());
    }
    let mask = m.width as f64 / m.height as f64;
    let video = w as f64 / h as f64;
    if (mask / video - 1.0).abs() <= 0.02 {
        return Ok(());
    }
    // Transposed: the mask's H/W is the video's W/H.
    let hint = if m.height * h == m.width * w {
        " (stored [T, W, H]? expected [T, H, W])"
    } else {
        ""
    };
    Err(format!(
        "{}x{} (HxW) for {h}x{w} video frames{hint}: masks of another aspect ratio cannot be resized to the video",
        m.height, m.width
    ))
}

/// Nearest-neighbour resize of every mask frame to `(h, w)` (masks from a
/// segmentation tool may come at another resolution than the video).
fn resize_masks_nearest(m: &EpisodeMasks, (h, w): (usize, usize)) -> Vec<u8> {
    if (m.height, m.width) == (h, w) {
        return m.data.clone();
    }
    let mut out = Vec::with_capacity(m.frames * h * w);
    for f in 0..m.frames {
        let frame = &m.data[f * m.height * m.width..(f + 1) * m.height * m.width];
        for y in 0..h {
            let sy = ((y as f64 + 0.5) * m.height as f64 / h as f64) as usize;
            for x in 0..w {
                let sx = ((x as f64 + 0.5) * m.width as f64 / w as f64) as usize;
                out.push(frame[sy.min(m.height - 1) * m.width + sx.min(m.width - 1)]);
            }
        }
    }
    out
}

fn video_shape(ds: &LeRobotDataset, key: &str) -> Option<(usize, usize)> {
    let shape = ds
        .info
        .get("features")?
        .get(key)?
        .get("shape")?
        .as_array()?;
    let dims: Vec<usize> = shape
        .iter()
        .filter_map(|v| v.as_u64().map(|x| x as usize))
        .collect();
    let names = ds.info["features"][key]
        .get("names")
        .and_then(|n| n.as_array())
        .map(|n| n.iter().filter_map(|x| x.as_str()).collect::<Vec<_>>());
    match (dims.as_slice(), names.as_deref()) {
        ([c, h, w], Some(["channels", ..])) if *c == 3 => Some((*h, *w)),
        ([h, w, 3], _) => Some((*h, *w)),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
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
