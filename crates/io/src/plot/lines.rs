//! Line panels: one or more charts side by side (a panel per training
//! stage, per split), each with its own axes, lines and legend.

use super::{chart_builder, color, draw_grid, padded_range, text_style, tick, Canvas, Figure};
use plotters::prelude::*;

/// One line of a panel.
#[derive(Debug, Clone, PartialEq)]
pub struct Line {
    /// The legend's text (`None`: not in the legend).
    pub label: Option<String>,
    /// `(x, y)` points in order; non-finite ones are skipped.
    pub points: Vec<(f64, f64)>,
    /// Palette index ([`super::color`]).
    pub color: usize,
    /// Drawn dashed (bounds and baselines).
    pub dashed: bool,
    /// Drawn thin and light (raw values under a smoothed line).
    pub faint: bool,
    /// A marker at every point (few points).
    pub markers: bool,
}

impl Line {
    /// A solid line with a legend entry.
    pub fn new(label: impl Into<String>, points: Vec<(f64, f64)>, color: usize) -> Self {
        Self {
            label: Some(label.into()),
            points,
            color,
            dashed: false,
            faint: false,
            markers: false,
        }
    }
}

/// One chart.
#[derive(Debug, Clone, PartialEq)]
pub struct Panel {
    /// Drawn above the chart.
    pub title: String,
    /// The x axis's description.
    pub x_desc: String,
    /// The y axis's description.
    pub y_desc: String,
    /// A logarithmic y axis (points at or below 0 are skipped).
    pub log_y: bool,
    /// The lines.
    pub lines: Vec<Line>,
}

/// Panels in a grid, row by row.
#[derive(Debug, Clone, PartialEq)]
pub struct LineFigure {
    /// The panels.
    pub panels: Vec<Panel>,
    /// Panels per row.
    pub columns: usize,
    /// Each panel's size in pixels.
    pub panel_size: (u32, u32),
}

impl Figure for LineFigure {
    fn size(&self) -> (u32, u32) {
        let cols = self.columns.clamp(1, self.panels.len().max(1));
        let rows = self.panels.len().div_ceil(cols).max(1);
        (
            self.panel_size.0 * cols as u32,
            self.panel_size.1 * rows as u32,
        )
    }

    fn draw(&self, root: &Canvas<'_>, text: bool) -> Result<(), String> {
        if self.panels.is_empty() {
            return Err("no panels to draw".into());
        }
        let cols = self.columns.clamp(1, self.panels.len());
        let rows = self.panels.len().div_ceil(cols);
        let areas = root.split_evenly((rows, cols));
        for (panel, area) in self.panels.iter().zip(&areas) {
            draw_panel(panel, area, text)?;
        }
        Ok(())
    }
}

/// A point as drawn: `y` as its base-10 logarithm on a log axis; `None`
/// when it cannot be drawn.
fn drawn(p: (f64, f64), log_y: bool) -> Option<(f64, f64)> {
    let (x, y) = if log_y {
        (p.0, if p.1 > 0.0 { p.1.log10() } else { f64::NAN })
    } else {
        p
    };
    (x.is_finite() && y.is_finite()).then_some((x, y))
}

/// The legend's place: the corner (or side) of the plot that the lines
/// cross least, judged on points sampled along them.
fn legend_corner(
    lines: &[Vec<(f64, f64)>],
    (x0, x1): (f64, f64),
    (y0, y1): (f64, f64),
) -> SeriesLabelPosition {
    use SeriesLabelPosition as P;
    // Candidates with their boxes in the unit square (x from the left, y from the bottom).
    let boxes = [
        (P::UpperRight, (0.55, 1.0), (0.6, 1.0)),
        (P::UpperLeft, (0.0, 0.45), (0.6, 1.0)),
        (P::LowerRight, (0.55, 1.0), (0.0, 0.4)),
        (P::LowerLeft, (0.0, 0.45), (0.0, 0.4)),
        (P::MiddleRight, (0.55, 1.0), (0.3, 0.7)),
        (P::MiddleLeft, (0.0, 0.45), (0.3, 0.7)),
    ];
    let unit = |(x, y): (f64, f64)| ((x - x0) / (x1 - x0), (y - y0) / (y1 - y0));
    let mut samples = Vec::new();
    for line in lines {
        for w in line.windows(2) {
            for k in 0..16 {
                let t = f64::from(k) / 16.0;
                samples.push(unit((
                    w[0].0 + t * (w[1].0 - w[0].0),
                    w[0].1 + t * (w[1].1 - w[0].1),
                )));
            }
        }
        samples.extend(line.last().map(|&p| unit(p)));
    }
    boxes
        .into_iter()
        .min_by_key(|(_, (bx0, bx1), (by0, by1))| {
            samples
                .iter()
                .filter(|(x, y)| (bx0..=bx1).contains(&x) && (by0..=by1).contains(&y))
                .count()
        })
        .map_or(P::UpperRight, |(p, _, _)| p)
}

fn draw_panel(panel: &Panel, area: &Canvas<'_>, text: bool) -> Result<(), String> {
    let pts: Vec<Vec<(f64, f64)>> = panel
        .lines
        .iter()
        .map(|l| {
            l.points
                .iter()
                .filter_map(|&p| drawn(p, panel.log_y))
                .collect()
        })
        .collect();
    let (Some(xr), Some(yr)) = (
        padded_range(pts.iter().flatten().map(|p| p.0)),
        padded_range(pts.iter().flatten().map(|p| p.1)),
    ) else {
        return Err(format!("panel `{}`: no finite points", panel.title));
    };
    let e = |e: DrawingAreaErrorKind<_>| e.to_string();
    let mut chart = chart_builder(area, 10, &panel.title, 40, text)
        .build_cartesian_2d(xr.0..xr.1, yr.0..yr.1)
        .map_err(e)?;
    let log_y = panel.log_y;
    let y_fmt = move |v: &f64| tick(if log_y { 10f64.powf(*v) } else { *v });
    let x_fmt = |v: &f64| tick(*v);
    draw_grid(
        &mut chart,
        text,
        (&panel.x_desc, &panel.y_desc),
        &x_fmt,
        &y_fmt,
    )?;
    for (line, pts) in panel.lines.iter().zip(&pts) {
        let c = color(line.color);
        let style = if line.faint {
            c.mix(0.3).stroke_width(1)
        } else {
            c.stroke_width(2)
        };
        let anno = if line.dashed {
            chart
                .draw_series(DashedLineSeries::new(pts.clone(), 6, 4, style))
                .map_err(e)?
        } else {
            chart
                .draw_series(LineSeries::new(pts.clone(), style))
                .map_err(e)?
        };
        if let Some(label) = line.label.as_ref().filter(|_| text) {
            anno.label(label.as_str()).legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 16, y)], c.stroke_width(2))
            });
        }
        if line.markers {
            chart
                .draw_series(pts.iter().map(|&p| Circle::new(p, 3, c.filled())))
                .map_err(e)?;
        }
    }
    if text && panel.lines.iter().any(|l| l.label.is_some()) {
        chart
            .configure_series_labels()
            .label_font(text_style(11))
            .background_style(WHITE.mix(0.85))
            .border_style(RGBColor(200, 200, 200))
            .position(legend_corner(&pts, xr, yr))
            .draw()
            .map_err(e)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_legend_goes_where_the_lines_are_not() {
        // Falling lines fill the upper left and the lower right.
        let falling = vec![vec![(0.0, 1.0), (1.0, 0.0)]];
        let at = legend_corner(&falling, (0.0, 1.0), (0.0, 1.0));
        assert!(matches!(at, SeriesLabelPosition::UpperRight), "{at:?}");
        // A line along the top and one along the bottom: a middle side.
        let both = vec![
            vec![(0.0, 0.95), (1.0, 0.95)],
            vec![(0.0, 0.05), (1.0, 0.05)],
        ];
        let at = legend_corner(&both, (0.0, 1.0), (0.0, 1.0));
        assert!(matches!(at, SeriesLabelPosition::MiddleRight), "{at:?}");
    }
}
