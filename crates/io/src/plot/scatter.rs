//! Scatter plots with a least-squares line per set of points (policy
//! evaluation: world-model success against real success, a set per world
//! model), next to the y = x diagonal of perfect agreement.

use super::{chart_builder, color, draw_grid, text_style, tick, Canvas, Figure};
use plotters::prelude::*;

/// One set of points, with its fitted line.
#[derive(Debug, Clone, PartialEq)]
pub struct PointSet {
    /// The legend's text (e.g. the model and its Pearson r).
    pub label: String,
    /// `(x, y)` points.
    pub points: Vec<(f64, f64)>,
    /// Palette index ([`super::color`]).
    pub color: usize,
}

/// A scatter plot on a square range.
#[derive(Debug, Clone, PartialEq)]
pub struct ScatterFigure {
    /// Drawn above the chart.
    pub title: String,
    /// The x axis's description.
    pub x_desc: String,
    /// The y axis's description.
    pub y_desc: String,
    /// The sets.
    pub sets: Vec<PointSet>,
    /// The range of both axes.
    pub range: (f64, f64),
    /// Size in pixels.
    pub size: (u32, u32),
}

/// The least-squares line `y = a + b x` of `points`: `(a, b)`; `None` for
/// fewer than two points or when every x is the same.
pub fn least_squares(points: &[(f64, f64)]) -> Option<(f64, f64)> {
    let n = points.len() as f64;
    if points.len() < 2 {
        return None;
    }
    let (mx, my) = (
        points.iter().map(|p| p.0).sum::<f64>() / n,
        points.iter().map(|p| p.1).sum::<f64>() / n,
    );
    let sxx: f64 = points.iter().map(|p| (p.0 - mx).powi(2)).sum();
    let sxy: f64 = points.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    (sxx > 1e-12).then(|| {
        let b = sxy / sxx;
        (my - b * mx, b)
    })
}

impl Figure for ScatterFigure {
    fn size(&self) -> (u32, u32) {
        self.size
    }

    fn draw(&self, root: &Canvas<'_>, text: bool) -> Result<(), String> {
        if self.sets.iter().all(|s| s.points.is_empty()) {
            return Err("no points to draw".into());
        }
        let e = |e: DrawingAreaErrorKind<_>| e.to_string();
        // The legend goes in a strip below the chart, so that it never hides
        // a point: a row for the diagonal and one per set.
        let strip = if text {
            LEGEND_ROW_PX * (self.sets.len() as u32 + 1) + 8
        } else {
            0
        };
        let height = root.dim_in_pixel().1;
        let (plot, legend) = root.split_vertically(height.saturating_sub(strip));
        let (lo, hi) = self.range;
        let mut chart = chart_builder(&plot, 12, &self.title, 40, text)
            .build_cartesian_2d(lo..hi, lo..hi)
            .map_err(e)?;
        let fmt = |v: &f64| tick(*v);
        draw_grid(&mut chart, text, (&self.x_desc, &self.y_desc), &fmt, &fmt)?;
        let grey = RGBColor(150, 150, 150);
        chart
            .draw_series(DashedLineSeries::new(
                vec![(lo, lo), (hi, hi)],
                5,
                5,
                grey.stroke_width(1),
            ))
            .map_err(e)?;
        for set in &self.sets {
            let c = color(set.color);
            if let Some((a, b)) = least_squares(&set.points) {
                chart
                    .draw_series(LineSeries::new(
                        vec![(lo, a + b * lo), (hi, a + b * hi)],
                        c.stroke_width(2),
                    ))
                    .map_err(e)?;
            }
            chart
                .draw_series(
                    set.points
                        .iter()
                        .filter(|p| p.0.is_finite() && p.1.is_finite())
                        .map(|&p| Circle::new(p, 5, c.filled())),
                )
                .map_err(e)?;
        }
        if text {
            let rows = std::iter::once(("y = x (dashed): perfect agreement", grey, 1)).chain(
                self.sets
                    .iter()
                    .map(|s| (s.label.as_str(), color(s.color), 2)),
            );
            for (i, (label, c, width)) in rows.enumerate() {
                let y = 4 + LEGEND_ROW_PX as i32 * i as i32 + LEGEND_ROW_PX as i32 / 2;
                legend
                    .draw(&PathElement::new(
                        vec![(LEGEND_X_PX, y), (LEGEND_X_PX + 18, y)],
                        c.stroke_width(width),
                    ))
                    .map_err(e)?;
                legend
                    .draw(&Text::new(
                        label.to_string(),
                        (LEGEND_X_PX + 26, y - 6),
                        text_style(11),
                    ))
                    .map_err(e)?;
            }
        }
        Ok(())
    }
}

/// The height of one legend row and the legend's left edge (pixels).
const LEGEND_ROW_PX: u32 = 18;
const LEGEND_X_PX: i32 = 72;
