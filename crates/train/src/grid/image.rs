//! The grid image: a clip's row of panels (first frame | masks | each
//! prediction | ground truth) and the rows as an animated GIF.

use crate::{Result, TrainError};
use bridgev2w_io::frame::{u8_from_unit, RgbFrame};
use std::path::Path;

/// One clip's row of a grid: per frame, the RGB8 strip of its panels.
pub(crate) type GridRow = Vec<Vec<u8>>;

/// Grid upscaling: each pixel as `GRID_SCALE` x `GRID_SCALE`.
pub const GRID_SCALE: usize = 2;

/// One clip's row of the grid, per frame: first frame | masks | each
/// prediction | ground truth, RGB8, upscaled.
pub(crate) fn grid_row(gt: &[RgbFrame], preds: &[&[RgbFrame]], masks: &[Vec<u8>]) -> GridRow {
    use bridgev2w_embodiment::overlay::{mask_rgb, side_by_side, upscale};
    let rgb8 = |f: &RgbFrame| -> Vec<u8> { f.rgb.iter().map(|&v| u8_from_unit(v)).collect() };
    let (w, h) = (gt[0].width, gt[0].height);
    let k = GRID_SCALE;
    let first = upscale(&rgb8(&gt[0]), w, h, k);
    let t_max = preds.iter().map(|p| p.len()).fold(gt.len(), usize::min);
    (0..t_max)
        .map(|t| {
            let mask = masks
                .get(t)
                .map(|m| mask_rgb(m))
                .unwrap_or_else(|| vec![0; w * h * 3]);
            let mut panels = vec![first.clone(), upscale(&mask, w, h, k)];
            panels.extend(preds.iter().map(|p| upscale(&rgb8(&p[t]), w, h, k)));
            panels.push(upscale(&rgb8(&gt[t]), w, h, k));
            let refs: Vec<&[u8]> = panels.iter().map(Vec::as_slice).collect();
            side_by_side(&refs, w * k, h * k)
        })
        .collect()
}

/// The rows stacked top to bottom, frame by frame, as an animated GIF;
/// `(w, h)` is a panel's size before upscaling.
pub(crate) fn write_grid(path: &Path, rows: &[GridRow], (w, h): (usize, usize)) -> Result<()> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(|e| {
            TrainError::input(dir.display().to_string(), format!("cannot create: {e}"))
        })?;
    }
    let t = rows.iter().map(Vec::len).min().unwrap_or(0);
    let frames: Vec<Vec<u8>> = (0..t)
        .map(|i| rows.iter().flat_map(|r| r[i].iter().copied()).collect())
        .collect();
    let k = GRID_SCALE;
    let row_width = frames
        .first()
        .map_or(0, |f| f.len() / rows.len().max(1) / (h * k * 3));
    debug_assert_eq!(row_width % (w * k), 0);
    bridgev2w_embodiment::overlay::write_gif(
        path,
        row_width as u32,
        (rows.len() * h * k) as u32,
        &frames,
        4,
    )
    .map_err(|e| TrainError::input(path.display().to_string(), e.to_string()))
}
