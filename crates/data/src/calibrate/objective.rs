//! How well a camera explains the video.
//!
//! The found robot pixels `F_t` (see [`super::foreground`]) are where a frame
//! differs from the temporal-median background: where the robot is now and
//! usually is not, and where it usually is (the median shows it) and now is
//! not. A candidate camera predicts that from the joints: it renders every
//! link's label map `L_t`, takes each pixel's usual label `U` (the most
//! frequent over a spread of the episode's frames; 0 = background), and
//! predicts a change where one of `L_t` and `U` is the robot and the other
//! the background. Where both are the robot but different links (its parts
//! passing over each other), a change may or may not show: found and
//! predicted pixels there are left out of the score. Where the link usually
//! there is there now, no change is predicted: a found change there is a
//! miss. (Leaving those out too let a camera inside the robot's base, which
//! sees one link everywhere, score a perfect 1 on real DROID video: every
//! pixel left out.) The robot's static parts cost nothing either way.
//!
//! On a reduced grid the found pixels are fractions (the box average of the
//! full-grid masks). Predicted `P_t` and found `F_t` are compared by
//! - IoU pooled over frames (outside the robot-over-robot pixels): the
//!   objective is `1 - IoU`, what the residuals report. Measured on the
//!   synthetic world (`calibrate-study`): a Tversky index that weighed
//!   misses over false alarms, or counted found robot-over-robot pixels
//!   half missed, moved a fit started at the true camera 7-9 cm away (it
//!   rewards a closer, wider camera whose larger robot covers more); `1 -
//!   IoU` keeps it within 1.3 cm;
//! - for the coarse search only, a chamfer distance (the mean distance from
//!   each predicted pixel to the nearest found one and back, capped at a
//!   quarter of the image width) and the distance between the predicted and
//!   found pixels' centroids, smooth enough to pull a far-off camera in.

use super::appearance::{appearance_cost, histograms};
use super::background::{background_cost, reduce_rgb};
use super::foreground::Foreground;
use bridgev2w_embodiment::camera::{Camera, Intrinsics};
use bridgev2w_embodiment::masks::render_items;
use bridgev2w_embodiment::raster::Rasterizer;
use bridgev2w_embodiment::robot::Robot;
use nalgebra::Isometry3;
use rayon::prelude::*;

/// One episode's found robot pixels on one level's grid.
#[derive(Debug, Clone)]
pub(crate) struct Level {
    /// Reduction from the analysis grid.
    pub factor: usize,
    /// Width (pixels).
    pub width: usize,
    /// Height (pixels).
    pub height: usize,
    /// Per frame: the found fraction of each pixel (of its known part).
    pub found: Vec<Vec<f32>>,
    /// Per frame: the known (scored) fraction of each pixel; empty when
    /// every pixel is known (see [`super::foreground::StaticChanges`]).
    pub known: Vec<Vec<f32>>,
    /// Distance cap (pixels).
    pub cap: f32,
    /// Per frame: the gain-compensated frame on this grid (RGB8), for
    /// [`super::background`]; empty when not kept.
    pub rgb: Vec<Vec<u8>>,
}

impl Level {
    /// The level of `foreground`'s masks reduced by `factor`.
    /// `keep_rgb`: also keep the frames on this grid (for the background's
    /// consistency).
    pub fn new(foreground: &Foreground, factor: usize, keep_rgb: bool) -> Level {
        let (w, h) = (foreground.width, foreground.height);
        let frames: &[Vec<u8>] = if keep_rgb { &foreground.frames } else { &[] };
        Level {
            rgb: frames
                .par_iter()
                .map(|f| reduce_rgb(f, (w, h), factor))
                .collect(),
            ..Self::from_masks(&foreground.masks, &foreground.unknown, (w, h), factor)
        }
    }

    /// The level of 0/1 `masks` on a `w` x `h` grid reduced by `factor`,
    /// leaving out the pixels where `unknown` (per frame, or empty) is 1.
    pub fn from_masks(
        masks: &[Vec<u8>],
        unknown: &[Vec<u8>],
        (w, h): (usize, usize),
        factor: usize,
    ) -> Level {
        let (lw, lh) = (w / factor, h / factor);
        let area = (factor * factor) as f32;
        let reduce = |m: &Vec<u8>, value: u8| {
            let mut out = vec![0f32; lw * lh];
            for y in 0..lh * factor {
                for x in 0..lw * factor {
                    if m[y * w + x] == value {
                        out[(y / factor) * lw + x / factor] += 1.0 / area;
                    }
                }
            }
            out
        };
        let found = masks
            .par_iter()
            .enumerate()
            .map(|(t, m)| match unknown.get(t) {
                // Found and known.
                Some(u) => reduce(
                    &m.iter()
                        .zip(u)
                        .map(|(&f, &u)| u8::from(f != 0 && u == 0))
                        .collect(),
                    1,
                ),
                None => reduce(&m.iter().map(|&f| u8::from(f != 0)).collect(), 1),
            })
            .collect();
        let known = unknown.par_iter().map(|u| reduce(u, 0)).collect();
        Level {
            factor,
            width: lw,
            height: lh,
            found,
            known,
            cap: (lw as f32 / 4.0).max(2.0),
            rgb: Vec::new(),
        }
    }

    /// The known fractions of frame `t`'s pixels, or `None` when all are.
    pub fn known(&self, t: usize) -> Option<&[f32]> {
        self.known.get(t).map(Vec::as_slice)
    }

    /// The analysis-grid camera's intrinsics on this level's grid (exact
    /// reduction by `factor`, pixel centres kept).
    pub fn intrinsics(&self, k: &Intrinsics) -> Intrinsics {
        reduce_intrinsics(k, self.factor as f64, self.width as u32, self.height as u32)
    }
}

/// Intrinsics of a grid whose pixel is `factor` x `factor` pixels of `k`'s
/// (`factor` < 1 enlarges), `width` x `height` pixels.
pub(crate) fn reduce_intrinsics(
    k: &Intrinsics,
    factor: f64,
    width: u32,
    height: u32,
) -> Intrinsics {
    Intrinsics {
        fx: k.fx / factor,
        fy: k.fy / factor,
        cx: (k.cx + 0.5) / factor - 0.5,
        cy: (k.cy + 0.5) / factor - 0.5,
        width,
        height,
        distortion: k.distortion,
    }
}

/// Two-pass chamfer distance transform (steps 1 and sqrt 2) to the nearest
/// seed, capped at `cap`.
pub(crate) fn distance_transform(seeds: &[bool], w: usize, h: usize, cap: f32) -> Vec<f32> {
    let mut d: Vec<f32> = seeds.iter().map(|&s| if s { 0.0 } else { cap }).collect();
    let diag = std::f32::consts::SQRT_2;
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let mut v = d[i];
            if x > 0 {
                v = v.min(d[i - 1] + 1.0);
            }
            if y > 0 {
                v = v.min(d[i - w] + 1.0);
                if x > 0 {
                    v = v.min(d[i - w - 1] + diag);
                }
                if x + 1 < w {
                    v = v.min(d[i - w + 1] + diag);
                }
            }
            d[i] = v;
        }
    }
    for y in (0..h).rev() {
        for x in (0..w).rev() {
            let i = y * w + x;
            let mut v = d[i];
            if x + 1 < w {
                v = v.min(d[i + 1] + 1.0);
            }
            if y + 1 < h {
                v = v.min(d[i + w] + 1.0);
                if x + 1 < w {
                    v = v.min(d[i + w + 1] + diag);
                }
                if x > 0 {
                    v = v.min(d[i + w - 1] + diag);
                }
            }
            d[i] = v;
        }
    }
    d
}

/// Renders the robot's 0/1 masks in `frames` (indices into `poses`) through
/// `camera`.
pub(crate) fn render_masks(
    robot: &Robot,
    poses: &[Vec<Isometry3<f64>>],
    camera: &Camera,
    frames: &[usize],
) -> Vec<Vec<u8>> {
    let rasterizer = Rasterizer::new(camera);
    frames
        .par_iter()
        .map(|&t| {
            rasterizer
                .render_labels(&render_items(robot, &poses[t], true))
                .iter()
                .map(|&l| u8::from(l != 0))
                .collect()
        })
        .collect()
}

/// The most frequent value of `values` (the smallest among ties): counted
/// when all are below 64 (a robot's link labels), else sorted.
fn modal(values: &mut [u16]) -> u16 {
    if values.iter().all(|&v| v < 64) {
        let mut counts = [0u16; 64];
        for &v in values.iter() {
            counts[usize::from(v)] += 1;
        }
        let mut best = 0;
        for (l, &n) in counts.iter().enumerate() {
            if n > counts[best] {
                best = l;
            }
        }
        return best as u16;
    }
    values.sort_unstable();
    let (mut best, mut best_n) = (0u16, 0usize);
    let mut i = 0;
    while i < values.len() {
        let mut j = i;
        while j < values.len() && values[j] == values[i] {
            j += 1;
        }
        if j - i > best_n {
            (best, best_n) = (values[i], j - i);
        }
        i = j;
    }
    best
}

/// The predicted pixels of `frames` through `camera` (on the level's grid),
/// and the robot's rendered pixels there:
/// 1 where the robot appears over its usual background or leaves its usual
/// place (the rendered label differs from the pixel's usual label over
/// `mode_frames`, one of them background), [`OVER_ROBOT`] where another
/// link shows over the one usually there, else 0 (see the module
/// documentation).
pub(crate) fn predicted(
    robot: &Robot,
    poses: &[Vec<Isometry3<f64>>],
    camera: &Camera,
    frames: &[usize],
    mode_frames: &[usize],
) -> Prediction {
    let mut all: Vec<usize> = frames.iter().chain(mode_frames).copied().collect();
    all.sort_unstable();
    all.dedup();
    let rasterizer = Rasterizer::new(camera);
    let labels: Vec<Vec<u16>> = all
        .par_iter()
        .map(|&t| rasterizer.render_labels(&render_items(robot, &poses[t], true)))
        .collect();
    let at = |t: usize| all.binary_search(&t).unwrap_or(0);
    let n = labels.first().map_or(0, Vec::len);
    let mut usual = vec![0u16; n];
    usual
        .par_chunks_mut(256)
        .enumerate()
        .for_each(|(c, chunk)| {
            let mut values = Vec::with_capacity(mode_frames.len());
            for (k, u) in chunk.iter_mut().enumerate() {
                values.clear();
                values.extend(mode_frames.iter().map(|&t| labels[at(t)][c * 256 + k]));
                *u = modal(&mut values);
            }
        });
    let (change, robot) = frames
        .par_iter()
        .map(|&t| {
            let l = &labels[at(t)];
            (
                l.iter()
                    .zip(&usual)
                    .map(|(&l, &u)| change_code(l, u))
                    .collect(),
                l.iter().map(|&l| u8::from(l != 0)).collect(),
            )
        })
        .unzip();
    Prediction { change, robot }
}

/// What a camera predicts in the scored frames (see [`predicted`]).
#[derive(Debug, Clone, Default)]
pub(crate) struct Prediction {
    /// Per frame: 1 where a change shows, [`OVER_ROBOT`] where one link
    /// passes over another, else 0.
    pub change: Vec<Vec<u8>>,
    /// Per frame: 1 where the robot is rendered.
    pub robot: Vec<Vec<u8>>,
}

/// The predicted change of a pixel whose rendered label is `l` and usual
/// label `u` (0 = background): none when they agree, [`OVER_ROBOT`] when
/// two different links meet, else a change.
pub(crate) fn change_code(l: u16, u: u16) -> u8 {
    if l == u {
        // Background as usual, or the link usually there.
        0
    } else if l != 0 && u != 0 {
        OVER_ROBOT
    } else {
        1
    }
}

/// The weight of the chamfer and centroid terms of
/// [`Score::coarse_objective`].
pub(crate) const COARSE_TERMS_WEIGHT: f64 = 0.25;

/// A predicted pixel where the robot is rendered and usually is too: its
/// own parts passing over each other may or may not change the pixel.
pub(crate) const OVER_ROBOT: u8 = 2;

/// Sums over scored frames.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct Score {
    /// Soft intersection.
    pub intersection: f64,
    /// Soft union.
    pub union: f64,
    /// Predicted pixels not found.
    pub false_alarms: f64,
    /// Found pixels not predicted.
    pub misses: f64,
    /// Sum over frames of the mean chamfer distance (pixels).
    pub chamfer: f64,
    /// Sum over frames of the distance between the predicted and the found
    /// pixels' centroids (pixels; twice the cap when only one has pixels).
    pub centroid: f64,
    /// Frames with any predicted or found foreground.
    pub frames: usize,
    /// The level's distance cap (pixels).
    pub cap: f64,
    /// Summed background-consistency cost (see [`super::background`]).
    pub background: f64,
    /// Pixel-frames it sums over (0 when not computed).
    pub background_n: f64,
    /// Summed appearance cost (see [`super::appearance`]): each episode's
    /// cost times its pixel-frames.
    pub appearance: f64,
    /// Pixel-frames it weighs (0 when not computed).
    pub appearance_n: f64,
}

impl Score {
    /// Adds another episode's sums (same level grid size assumed).
    pub fn add(&mut self, other: &Score) {
        self.intersection += other.intersection;
        self.union += other.union;
        self.false_alarms += other.false_alarms;
        self.misses += other.misses;
        self.chamfer += other.chamfer;
        self.centroid += other.centroid;
        self.frames += other.frames;
        self.cap = self.cap.max(other.cap);
        self.background += other.background;
        self.background_n += other.background_n;
        self.appearance += other.appearance;
        self.appearance_n += other.appearance_n;
    }

    /// Pooled soft IoU (1 when nothing is predicted or found anywhere).
    pub fn iou(&self) -> f64 {
        if self.union > 0.0 {
            self.intersection / self.union
        } else {
            1.0
        }
    }

    /// Mean chamfer distance over frames as a fraction of the cap.
    pub fn chamfer_fraction(&self) -> f64 {
        if self.frames == 0 || self.cap <= 0.0 {
            0.0
        } else {
            self.chamfer / self.frames as f64 / self.cap
        }
    }

    /// The mean background-consistency cost (0..1; 0 when not computed).
    pub fn background_mean(&self) -> f64 {
        if self.background_n > 0.0 {
            self.background / self.background_n
        } else {
            0.0
        }
    }

    /// The mean appearance cost (0..1; 0 when not computed).
    pub fn appearance_mean(&self) -> f64 {
        if self.appearance_n > 0.0 {
            self.appearance / self.appearance_n
        } else {
            0.0
        }
    }

    /// The objective: `1 - IoU` (2 when no frame was scored).
    pub fn objective(&self) -> f64 {
        if self.frames == 0 {
            return 2.0;
        }
        1.0 - self.iou()
    }

    /// [`Score::objective`] plus a quarter of the chamfer distance and of
    /// the centroid distance, each over the cap: smooth, for the coarse
    /// search far from the answer (they would bias a fit, since found pixels
    /// miss robot parts the colour of the background).
    pub fn coarse_objective(&self) -> f64 {
        if self.frames == 0 {
            return 4.0;
        }
        let centroid = self.centroid / self.frames as f64 / self.cap.max(1e-9);
        self.objective() + COARSE_TERMS_WEIGHT * (self.chamfer_fraction() + centroid)
    }
}

/// One frame's score of predicted `m` (0/1) against found fractions `f`
/// on a `w` x `h` grid, and its IoU when either has pixels; the chamfer
/// distance only `with_chamfer` (it costs two distance transforms).
/// `known` (or `None`: all known) weighs each predicted pixel by its known
/// fraction; `f` counts only known pixels already.
pub(crate) fn frame_score(
    m: &[u8],
    f: &[f32],
    known: Option<&[f32]>,
    (w, h): (usize, usize),
    cap: f32,
    with_chamfer: bool,
) -> (Score, Option<f64>) {
    let (mut inter, mut n_m, mut n_f) = (0f64, 0f64, 0f64);
    let (mut sm, mut sf) = ([0f64; 2], [0f64; 2]);
    let mut over_robot = 0f64;
    for (i, (&a, &b)) in m.iter().zip(f).enumerate() {
        let b = f64::from(b);
        if a == OVER_ROBOT {
            over_robot += b;
            continue;
        }
        let (x, y) = ((i % w) as f64, (i / w) as f64);
        n_f += b;
        sf[0] += b * x;
        sf[1] += b * y;
        if a != 0 {
            let k = known.map_or(1.0, |k| f64::from(k[i]));
            n_m += k;
            inter += b;
            sm[0] += k * x;
            sm[1] += k * y;
        }
    }
    if n_m + n_f + over_robot <= 0.0 {
        return (Score::default(), None);
    }
    let union = n_m + n_f - inter;
    let chamfer = if with_chamfer {
        let seeds_m: Vec<bool> = m
            .iter()
            .enumerate()
            .map(|(i, &v)| v == 1 && known.is_none_or(|k| k[i] >= 0.5))
            .collect();
        let seeds_f: Vec<bool> = f
            .iter()
            .zip(m)
            .map(|(&v, &a)| v >= 0.5 && a != OVER_ROBOT)
            .collect();
        let dm = distance_transform(&seeds_m, w, h, cap);
        let df = distance_transform(&seeds_f, w, h, cap);
        let far = |x: &[bool], d: &[f32]| -> (f64, f64) {
            x.iter()
                .zip(d)
                .filter(|(&v, _)| v)
                .fold((0.0, 0.0), |(s, n), (_, &dv)| (s + f64::from(dv), n + 1.0))
        };
        let (a, na) = far(&seeds_m, &df);
        let (b, nb) = far(&seeds_f, &dm);
        (a + b) / (na + nb).max(1.0)
    } else {
        0.0
    };
    let centroid = if n_m <= 0.0 || n_f <= 0.0 {
        2.0 * f64::from(cap)
    } else {
        ((sm[0] / n_m - sf[0] / n_f).powi(2) + (sm[1] / n_m - sf[1] / n_f).powi(2)).sqrt()
    };
    (
        Score {
            intersection: inter,
            union,
            false_alarms: n_m - inter,
            misses: n_f - inter,
            chamfer,
            centroid,
            frames: 1,
            cap: f64::from(cap),
            ..Score::default()
        },
        Some(if union > 0.0 { inter / union } else { 0.0 }),
    )
}

/// The pooled [`Score`] and the per-frame IoUs of the predicted pixels of
/// `frames` against the level's found ones (chamfer only `with_chamfer`;
/// the background-consistency and appearance costs only `with_background`,
/// and only when the level keeps its frames).
pub(crate) fn score(
    level: &Level,
    frames: &[usize],
    predicted: &Prediction,
    with_chamfer: bool,
    with_background: bool,
) -> (Score, Vec<f64>) {
    let size = (level.width, level.height);
    let parts: Vec<(Score, Option<f64>)> = frames
        .par_iter()
        .zip(&predicted.change)
        .map(|(&t, m)| {
            frame_score(
                m,
                &level.found[t],
                level.known(t),
                size,
                level.cap,
                with_chamfer,
            )
        })
        .collect();
    let mut total = Score {
        cap: f64::from(level.cap),
        ..Score::default()
    };
    let mut per_frame = Vec::new();
    for (s, iou) in &parts {
        total.add(s);
        per_frame.extend(iou);
    }
    if with_background && !level.rgb.is_empty() {
        let (sum, n) = background_cost(
            &level.rgb,
            frames,
            &predicted.robot,
            level.width * level.height,
        );
        total.background = sum;
        total.background_n = n;
        let h = histograms(
            &level.rgb,
            frames,
            &predicted.robot,
            level.width * level.height,
        );
        total.appearance = appearance_cost(&h) * n;
        total.appearance_n = n;
    }
    (total, per_frame)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn distance_transform_measures_steps_and_caps() {
        let (w, h) = (7, 5);
        let mut seeds = vec![false; w * h];
        seeds[2 * w + 3] = true;
        let d = distance_transform(&seeds, w, h, 2.5);
        assert_eq!(d[2 * w + 3], 0.0);
        assert_eq!(d[2 * w + 4], 1.0);
        assert!((d[3 * w + 4] - std::f32::consts::SQRT_2).abs() < 1e-6);
        assert_eq!(d[2 * w + 6], 2.5, "3 pixels away is capped");
        assert_eq!(distance_transform(&[false; 4], 2, 2, 9.0), vec![9.0; 4]);
    }

    #[test]
    fn score_is_perfect_for_matching_masks_and_worse_when_shifted() {
        let (w, h) = (20, 10);
        let mut mask = vec![0u8; w * h];
        for y in 3..7 {
            for x in 4..9 {
                mask[y * w + x] = 1;
            }
        }
        let found: Vec<f32> = mask.iter().map(|&v| f32::from(v)).collect();
        let (s, iou) = frame_score(&mask, &found, None, (w, h), 5.0, true);
        assert_eq!(
            (s.iou(), s.chamfer, s.centroid, iou),
            (1.0, 0.0, 0.0, Some(1.0))
        );
        assert_eq!(s.objective(), 0.0);
        let shifted: Vec<u8> = (0..w * h)
            .map(|i| if i % w >= 3 { mask[i - 3] } else { 0 })
            .collect();
        let (s2, _) = frame_score(&shifted, &found, None, (w, h), 5.0, true);
        assert!((s2.iou() - 8.0 / 32.0).abs() < 1e-9, "{}", s2.iou());
        assert!((s2.centroid - 3.0).abs() < 1e-9, "{}", s2.centroid);
        assert!(s2.chamfer > 1.0 && s2.objective() > s.objective());
        assert_eq!(
            frame_score(&[0; 4], &[0.0; 4], None, (2, 2), 1.0, true).1,
            None
        );
        // A found half-pixel counts half.
        let (s3, _) = frame_score(&[1, 0], &[0.5, 0.0], None, (2, 1), 1.0, false);
        assert_eq!(
            (s3.intersection, s3.false_alarms, s3.misses),
            (0.5, 0.5, 0.0)
        );
    }

    #[test]
    fn a_view_filled_by_the_link_usually_there_predicts_no_change() {
        assert_eq!(change_code(0, 0), 0);
        assert_eq!(change_code(3, 3), 0);
        assert_eq!(change_code(3, 0), 1);
        assert_eq!(change_code(0, 3), 1);
        assert_eq!(change_code(4, 3), OVER_ROBOT);
        // A camera inside the base sees link 1 everywhere in every frame:
        // nothing is left out, so the found changes are all misses (it
        // scored a perfect IoU of 1 when such pixels were left out).
        let (w, h) = (8, 6);
        let labels = vec![1u16; w * h];
        let predicted: Vec<u8> = labels.iter().map(|&l| change_code(l, 1)).collect();
        let mut found = vec![0.0f32; w * h];
        found[..10].iter_mut().for_each(|v| *v = 1.0);
        let (s, _) = frame_score(&predicted, &found, None, (w, h), 4.0, false);
        assert_eq!(s.intersection, 0.0);
        assert!(s.union >= 10.0, "{s:?}");
        assert_eq!(s.iou(), 0.0);
    }

    #[test]
    fn unknown_pixels_cost_no_camera_anything() {
        // Found: pixels 0..4, of which 2 and 3 are unknown (static).
        let found = vec![1u8, 1, 1, 1, 0, 0, 0, 0];
        let unknown = vec![0u8, 0, 1, 1, 0, 0, 0, 0];
        let level = Level::from_masks(&[found], &[unknown], (8, 1), 1);
        assert_eq!(level.found[0], vec![1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
        let known = level.known(0);
        // Predicting the known found pixels is perfect, whatever is predicted
        // on the unknown ones.
        for m in [[1u8, 1, 0, 0, 0, 0, 0, 0], [1, 1, 1, 1, 0, 0, 0, 0]] {
            let (s, iou) = frame_score(&m, &level.found[0], known, (8, 1), 2.0, true);
            assert_eq!((s.iou(), iou), (1.0, Some(1.0)), "{m:?}");
        }
        // A known pixel predicted but not found still costs.
        let m = [1u8, 1, 0, 0, 1, 0, 0, 0];
        let (s, _) = frame_score(&m, &level.found[0], known, (8, 1), 2.0, false);
        assert!((s.iou() - 2.0 / 3.0).abs() < 1e-9, "{s:?}");
        // Box-averaged: two of a 2 x 2 cell's pixels found, one of them
        // unknown.
        let level = Level::from_masks(&[vec![1, 1, 0, 0]], &[vec![0, 1, 0, 0]], (2, 2), 2);
        assert_eq!((level.found[0][0], level.known[0][0]), (0.25, 0.75));
    }

    #[test]
    fn the_usual_label_is_the_most_frequent_one() {
        assert_eq!(modal(&mut [3, 0, 3, 2, 0, 3]), 3);
        assert_eq!(modal(&mut [1, 0, 0, 1]), 0, "ties go to the smaller label");
        assert_eq!(modal(&mut [300, 300, 2]), 300);
        assert_eq!(modal(&mut []), 0);
    }

    #[test]
    fn found_masks_are_box_averaged_onto_a_level() {
        let mask = vec![1u8, 1, 0, 0, 1, 0, 0, 0];
        let level = Level::from_masks(&[mask], &[], (4, 2), 2);
        assert_eq!((level.width, level.height), (2, 1));
        assert_eq!(level.found[0], vec![0.75, 0.0]);
    }
}
