//! The robot's pixels in a fixed camera's video, found from the video alone:
//! what moves against a static background.
//!
//! 1. Background: the per-pixel, per-channel temporal median of the frames,
//!    after a per-frame gain (the median ratio of a frame's brightness to the
//!    background's) is divided out, so auto-exposure does not light up the
//!    whole frame.
//! 2. Difference: a pixel is foreground in a frame when its largest channel
//!    difference to the background exceeds `max(min_threshold,
//!    noise_factor x the median difference over all pixels and frames)`.
//! 3. Cleanup: a 3 x 3 majority filter removes isolated pixels and fills
//!    pinholes.
//!
//! 4. Optionally ([`StaticChanges::LeaveOut`]), a found pixel whose colour
//!    stays put over the frames around it (within half the threshold over
//!    `static_window` frames each side) is marked *unknown*: a moved object
//!    at rest in its new place, the place it left, a slow exposure drift, or
//!    the robot itself at rest. Unknown pixels are left out of the score, of
//!    the found and the predicted pixels alike, so they cost no camera
//!    anything; what moves (the robot, and the shadows it drags) is scored.
//!
//! A pixel the robot covers in most frames is part of the median, so there
//! the robot's *absence* is foreground; the calibration's model of the
//! foreground accounts for that (see `objective`). The same pass measures
//! whether the camera is fixed at all: on a coarse grid (about 80 pixels
//! wide) the median difference to the background (`noise_level`) and the
//! fraction of pixels that differ from it in most frames
//! (`unstable_fraction`); a camera that moves changes most of its image.

use super::episode::EpisodeData;
use rayon::prelude::*;
use serde::Serialize;

/// What the score does with found pixels that do not move (see the module
/// documentation, step 4).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum StaticChanges {
    /// Every found pixel is scored.
    #[default]
    Score,
    /// Found pixels whose colour stays put around their frame are left out
    /// of the score.
    LeaveOut,
}

impl StaticChanges {
    /// The names [`std::str::FromStr`] takes.
    pub const NAMES: [&'static str; 2] = ["score", "leave-out"];
}

impl std::str::FromStr for StaticChanges {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "score" => Ok(Self::Score),
            "leave-out" => Ok(Self::LeaveOut),
            other => Err(format!(
                "unknown static-changes mode {other:?}: expected one of {}",
                Self::NAMES.join(", ")
            )),
        }
    }
}

impl std::fmt::Display for StaticChanges {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Score => "score",
            Self::LeaveOut => "leave-out",
        })
    }
}

/// Options of [`find_foreground`].
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ForegroundOptions {
    /// The smallest difference (0..255, largest channel) that counts as
    /// foreground.
    pub min_threshold: f64,
    /// The threshold is at least this many times the median difference.
    pub noise_factor: f64,
    /// A frame counts as showing the robot when at least this fraction of
    /// its pixels is foreground.
    pub min_robot_pixels_fraction: f64,
    /// Found pixels that do not move: scored, or left out.
    pub static_changes: StaticChanges,
    /// Frames on each side of a frame over which a found pixel must keep
    /// its colour to count as static.
    pub static_window: usize,
}

impl Default for ForegroundOptions {
    fn default() -> Self {
        Self {
            min_threshold: 20.0,
            noise_factor: 4.0,
            min_robot_pixels_fraction: 0.002,
            static_changes: StaticChanges::Score,
            static_window: 2,
        }
    }
}

/// What [`find_foreground`] measured.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ForegroundStats {
    /// Frames analysed.
    pub frames: usize,
    /// Frames with at least the minimum of foreground pixels.
    pub frames_with_robot: usize,
    /// `frames_with_robot / frames`.
    pub robot_frame_fraction: f64,
    /// Median over frames of the fraction of foreground pixels.
    pub median_foreground_fraction: f64,
    /// The difference threshold used (0..255).
    pub threshold: f64,
    /// Median difference to the background over pixels and frames on the
    /// coarse grid (0..255): about 1-3 for DROID's fixed cameras, 8-50 for
    /// its wrist cameras.
    pub noise_level: f64,
    /// Fraction of coarse-grid pixels whose median difference to the
    /// background exceeds 4: about 0.1-0.35 for DROID's fixed cameras, 0.7
    /// and more for its wrist cameras.
    pub unstable_fraction: f64,
    /// Fraction of the found pixels left out as static (0 unless
    /// [`StaticChanges::LeaveOut`]).
    pub static_fraction: f64,
}

/// Foreground masks of one episode (analysis grid).
#[derive(Debug, Clone)]
pub struct Foreground {
    /// Width (pixels).
    pub width: usize,
    /// Height (pixels).
    pub height: usize,
    /// Per frame, 0/1 row-major.
    pub masks: Vec<Vec<u8>>,
    /// Per frame, 1 where a found pixel is static and left out of the score
    /// (see [`StaticChanges`]); empty when none is.
    pub unknown: Vec<Vec<u8>>,
    /// The background (RGB8).
    pub background: Vec<u8>,
    /// The frames after gain compensation (RGB8), what the masks were
    /// found in.
    pub frames: Vec<Vec<u8>>,
    /// Measurements.
    pub stats: ForegroundStats,
}

/// Median of `values` (upper median for an even count); 0 when empty.
fn median_u8(values: &mut [u8]) -> u8 {
    if values.is_empty() {
        return 0;
    }
    let mid = values.len() / 2;
    *values.select_nth_unstable(mid).1
}

fn median_f32(values: &mut [f32]) -> f32 {
    if values.is_empty() {
        return 0.0;
    }
    let mid = values.len() / 2;
    *values.select_nth_unstable_by(mid, f32::total_cmp).1
}

/// The per-value temporal median of equally long buffers.
fn temporal_median(frames: &[Vec<u8>]) -> Vec<u8> {
    let n = frames.first().map_or(0, Vec::len);
    let mut out = vec![0u8; n];
    out.par_chunks_mut(1024).enumerate().for_each(|(c, chunk)| {
        let mut column = vec![0u8; frames.len()];
        for (k, o) in chunk.iter_mut().enumerate() {
            let i = c * 1024 + k;
            for (v, f) in column.iter_mut().zip(frames) {
                *v = f[i];
            }
            *o = median_u8(&mut column);
        }
    });
    out
}

/// Per-frame brightness gain relative to `background` (median ratio of
/// channel sums over pixels).
fn gain(frame: &[u8], background: &[u8]) -> f32 {
    let mut ratios: Vec<f32> = frame
        .chunks_exact(3)
        .zip(background.chunks_exact(3))
        .map(|(a, b)| {
            let la: f32 = a.iter().map(|&v| f32::from(v)).sum();
            let lb: f32 = b.iter().map(|&v| f32::from(v)).sum();
            (la + 3.0) / (lb + 3.0)
        })
        .collect();
    median_f32(&mut ratios)
}

/// The largest channel difference per pixel.
fn difference(frame: &[u8], background: &[u8]) -> Vec<u8> {
    frame
        .chunks_exact(3)
        .zip(background.chunks_exact(3))
        .map(|(a, b)| (0..3).map(|c| a[c].abs_diff(b[c])).max().unwrap_or(0))
        .collect()
}

/// 3 x 3 majority filter of a 0/1 mask (pixels outside count as 0).
pub(crate) fn majority(mask: &[u8], w: usize, h: usize) -> Vec<u8> {
    let mut out = vec![0u8; mask.len()];
    for y in 0..h {
        for x in 0..w {
            let mut n = 0;
            for yy in y.saturating_sub(1)..(y + 2).min(h) {
                for xx in x.saturating_sub(1)..(x + 2).min(w) {
                    n += usize::from(mask[yy * w + xx]);
                }
            }
            out[y * w + x] = u8::from(n >= 5);
        }
    }
    out
}

/// Mean over `factor` x `factor` blocks of an RGB8 frame, as f32.
fn coarse_rgb(frame: &[u8], w: usize, factor: usize) -> Vec<f32> {
    let (cw, ch) = (w / factor, frame.len() / 3 / w / factor);
    let mut out = vec![0f32; cw * ch * 3];
    let area = (factor * factor) as f32;
    for y in 0..ch * factor {
        for x in 0..cw * factor {
            let i = (y * w + x) * 3;
            let o = ((y / factor) * cw + x / factor) * 3;
            for c in 0..3 {
                out[o + c] += f32::from(frame[i + c]) / area;
            }
        }
    }
    out
}

/// `noise_level` and `unstable_fraction` (see [`ForegroundStats`]) of
/// gain-compensated frames, on a grid about 80 pixels wide.
fn fixed_camera_stats(frames: &[Vec<u8>], w: usize) -> (f64, f64) {
    let factor = ((w as f64 / 80.0).round() as usize).max(1);
    let coarse: Vec<Vec<f32>> = frames
        .par_iter()
        .map(|f| coarse_rgb(f, w, factor))
        .collect();
    let n = coarse.first().map_or(0, Vec::len);
    let pixels = n / 3;
    if pixels == 0 || coarse.is_empty() {
        return (0.0, 0.0);
    }
    let mut background = vec![0f32; n];
    let mut column = vec![0f32; coarse.len()];
    for (i, b) in background.iter_mut().enumerate() {
        for (v, f) in column.iter_mut().zip(&coarse) {
            *v = f[i];
        }
        *b = median_f32(&mut column);
    }
    // Per frame and pixel: the largest channel difference.
    let diffs: Vec<Vec<f32>> = coarse
        .iter()
        .map(|f| {
            (0..pixels)
                .map(|p| {
                    (0..3)
                        .map(|c| (f[3 * p + c] - background[3 * p + c]).abs())
                        .fold(0.0, f32::max)
                })
                .collect()
        })
        .collect();
    let mut all: Vec<f32> = diffs.iter().flatten().copied().collect();
    let noise = median_f32(&mut all);
    let mut unstable = 0usize;
    for p in 0..pixels {
        for (v, d) in column.iter_mut().zip(&diffs) {
            *v = d[p];
        }
        if median_f32(&mut column) > 4.0 {
            unstable += 1;
        }
    }
    (f64::from(noise), unstable as f64 / pixels as f64)
}

/// Finds the robot's pixels in every frame of `episode` (see the module
/// documentation).
pub fn find_foreground(episode: &EpisodeData, options: &ForegroundOptions) -> Foreground {
    let (w, h) = (episode.width, episode.height);
    let first = temporal_median(&episode.frames);
    // Gain-compensated frames (only where the gain differs by over 1 %).
    let frames: Vec<Vec<u8>> = episode
        .frames
        .par_iter()
        .map(|f| {
            let g = gain(f, &first);
            if (g - 1.0).abs() <= 0.01 || !g.is_finite() || g <= 0.0 {
                f.clone()
            } else {
                f.iter()
                    .map(|&v| (f32::from(v) / g).round().clamp(0.0, 255.0) as u8)
                    .collect()
            }
        })
        .collect();
    let background = temporal_median(&frames);
    let diffs: Vec<Vec<u8>> = frames
        .par_iter()
        .map(|f| difference(f, &background))
        .collect();
    let mut histogram = [0usize; 256];
    for d in diffs.iter().flatten() {
        histogram[usize::from(*d)] += 1;
    }
    let total: usize = histogram.iter().sum();
    let mut acc = 0;
    let mut median_diff = 0;
    for (v, &c) in histogram.iter().enumerate() {
        acc += c;
        if 2 * acc >= total {
            median_diff = v;
            break;
        }
    }
    let threshold = options
        .min_threshold
        .max(options.noise_factor * median_diff as f64);
    let masks: Vec<Vec<u8>> = diffs
        .par_iter()
        .map(|d| {
            let raw: Vec<u8> = d
                .iter()
                .map(|&v| u8::from(f64::from(v) > threshold))
                .collect();
            majority(&raw, w, h)
        })
        .collect();
    let area = (w * h).max(1) as f64;
    let mut fractions: Vec<f32> = masks
        .iter()
        .map(|m| (m.iter().map(|&v| usize::from(v)).sum::<usize>() as f64 / area) as f32)
        .collect();
    let frames_with_robot = fractions
        .iter()
        .filter(|&&f| f64::from(f) >= options.min_robot_pixels_fraction)
        .count();
    let (noise_level, unstable_fraction) = fixed_camera_stats(&frames, w);
    let unknown = match options.static_changes {
        StaticChanges::Score => Vec::new(),
        StaticChanges::LeaveOut => {
            static_pixels(&frames, &masks, options.static_window, threshold / 2.0)
        }
    };
    let found_total: usize = masks.iter().flatten().map(|&v| usize::from(v)).sum();
    let static_total: usize = unknown.iter().flatten().map(|&v| usize::from(v)).sum();
    let n = masks.len();
    Foreground {
        width: w,
        height: h,
        masks,
        unknown,
        background,
        frames,
        stats: ForegroundStats {
            frames: n,
            frames_with_robot,
            robot_frame_fraction: frames_with_robot as f64 / n.max(1) as f64,
            median_foreground_fraction: f64::from(median_f32(&mut fractions)),
            threshold,
            noise_level,
            unstable_fraction,
            static_fraction: static_total as f64 / found_total.max(1) as f64,
        },
    }
}

/// Per frame, 1 where a found pixel (`masks`) keeps its colour (largest
/// channel difference at most `tolerance`) in every frame within `window`
/// frames on each side (those that exist; at least `window` of them).
fn static_pixels(
    frames: &[Vec<u8>],
    masks: &[Vec<u8>],
    window: usize,
    tolerance: f64,
) -> Vec<Vec<u8>> {
    let n = frames.len();
    (0..n)
        .into_par_iter()
        .map(|t| {
            let others: Vec<&Vec<u8>> = (t.saturating_sub(window)..(t + window + 1).min(n))
                .filter(|&s| s != t)
                .map(|s| &frames[s])
                .collect();
            let frame = &frames[t];
            masks[t]
                .iter()
                .enumerate()
                .map(|(p, &m)| {
                    if m == 0 || others.len() < window.max(1) {
                        return 0;
                    }
                    let still = others.iter().all(|o| {
                        (0..3).all(|c| {
                            f64::from(o[3 * p + c].abs_diff(frame[3 * p + c])) <= tolerance
                        })
                    });
                    u8::from(still)
                })
                .collect()
        })
        .collect()
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn episode(frames: Vec<Vec<u8>>, w: usize, h: usize) -> EpisodeData {
        let n = frames.len();
        EpisodeData::new(
            "t",
            (w as u32, h as u32),
            1,
            (w, h),
            frames,
            vec![vec![0.0]; n],
        )
        .unwrap()
    }

    #[test]
    fn a_moving_square_is_found_against_a_static_textured_background() {
        let (w, h) = (64, 48);
        let background: Vec<u8> = (0..w * h * 3).map(|i| ((i * 37) % 97) as u8 + 60).collect();
        let frames: Vec<Vec<u8>> = (0..20)
            .map(|t| {
                let mut f = background.clone();
                for y in 10..20 {
                    for x in (2 * t)..(2 * t + 10) {
                        f[(y * w + x) * 3..(y * w + x) * 3 + 3].copy_from_slice(&[250, 250, 250]);
                    }
                }
                f
            })
            .collect();
        let fg = find_foreground(&episode(frames, w, h), &ForegroundOptions::default());
        for t in 0..20 {
            let m = &fg.masks[t];
            let inside = m[15 * w + 2 * t + 5];
            let outside = m[30 * w + 5];
            assert_eq!((inside, outside), (1, 0), "frame {t}");
            let count: usize = m.iter().map(|&v| usize::from(v)).sum();
            assert!((80..=100).contains(&count), "frame {t}: {count} pixels");
        }
        assert_eq!(fg.stats.frames_with_robot, 20);
        assert!(fg.stats.noise_level < 2.0, "{:?}", fg.stats);
        assert!(fg.stats.unstable_fraction < 0.1, "{:?}", fg.stats);
    }

    #[test]
    fn a_moved_object_at_rest_is_left_out_and_the_moving_square_is_not() {
        let (w, h) = (64, 48);
        let background: Vec<u8> = (0..w * h * 3).map(|i| ((i * 37) % 97) as u8 + 60).collect();
        let paint = |f: &mut Vec<u8>, x0: usize, y0: usize, rgb: [u8; 3]| {
            for y in y0..y0 + 8 {
                for x in x0..x0 + 8 {
                    f[(y * w + x) * 3..(y * w + x) * 3 + 3].copy_from_slice(&rgb);
                }
            }
        };
        // A red box sits at (40, 30) for the first 14 frames (the median's
        // place), then at (40, 4) (moved once); a white square crosses the
        // image all along.
        let frames: Vec<Vec<u8>> = (0..20)
            .map(|t| {
                let mut f = background.clone();
                paint(&mut f, 40, if t < 14 { 30 } else { 4 }, [200, 20, 20]);
                paint(&mut f, 2 * t + 2, 14, [250, 250, 250]);
                f
            })
            .collect();
        let e = episode(frames, w, h);
        let scored = find_foreground(&e, &ForegroundOptions::default());
        assert!(scored.unknown.is_empty());
        assert_eq!(scored.stats.static_fraction, 0.0);
        let options = ForegroundOptions {
            static_changes: StaticChanges::LeaveOut,
            ..ForegroundOptions::default()
        };
        let fg = find_foreground(&e, &options);
        assert_eq!(fg.masks, scored.masks, "the found pixels are the same");
        for t in 0..20 {
            // The square's second column: a frame later the square has left it.
            let square = 2 * t + 3;
            // The box where it rests after the move, and the place it left:
            // found, and static once it has rested two frames.
            if t >= 14 {
                for row in [7, 33] {
                    assert_eq!(fg.masks[t][row * w + 44], 1, "frame {t}");
                    assert_eq!(fg.unknown[t][row * w + 44], u8::from(t >= 16), "frame {t}");
                }
            }
            // What the moving square leaves behind next is never static
            // (the last frame has no next).
            assert_eq!(fg.masks[t][17 * w + square], 1, "frame {t}");
            if t < 19 {
                assert_eq!(fg.unknown[t][17 * w + square], 0, "frame {t}");
            }
        }
        assert!(
            fg.stats.static_fraction > 0.1 && fg.stats.static_fraction < 0.9,
            "{:?}",
            fg.stats
        );
        assert_eq!(
            "leave-out".parse::<StaticChanges>(),
            Ok(StaticChanges::LeaveOut)
        );
        let err = "leaveout".parse::<StaticChanges>().unwrap_err();
        assert!(
            err.contains("leaveout") && err.contains("score, leave-out"),
            "{err}"
        );
    }

    #[test]
    fn a_panning_camera_is_measured_as_unstable() {
        let (w, h) = (160, 48);
        let scene = |x: usize, y: usize| (((x / 7) * 31 + (y / 5) * 17) % 150 + 50) as u8;
        let frames: Vec<Vec<u8>> = (0..16)
            .map(|t| {
                (0..w * h * 3)
                    .map(|i| scene(i / 3 % w + 6 * t, i / 3 / w))
                    .collect()
            })
            .collect();
        let fg = find_foreground(&episode(frames, w, h), &ForegroundOptions::default());
        assert!(fg.stats.noise_level > 8.0, "{:?}", fg.stats);
        assert!(fg.stats.unstable_fraction > 0.5, "{:?}", fg.stats);
    }
}
