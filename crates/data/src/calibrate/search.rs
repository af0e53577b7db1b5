//! Finding the camera: a coarse search over poses around the robot's
//! workspace, then Nelder-Mead refinement on finer and finer grids.
//!
//! - Coarse search: cameras on a grid of azimuths (all around), elevations
//!   and distances, looking at the centroid of the robot's motion, with
//!   roll 0 (image up = world up). Each is aimed and zoomed twice by image
//!   moments (the predicted foreground's centroid moved onto the found
//!   one's by a rotation, its spread matched by the focal length), then
//!   scored on the coarse grid. No hand-given start is needed; a guess, if
//!   given, joins the starts.
//! - Refinement: the best distinct candidates refined on the coarse grid
//!   (position, rotation, focal length), the best few of those on the
//!   middle grid with every fitted parameter, the best one on the full
//!   analysis grid.

use super::marks::{errors_px, rms_px, PlacedMark, MARKS_WEIGHT};
use super::nelder_mead::minimize;
use super::objective::{predicted, score, Prediction, Score};
use super::problem::{clearance_penalty, spread, Prepared};
use super::CalibrateOptions;
use bridgev2w_embodiment::camera::{Camera, Intrinsics};
use bridgev2w_embodiment::robot::Robot;
use nalgebra::{Point3, Translation3, UnitQuaternion, Vector3};
use rayon::prelude::*;
use std::sync::atomic::{AtomicUsize, Ordering};

/// Parameters, chosen so that the silhouette's near-degeneracies are
/// single coordinates: orbit about the target (2, radians: azimuth about
/// world z, elevation), dolly-zoom (log of the distance to the target, the
/// focal length scaled with it so the target's image keeps its size),
/// rotation (3, radians, rotation vector in the camera frame), log focal
/// length, log aspect (fy / fx), principal point (2, fractions of the image
/// size).
pub(crate) const N_PARAMS: usize = 10;
/// The smallest and largest focal length as a fraction of the image width
/// (a horizontal field of view of about 127 to 19 degrees).
const FOCAL_RANGE: (f64, f64) = (0.25, 3.0);
/// The nearest and farthest camera from the motion's centroid (metres).
const DISTANCE_RANGE_M: (f64, f64) = (0.25, 5.0);

/// The weight of the silhouette objective's excess over an evaluator's
/// ceiling (see [`Evaluator::with_silhouette_ceiling`]).
const CEILING_WEIGHT: f64 = 10.0;

/// Scores analysis-grid cameras on one level over chosen frames.
#[derive(Debug)]
pub(crate) struct Evaluator<'a> {
    robot: &'a Robot,
    episodes: &'a [Prepared],
    level: usize,
    frames: Vec<Vec<usize>>,
    coarse: bool,
    background_weight: f64,
    appearance_weight: f64,
    silhouette_ceiling: f64,
    evaluations: AtomicUsize,
}

impl<'a> Evaluator<'a> {
    /// Scores `frames[e]` of each episode `e` on `level`.
    pub fn new(
        robot: &'a Robot,
        episodes: &'a [Prepared],
        level: usize,
        frames: Vec<Vec<usize>>,
    ) -> Self {
        Self {
            robot,
            episodes,
            level,
            frames,
            coarse: false,
            background_weight: 0.0,
            appearance_weight: 0.0,
            silhouette_ceiling: f64::INFINITY,
            evaluations: AtomicUsize::new(0),
        }
    }

    /// Adds `weight` times the background-consistency cost (see
    /// [`super::background`]) to [`Evaluator::value`]; 0 leaves it out.
    pub fn with_background(mut self, weight: f64) -> Self {
        self.background_weight = weight;
        self
    }

    /// Adds `weight` times the appearance cost (see [`super::appearance`])
    /// to [`Evaluator::value`]; 0 leaves it out.
    pub fn with_appearance(mut self, weight: f64) -> Self {
        self.appearance_weight = weight;
        self
    }

    /// Adds [`CEILING_WEIGHT`] times the silhouette objective's excess over
    /// `ceiling` to [`Evaluator::value`]: the other scores choose among
    /// cameras the silhouette finds about as good, and never override it by
    /// more (on real video a colour split can favour a camera that renders
    /// a sliver of the robot over a patch of its own colours).
    pub fn with_silhouette_ceiling(mut self, ceiling: f64) -> Self {
        self.silhouette_ceiling = ceiling;
        self
    }

    /// Scores with [`Score::coarse_objective`] (see [`Evaluator::value`]).
    pub fn coarse(mut self) -> Self {
        self.coarse = true;
        self
    }

    /// The objective of `camera`: [`Score::coarse_objective`] for a coarse
    /// evaluator, else [`Score::objective`]; plus the weighted background
    /// cost ([`Evaluator::with_background`]); plus the clearance penalty of
    /// a camera where the robot's surface passes ([`clearance_penalty`]).
    pub fn value(&self, camera: &Camera) -> f64 {
        let eye = Point3::from(camera.world_from_camera.translation.vector);
        let penalty = self
            .episodes
            .iter()
            .map(|e| clearance_penalty(&e.surface, &eye))
            .fold(0.0, f64::max);
        let s = self.score(camera);
        let silhouette = if self.coarse {
            s.coarse_objective()
        } else {
            s.objective()
        };
        penalty
            + CEILING_WEIGHT * (silhouette - self.silhouette_ceiling).max(0.0)
            + self.marks_term(camera)
            + self.background_weight * s.background_mean()
            + self.appearance_weight * s.appearance_mean()
            + silhouette
    }

    /// [`MARKS_WEIGHT`] times the RMS reprojection error of the episodes'
    /// hand marks over the image width (0 without marks).
    pub fn marks_term(&self, camera: &Camera) -> f64 {
        // Per episode, without copying the marks (a hot path).
        let (mut sum_sq, mut n) = (0.0, 0usize);
        for e in self.episodes {
            for err in errors_px(&e.marks, camera) {
                sum_sq += err * err;
                n += 1;
            }
        }
        if n == 0 {
            return 0.0;
        }
        MARKS_WEIGHT * (sum_sq / n as f64).sqrt() / f64::from(camera.intrinsics.width)
    }

    /// At most `n` fitted frames per episode, spread over it.
    pub fn fit(robot: &'a Robot, episodes: &'a [Prepared], level: usize, n: usize) -> Self {
        let frames = episodes.iter().map(|e| spread(&e.fit, n)).collect();
        Self::new(robot, episodes, level, frames)
    }

    /// Evaluations so far.
    pub fn evaluations(&self) -> usize {
        self.evaluations.load(Ordering::Relaxed)
    }

    fn level_camera(&self, e: &Prepared, camera: &Camera) -> Camera {
        Camera {
            intrinsics: e.levels[self.level].intrinsics(&camera.intrinsics),
            world_from_camera: camera.world_from_camera,
        }
    }

    /// Predicted pixels per episode and scored frame.
    pub fn predicted(&self, camera: &Camera) -> Vec<Prediction> {
        self.episodes
            .iter()
            .zip(&self.frames)
            .map(|(e, frames)| {
                let c = self.level_camera(e, camera);
                predicted(self.robot, &e.poses, &c, frames, &e.mode)
            })
            .collect()
    }

    /// Per episode: the score and the per-frame IoU.
    pub fn detail(&self, camera: &Camera) -> Vec<(Score, Vec<f64>)> {
        self.evaluations.fetch_add(1, Ordering::Relaxed);
        let predictions = self.predicted(camera);
        self.episodes
            .iter()
            .zip(&self.frames)
            .zip(&predictions)
            .map(|((e, frames), p)| {
                score(
                    &e.levels[self.level],
                    frames,
                    p,
                    self.coarse,
                    self.background_weight > 0.0 || self.appearance_weight > 0.0,
                )
            })
            .collect()
    }

    /// The pooled score over episodes.
    pub fn score(&self, camera: &Camera) -> Score {
        let mut total = Score::default();
        for (s, _) in self.detail(camera) {
            total.add(&s);
        }
        total
    }
}

/// A camera varied by the parameters of [`N_PARAMS`] around `base`, only
/// the `active` ones free; orbit and dolly about `target`.
#[derive(Debug, Clone)]
pub(crate) struct Parametrization {
    base: Camera,
    target: Point3<f64>,
    active: Vec<usize>,
}

impl Parametrization {
    pub fn new(base: Camera, target: Point3<f64>, active: &[usize]) -> Self {
        Self {
            base,
            target,
            active: active.to_vec(),
        }
    }

    /// The camera at the active parameters `x`, or `None` when its focal
    /// length or principal point leave the plausible range.
    pub fn camera(&self, x: &[f64]) -> Option<Camera> {
        let mut p = [0f64; N_PARAMS];
        for (&i, &v) in self.active.iter().zip(x) {
            p[i] = v;
        }
        if !self.active.contains(&6) {
            // A fixed focal length: the dolly moves the camera only.
            p[6] = -p[2];
        }
        let b = &self.base;
        let k = &b.intrinsics;
        let (w, h) = (f64::from(k.width), f64::from(k.height));
        let fx = k.fx * (p[2] + p[6]).exp();
        let fy = k.fy * (p[2] + p[6] + p[7]).exp();
        let cx = k.cx + p[8] * w;
        let cy = k.cy + p[9] * h;
        let ok = p.iter().all(|v| v.is_finite())
            && (FOCAL_RANGE.0..=FOCAL_RANGE.1).contains(&(fx / w))
            && (FOCAL_RANGE.0..=FOCAL_RANGE.1).contains(&(fy / w))
            && (0.0..=w).contains(&cx)
            && (0.0..=h).contains(&cy);
        if !ok {
            return None;
        }
        // Orbit: the camera and its orientation turned about the target.
        let offset = b.world_from_camera.translation.vector - self.target.coords;
        let side = Vector3::z().cross(&offset);
        let side = if side.norm() > 1e-9 {
            side.normalize()
        } else {
            b.world_from_camera.rotation * Vector3::x()
        };
        let orbit = UnitQuaternion::from_scaled_axis(Vector3::z() * p[0])
            * UnitQuaternion::from_scaled_axis(side * -p[1]);
        let distance = offset.norm() * p[2].exp();
        if !(DISTANCE_RANGE_M.0..=DISTANCE_RANGE_M.1).contains(&distance) {
            return None;
        }
        let t = self.target.coords + orbit * (offset * p[2].exp());
        let r = orbit
            * b.world_from_camera.rotation
            * UnitQuaternion::from_scaled_axis(Vector3::new(p[3], p[4], p[5]));
        Some(Camera {
            intrinsics: Intrinsics {
                fx,
                fy,
                cx,
                cy,
                ..*k
            },
            world_from_camera: nalgebra::Isometry3::from_parts(Translation3::from(t), r),
        })
    }
}

/// Pooled centroid and RMS spread (analysis-grid pixels) of the rendered
/// and the found robot pixels: `((cx, cy, spread, n) rendered, found)`.
type Moments = ([f64; 4], [f64; 4]);

fn moments(ev: &Evaluator, camera: &Camera) -> Moments {
    let predictions = ev.predicted(camera);
    let mut acc = [[0f64; 4]; 2];
    for ((e, frames), preds) in ev.episodes.iter().zip(&ev.frames).zip(&predictions) {
        let level = &e.levels[ev.level];
        let f = level.factor as f64;
        for (&t, m) in frames.iter().zip(&preds.change) {
            let known = level.known(t);
            for (i, (&pv, &ov)) in m.iter().zip(&level.found[t]).enumerate() {
                let pv = f32::from(pv) * known.map_or(1.0, |k| k[i]);
                let x = ((i % level.width) as f64 + 0.5) * f - 0.5;
                let y = ((i / level.width) as f64 + 0.5) * f - 0.5;
                for (a, wgt) in acc.iter_mut().zip([f64::from(pv), f64::from(ov)]) {
                    if wgt > 0.0 {
                        a[0] += wgt * x;
                        a[1] += wgt * y;
                        a[2] += wgt * (x * x + y * y);
                        a[3] += wgt;
                    }
                }
            }
        }
    }
    let finish = |a: [f64; 4]| {
        let n = a[3].max(1e-9);
        let (cx, cy) = (a[0] / n, a[1] / n);
        let var = (a[2] / n - cx * cx - cy * cy).max(0.0);
        [cx, cy, var.sqrt(), a[3]]
    };
    (finish(acc[0]), finish(acc[1]))
}

/// Turns `camera` so that its rendered robot's centroid matches the found
/// robot pixels', and (`zoom`) scales its focal length so their spreads
/// match; `None` when either is empty.
fn recentre(ev: &Evaluator, camera: &Camera, zoom: bool) -> Option<Camera> {
    let (p, o) = moments(ev, camera);
    if p[3] < 3.0 || o[3] < 3.0 || p[2] <= 0.0 {
        return None;
    }
    let k = &camera.intrinsics;
    let w = f64::from(k.width);
    let s = if zoom {
        (o[2] / p[2]).clamp(1.0 / 3.0, 3.0)
    } else {
        1.0
    };
    let fx = (k.fx * s).clamp(FOCAL_RANGE.0 * w, FOCAL_RANGE.1 * w);
    let s = fx / k.fx;
    let fy = k.fy * s;
    let old = Vector3::new((p[0] - k.cx) / k.fx, (p[1] - k.cy) / k.fy, 1.0);
    let new = Vector3::new((o[0] - k.cx) / fx, (o[1] - k.cy) / fy, 1.0);
    let q = UnitQuaternion::rotation_between(&new, &old)?;
    Some(Camera {
        intrinsics: Intrinsics { fx, fy, ..*k },
        world_from_camera: nalgebra::Isometry3::from_parts(
            camera.world_from_camera.translation,
            camera.world_from_camera.rotation * q,
        ),
    })
}

/// The search's starting intrinsics on the analysis grid: the known focal
/// length or 0.8 x the width, `fy_over_fx`, the principal point centred.
pub(crate) fn start_intrinsics(
    (width, height): (u32, u32),
    options: &CalibrateOptions,
    focal: Option<f64>,
) -> Intrinsics {
    let f0 = focal.unwrap_or(0.8 * f64::from(width));
    Intrinsics {
        fx: f0,
        fy: f0 * options.fy_over_fx,
        cx: (f64::from(width) - 1.0) / 2.0,
        cy: (f64::from(height) - 1.0) / 2.0,
        width,
        height,
        distortion: None,
    }
}

/// The coarse grid's camera positions: every azimuth step all around,
/// each elevation and distance from `target`.
fn grid_eyes(target: Point3<f64>, options: &CalibrateOptions) -> Vec<Point3<f64>> {
    let steps = (360.0 / options.azimuth_step_deg).round().max(1.0) as usize;
    let mut grid = Vec::new();
    for a in 0..steps {
        let az = (a as f64 * 360.0 / steps as f64).to_radians();
        for &el in &options.elevations_deg {
            for &d in &options.distances_m {
                let el = el.to_radians();
                let dir = Vector3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
                grid.push(target + d * dir);
            }
        }
    }
    grid
}

/// The camera that best projects the hand marks of `episodes` onto their
/// pixels: from every coarse-grid pose looking at `target`, the pose (and,
/// unless `focal` is known, the focal length) fitted to the marks alone by
/// Nelder-Mead; the best, or `None` without marks.
pub(crate) fn marks_start(
    episodes: &[Prepared],
    intrinsics: Intrinsics,
    target: Point3<f64>,
    options: &CalibrateOptions,
    focal: Option<f64>,
) -> Option<(Camera, f64)> {
    let marks: Vec<PlacedMark> = episodes.iter().flat_map(|e| e.marks.clone()).collect();
    if marks.is_empty() {
        return None;
    }
    let mut active = vec![0, 1, 2, 3, 4, 5];
    if focal.is_none() {
        active.push(6);
    }
    let rms = |c: &Camera| rms_px(&marks, c).unwrap_or(f64::INFINITY);
    grid_eyes(target, options)
        .par_iter()
        .filter_map(|eye| {
            let mut camera = Camera::look_at(intrinsics, *eye, target, Vector3::z()).ok()?;
            for round in 0..3 {
                let param = Parametrization::new(camera.clone(), target, &active);
                let f = |x: &[f64]| param.camera(x).map_or(f64::INFINITY, |c| rms(&c));
                let s = steps(&active, 0.5f64.powi(round));
                let m = minimize(&f, &vec![0.0; active.len()], &s, 400, 1e-9);
                camera = param.camera(&m.x)?;
            }
            let v = rms(&camera);
            v.is_finite().then_some((camera, v))
        })
        .min_by(|a, b| a.1.total_cmp(&b.1))
}

/// The coarse search's candidates, scored on `ev`'s level, best first.
pub(crate) fn coarse_candidates(
    ev: &Evaluator,
    target: Point3<f64>,
    (width, height): (u32, u32),
    options: &CalibrateOptions,
    focal: Option<f64>,
) -> Vec<(Camera, f64)> {
    let intrinsics = start_intrinsics((width, height), options, focal);
    let mut out: Vec<(Camera, f64)> = grid_eyes(target, options)
        .par_iter()
        .filter_map(|eye| {
            let mut c = Camera::look_at(intrinsics, *eye, target, Vector3::z()).ok()?;
            for _ in 0..2 {
                c = recentre(ev, &c, focal.is_none())?;
            }
            Some((c.clone(), ev.value(&c)))
        })
        .collect();
    out.sort_by(|a, b| a.1.total_cmp(&b.1));
    out
}

/// Angle between two cameras' orientations (radians).
pub(crate) fn angle_between(a: &Camera, b: &Camera) -> f64 {
    a.world_from_camera
        .rotation
        .angle_to(&b.world_from_camera.rotation)
}

/// Picks up to `n` candidates, best first, skipping any within 0.1 m and
/// 8 degrees of one already picked.
pub(crate) fn distinct(candidates: &[(Camera, f64)], n: usize) -> Vec<(Camera, f64)> {
    let mut out: Vec<(Camera, f64)> = Vec::new();
    for c in candidates {
        if out.len() >= n {
            break;
        }
        let near = out.iter().any(|(o, _)| {
            let d = (o.world_from_camera.translation.vector
                - c.0.world_from_camera.translation.vector)
                .norm();
            d < 0.1 && angle_between(o, &c.0) < 8f64.to_radians()
        });
        if !near {
            out.push(c.clone());
        }
    }
    out
}

/// The parameter indices fitted: position, rotation, focal length (unless
/// known), and per options the aspect (unless the focal length is known)
/// and the principal point.
pub(crate) fn active_parameters(options: &CalibrateOptions, all: bool) -> Vec<usize> {
    // A known focal length: no focal (6) and no aspect (7) parameter.
    let known = options.focal_px.is_some();
    let mut active: Vec<usize> = if known {
        (0..6).collect()
    } else {
        (0..7).collect()
    };
    if all && options.fit_aspect && !known {
        active.push(7);
    }
    if all && options.fit_principal_point {
        active.extend([8, 9]);
    }
    active
}

/// Initial simplex steps of the parameters, multiplied by `scale`.
pub(crate) fn steps(active: &[usize], scale: f64) -> Vec<f64> {
    active
        .iter()
        .map(|&i| {
            scale
                * match i {
                    0 | 1 => 0.06,
                    2 => 0.08,
                    3..=5 => 0.03,
                    6 => 0.05,
                    7 => 0.01,
                    _ => 0.01,
                }
        })
        .collect()
}

/// Refines `start` on `ev` with Nelder-Mead over `active`, `rounds` times
/// (each restart from the last result with half the steps): the camera and
/// its objective.
pub(crate) fn refine(
    ev: &Evaluator,
    start: &Camera,
    target: Point3<f64>,
    active: &[usize],
    scale: f64,
    max_evaluations: usize,
    rounds: usize,
) -> (Camera, f64) {
    let mut camera = start.clone();
    let mut value = ev.value(&camera);
    for round in 0..rounds {
        let param = Parametrization::new(camera.clone(), target, active);
        let f = |x: &[f64]| param.camera(x).map_or(5.0, |c| ev.value(&c));
        let s = steps(active, scale * 0.5f64.powi(round as i32));
        let m = minimize(&f, &vec![0.0; active.len()], &s, max_evaluations, 1e-6);
        if m.value < value {
            if let Some(c) = param.camera(&m.x) {
                camera = c;
                value = m.value;
            }
        }
    }
    (camera, value)
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
pub(crate) mod tests {
    use super::*;
    use crate::calibrate::episode::EpisodeData;
    use crate::calibrate::foreground::find_foreground;
    use crate::calibrate::problem::prepare;
    use crate::calibrate::study::camera_errors;
    use crate::calibrate::valley::refit_with_fixed;
    use crate::synth::{Split, SynthConfig, Task, World};

    /// A synthetic `test` episode of `frames` frames at 128 x 80 (dataset
    /// `seed`) made ready on the analysis grid, with options that know the
    /// true focal length.
    pub(crate) fn synthetic(
        (frames, seed): (usize, u64),
        index: usize,
        task: Task,
    ) -> (
        World,
        crate::synth::Episode,
        CalibrateOptions,
        [Prepared; 1],
    ) {
        let world = World::new(&SynthConfig {
            frames,
            width: 128,
            height: 80,
            seed,
            ..SynthConfig::default()
        })
        .unwrap();
        let ep = world.generate(Split::Test, index, task).unwrap();
        let data = EpisodeData::new(
            "synthetic",
            (128, 80),
            1,
            (128, 80),
            ep.rgb.clone(),
            ep.joints.clone(),
        )
        .unwrap();
        let options = CalibrateOptions {
            focal_px: Some(ep.camera.intrinsics.fx),
            ..CalibrateOptions::default()
        };
        let fg = find_foreground(&data, &options.foreground);
        let prepared = [prepare(
            &world.embodiment.robot,
            &data,
            &fg,
            &[1],
            4,
            frames,
        )];
        (world, ep, options, prepared)
    }

    #[test]
    fn the_background_tells_a_camera_stalled_in_a_valley_from_the_truth() {
        let (world, ep, options, prepared) = synthetic((24, 7), 1, Task::Push);
        let (truth, robot) = (&ep.camera, &world.embodiment.robot);
        let target = prepared[0].motion.centroid;
        let silhouette = Evaluator::fit(robot, &prepared, 0, 24);
        let both = Evaluator::fit(robot, &prepared, 0, 24).with_background(10.0);
        let active = active_parameters(&options, true);
        for (index, value) in [(0, 0.12), (1, -0.12), (2, 0.15)] {
            // The truth moved along an orbit or the dolly, the rest re-fitted
            // to the silhouette: a camera stalled in its valley.
            let (stalled, _) =
                refit_with_fixed(&silhouette, truth, target, &active, (index, value), 120).unwrap();
            let gap = |ev: &Evaluator| ev.value(&stalled) - ev.value(truth);
            let (alone, with_bg) = (gap(&silhouette), gap(&both));
            let cm = camera_errors(&stalled, truth).0;
            assert!(cm > 10.0, "{cm:.2} cm");
            // Measured: -0.0122 / 0.0050, -0.0051 / 0.0746, 0.0802 / 0.1586:
            // the silhouette alone ranks two of them above the truth.
            assert!(
                with_bg > 0.003 && with_bg > alone,
                "parameter {index} moved {value}: {cm:.2} cm off; silhouette gap {alone:.4}, with the background {with_bg:.4}"
            );
        }
    }

    #[test]
    fn the_appearance_tells_a_reachs_misplaced_cameras_from_the_truth() {
        // A reach: only the arm moves; the base and the shoulder stay put,
        // and neither the silhouette nor the background's consistency sees
        // where they are.
        let (world, ep, options, prepared) = synthetic((24, 7), 3, Task::Reach);
        let (truth, robot) = (&ep.camera, &world.embodiment.robot);
        let target = prepared[0].motion.centroid;
        let both = Evaluator::fit(robot, &prepared, 0, 24).with_background(10.0);
        let appearance = |c: &Camera| both.score(c).appearance_mean();
        let active = active_parameters(&options, true);
        for (index, value) in [(0, 0.12), (1, 0.12), (1, -0.12)] {
            // Moved along an orbit, the rest re-fitted to the silhouette and
            // the background: 16.6-17.2 cm off.
            let (moved, _) =
                refit_with_fixed(&both, truth, target, &active, (index, value), 120).unwrap();
            let gap = both.value(&moved) - both.value(truth);
            let app_gap = appearance(&moved) - appearance(truth);
            // Measured: the two scores' gap -0.0000 / 0.0071 / 0.0495, the
            // appearance's 0.183 / 0.075 / 0.159.
            assert!(
                app_gap > 0.05 && app_gap > 1.5 * gap,
                "parameter {index} moved {value}: {:.2} cm off; silhouette and background gap {gap:.4}, appearance gap {app_gap:.4}",
                camera_errors(&moved, truth).0
            );
        }
    }

    #[test]
    fn the_silhouette_ceiling_charges_only_the_excess() {
        let (world, ep, _, prepared) = synthetic((8, 7), 0, Task::Push);
        let robot = &world.embodiment.robot;
        let plain = Evaluator::fit(robot, &prepared, 0, 8);
        let silhouette = plain.score(&ep.camera).objective();
        let base = plain.value(&ep.camera);
        let above =
            Evaluator::fit(robot, &prepared, 0, 8).with_silhouette_ceiling(silhouette + 0.01);
        assert_eq!(above.value(&ep.camera), base);
        let below =
            Evaluator::fit(robot, &prepared, 0, 8).with_silhouette_ceiling(silhouette - 0.02);
        let charged = below.value(&ep.camera) - base;
        assert!((charged - CEILING_WEIGHT * 0.02).abs() < 1e-9, "{charged}");
    }
}
