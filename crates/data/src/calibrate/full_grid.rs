//! The last stage of the search: the middle grid's finalists refined on
//! the full analysis grid with every score, and with the focal length
//! fitted, its profile (see [`super::valley::focal_profile`]).

use super::problem::Prepared;
use super::search::{active_parameters, distinct, refine, Evaluator};
use super::valley::focal_profile;
use super::CalibrateOptions;
use bridgev2w_embodiment::camera::Camera;
use bridgev2w_embodiment::robot::Robot;
use nalgebra::Point3;

/// Finalists whose silhouette objective on the middle grid is within this
/// of the best one's are refined again on the full grid with the
/// background's consistency and the appearance; and there the silhouette
/// may rise this much above the best start's before it is charged. Measured on the synthetic world (ten cameras,
/// docs/guide/calibrate.md): the same median error with every distinct
/// finalist, the worst camera 40.0 cm off against 31.8 with the margin.
pub(crate) const FINALIST_MARGIN: f64 = 0.05;

/// The last stage: the middle grid's `finalists` (sorted, best first)
/// refined on the full analysis grid with the silhouette, the background's
/// consistency and the appearance together (see [`super::background`],
/// [`super::appearance`]), from each distinct finalist the silhouette
/// scores within [`FINALIST_MARGIN`] of the best, since the silhouette
/// alone can rank a misplaced camera first; the silhouette kept within
/// [`FINALIST_MARGIN`] of the best start's on this grid, since the other
/// scores can have wrong minima of their own far from the silhouette's.
/// With the focal length fitted, then the focal length's profile
/// ([`focal_profile`]). Returns the camera and the evaluations spent.
pub(crate) fn refine_on_full_grid(
    robot: &Robot,
    prepared: &[Prepared],
    finalists: &[(Camera, f64)],
    target: Point3<f64>,
    options: &CalibrateOptions,
    progress: &dyn Fn(&str),
) -> (Camera, usize) {
    let all = active_parameters(options, true);
    let best_value = finalists.first().map_or(f64::INFINITY, |f| f.1);
    let extras = options.background_weight > 0.0 || options.appearance_weight > 0.0;
    let last: Vec<(Camera, f64)> = if extras {
        let close: Vec<(Camera, f64)> = finalists
            .iter()
            .filter(|(_, v)| *v <= best_value + FINALIST_MARGIN)
            .cloned()
            .collect();
        distinct(&close, options.finalists)
    } else {
        finalists.iter().take(1).cloned().collect()
    };
    let silhouette = Evaluator::fit(robot, prepared, 0, 2 * options.fit_frames);
    let ceiling = last
        .iter()
        .map(|(c, _)| silhouette.value(c))
        .fold(f64::INFINITY, f64::min)
        + FINALIST_MARGIN;
    let full = Evaluator::fit(robot, prepared, 0, 2 * options.fit_frames)
        .with_background(options.background_weight)
        .with_appearance(options.appearance_weight)
        .with_silhouette_ceiling(if extras { ceiling } else { f64::INFINITY });
    progress(&format!("refining {} on the full grid", last.len()));
    let (mut camera, _) = last
        .iter()
        .map(|(c, _)| refine(&full, c, target, &all, 0.5, options.max_evaluations, 2))
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .unwrap_or_else(|| finalists[0].clone());
    // The dolly-zoom valley searched again with every score, as a profile
    // over the focal length: they tell a near, wide camera from a far,
    // narrow one better than the silhouette alone.
    if extras && options.focal_px.is_none() {
        progress("profiling the focal length on the full grid");
        let (c, _) = focal_profile(&full, &camera, target, &all, options.max_evaluations);
        camera = refine(&full, &c, target, &all, 0.25, options.max_evaluations, 1).0;
    }
    (camera, silhouette.evaluations() + full.evaluations())
}
