//! An episode made ready for the search: the robot's link poses per frame,
//! the frames fitted and held out, the found foreground on each level's
//! grid, and how far the robot moves.

use super::episode::EpisodeData;
use super::foreground::{Foreground, ForegroundStats};
use super::marks::PlacedMark;
use super::objective::Level;
use bridgev2w_embodiment::robot::Robot;
use nalgebra::{Isometry3, Point3, Vector3};

/// Most mesh vertices per link used to measure the robot's motion.
const MOTION_POINTS_PER_LINK: usize = 64;

/// One episode ready for scoring.
#[derive(Debug, Clone)]
pub(crate) struct Prepared {
    /// Name for reports.
    pub name: String,
    /// Per frame: `world_from_link` of every link.
    pub poses: Vec<Vec<Isometry3<f64>>>,
    /// Frames the fit sees.
    pub fit: Vec<usize>,
    /// Frames held out from the fit.
    pub held: Vec<usize>,
    /// Frames whose rendered masks give `mode(M)` (a spread of all frames).
    pub mode: Vec<usize>,
    /// Found foreground per level (index 0 = the analysis grid).
    pub levels: Vec<Level>,
    /// The foreground measurements.
    pub foreground: ForegroundStats,
    /// The robot's motion (see [`motion`]).
    pub motion: Motion,
    /// Sampled points of the robot's surface over a spread of frames
    /// (world frame): a fixed camera cannot be where the robot passes.
    pub surface: Vec<Point3<f64>>,
    /// Hand marks of the tool point (see [`super::marks`]).
    pub marks: Vec<PlacedMark>,
}

/// How close a fixed camera may be to the robot's surface in any frame
/// (metres); nearer, the robot would strike it. On real DROID video, the
/// search otherwise found cameras inside or against the robot's base,
/// which a view filled by the robot explains too easily.
pub(crate) const MIN_CLEARANCE_M: f64 = 0.15;

/// The penalty added to the objective of a camera nearer than
/// [`MIN_CLEARANCE_M`] to `surface`: 0 at the clearance or beyond, rising
/// linearly to 1 at the surface (an objective is at most 1).
pub(crate) fn clearance_penalty(surface: &[Point3<f64>], eye: &Point3<f64>) -> f64 {
    let nearest_sq = surface
        .iter()
        .map(|p| (p - eye).norm_squared())
        .fold(f64::INFINITY, f64::min);
    let nearest = nearest_sq.sqrt();
    if nearest >= MIN_CLEARANCE_M {
        0.0
    } else {
        (MIN_CLEARANCE_M - nearest) / MIN_CLEARANCE_M
    }
}

/// The sampled surface points (as [`motion`] samples them) at frames `at`.
fn surface_points(robot: &Robot, poses: &[Vec<Isometry3<f64>>], at: &[usize]) -> Vec<Point3<f64>> {
    let mut out = Vec::new();
    for (i, link) in robot.links.iter().enumerate() {
        let Some(mesh) = &link.mesh else { continue };
        let stride = mesh.vertices.len().div_ceil(MOTION_POINTS_PER_LINK).max(1);
        for v in mesh.vertices.iter().step_by(stride) {
            let p = Point3::new(f64::from(v.x), f64::from(v.y), f64::from(v.z));
            out.extend(at.iter().map(|&t| poses[t][i] * p));
        }
    }
    out
}

/// How far the robot's surface moves over an episode.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Motion {
    /// The largest distance any sampled surface point travels from its
    /// first-frame position (metres).
    pub range_m: f64,
    /// The centroid of the sampled points weighted by how much each moves
    /// (world frame): where the camera sees motion.
    pub centroid: Point3<f64>,
}

/// `n` indices of `frames` spread evenly (all of them when there are fewer).
pub(crate) fn spread(frames: &[usize], n: usize) -> Vec<usize> {
    if frames.len() <= n {
        return frames.to_vec();
    }
    let mut out: Vec<usize> = (0..n)
        .map(|i| frames[(i * (frames.len() - 1)) / (n - 1).max(1)])
        .collect();
    out.dedup();
    out
}

/// Splits `n` frames into blocks of `block` frames and holds out every
/// `every`-th block (the last of each group of `every`): `(fit, held)`.
pub(crate) fn split_frames(n: usize, block: usize, every: usize) -> (Vec<usize>, Vec<usize>) {
    let block = block.max(1);
    (0..n).partition(|&t| (t / block) % every.max(2) != every.max(2) - 1)
}

/// The block size that splits `n` frames into about 16 blocks.
pub(crate) fn block_size(n: usize) -> usize {
    n.div_ceil(16).max(1)
}

/// The robot's motion over `poses` (see [`Motion`]).
pub(crate) fn motion(robot: &Robot, poses: &[Vec<Isometry3<f64>>]) -> Motion {
    let mut points: Vec<(usize, Point3<f64>)> = Vec::new();
    for (i, link) in robot.links.iter().enumerate() {
        let Some(mesh) = &link.mesh else { continue };
        let stride = mesh.vertices.len().div_ceil(MOTION_POINTS_PER_LINK).max(1);
        for v in mesh.vertices.iter().step_by(stride) {
            points.push((
                i,
                Point3::new(f64::from(v.x), f64::from(v.y), f64::from(v.z)),
            ));
        }
    }
    let mut range_m = 0f64;
    let mut weighted = Vector3::zeros();
    let mut weight = 0f64;
    let mut all = Vector3::zeros();
    for &(link, p) in &points {
        let track: Vec<Point3<f64>> = poses.iter().map(|q| q[link] * p).collect();
        let Some(first) = track.first() else { continue };
        let mean: Vector3<f64> =
            track.iter().map(|x| x.coords).sum::<Vector3<f64>>() / track.len() as f64;
        let spread_m = (track
            .iter()
            .map(|x| (x.coords - mean).norm_squared())
            .sum::<f64>()
            / track.len() as f64)
            .sqrt();
        for x in &track {
            range_m = range_m.max((x - first).norm());
        }
        weighted += spread_m * mean;
        weight += spread_m;
        all += mean;
    }
    let centroid = if weight > 1e-9 {
        weighted / weight
    } else {
        all / points.len().max(1) as f64
    };
    Motion {
        range_m,
        centroid: Point3::from(centroid),
    }
}

/// Prepares `episode` with its found `foreground` for levels reduced by
/// `factors` from the analysis grid (the first should be 1).
pub(crate) fn prepare(
    robot: &Robot,
    episode: &EpisodeData,
    foreground: &Foreground,
    factors: &[usize],
    held_out_every: usize,
    max_mode_frames: usize,
) -> Prepared {
    let poses: Vec<Vec<Isometry3<f64>>> =
        episode.joints.iter().map(|q| robot.link_poses(q)).collect();
    let n = poses.len();
    let (fit, held) = split_frames(n, block_size(n), held_out_every);
    let all: Vec<usize> = (0..n).collect();
    // Only the analysis grid (level 0) keeps the frames: the background's
    // consistency and the appearance are scored there alone.
    let levels = factors
        .iter()
        .enumerate()
        .map(|(i, &f)| Level::new(foreground, f, i == 0))
        .collect();
    let mode = spread(&all, max_mode_frames);
    Prepared {
        name: episode.name.clone(),
        motion: motion(robot, &poses),
        surface: surface_points(robot, &poses, &mode),
        poses,
        fit,
        held,
        mode,
        levels,
        foreground: foreground.stats.clone(),
        marks: Vec::new(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_split_into_fitted_and_held_out_blocks() {
        let (fit, held) = split_frames(16, 2, 4);
        assert_eq!(held, vec![6, 7, 14, 15]);
        assert_eq!(fit.len(), 12);
        assert!(fit.iter().all(|t| !held.contains(t)));
        assert_eq!(block_size(40), 3);
        assert_eq!(spread(&[0, 1, 2, 3, 4, 5, 6, 7, 8], 3), vec![0, 4, 8]);
        assert_eq!(spread(&[3, 4], 5), vec![3, 4]);
    }

    #[test]
    fn a_camera_against_the_robot_is_penalised_one_beyond_its_reach_not() {
        let surface = [Point3::new(0.0, 0.0, 0.5), Point3::new(0.3, 0.0, 0.5)];
        assert_eq!(
            clearance_penalty(&surface, &Point3::new(1.0, 0.0, 0.5)),
            0.0
        );
        assert_eq!(
            clearance_penalty(&surface, &Point3::new(0.3, 0.0, 0.5)),
            1.0
        );
        let half = clearance_penalty(&surface, &Point3::new(0.3, MIN_CLEARANCE_M / 2.0, 0.5));
        assert!((half - 0.5).abs() < 1e-9, "{half}");
    }
}
