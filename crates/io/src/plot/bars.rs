//! Grouped bars: a group per category (a task), a bar per series (a
//! planner, the random baseline), each labelled under its group.

use super::{chart_builder, color, text_style, tick, Canvas, Figure, GRID_BOLD, GRID_LIGHT};
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

/// One series of bars: a value per category.
#[derive(Debug, Clone, PartialEq)]
pub struct Bars {
    /// The legend's text.
    pub label: String,
    /// A value per category, in the categories' order.
    pub values: Vec<f64>,
    /// Palette index ([`super::color`]).
    pub color: usize,
}

/// A grouped bar chart.
#[derive(Debug, Clone, PartialEq)]
pub struct BarFigure {
    /// Drawn above the chart.
    pub title: String,
    /// The y axis's description.
    pub y_desc: String,
    /// The groups, left to right.
    pub categories: Vec<String>,
    /// The bars of each group, left to right.
    pub series: Vec<Bars>,
    /// The y axis's range.
    pub y_range: (f64, f64),
    /// Size in pixels.
    pub size: (u32, u32),
}

impl Figure for BarFigure {
    fn size(&self) -> (u32, u32) {
        self.size
    }

    fn draw(&self, root: &Canvas<'_>, text: bool) -> Result<(), String> {
        let n = self.categories.len();
        if n == 0 || self.series.is_empty() {
            return Err("no bars to draw".into());
        }
        if let Some(s) = self.series.iter().find(|s| s.values.len() != n) {
            return Err(format!(
                "series `{}` has {} values for {n} categories",
                s.label,
                s.values.len()
            ));
        }
        let e = |e: DrawingAreaErrorKind<_>| e.to_string();
        let (lo, hi) = self.y_range;
        let mut chart = chart_builder(root, 12, &self.title, 30, text)
            .build_cartesian_2d(-0.5..(n as f64 - 0.5), lo..hi)
            .map_err(e)?;
        let y_fmt = |v: &f64| tick(*v);
        let mut mesh = chart.configure_mesh();
        mesh.disable_x_mesh()
            .x_labels(0)
            .light_line_style(GRID_LIGHT)
            .bold_line_style(GRID_BOLD);
        if text {
            mesh.label_style(text_style(12))
                .axis_desc_style(text_style(13))
                .y_desc(self.y_desc.as_str())
                .y_label_formatter(&y_fmt)
                .y_labels(6);
        } else {
            mesh.y_labels(0);
        }
        mesh.draw().map_err(e)?;
        let k = self.series.len() as f64;
        let width = 0.8 / k;
        for (j, s) in self.series.iter().enumerate() {
            let c = color(s.color);
            let x0 = |i: usize| i as f64 - 0.4 + j as f64 * width;
            let anno = chart
                .draw_series(
                    s.values
                        .iter()
                        .enumerate()
                        .filter(|(_, v)| v.is_finite())
                        .map(|(i, &v)| {
                            Rectangle::new(
                                [
                                    (x0(i) + 0.05 * width, lo.max(0.0)),
                                    (x0(i) + 0.95 * width, v),
                                ],
                                c.filled(),
                            )
                        }),
                )
                .map_err(e)?;
            if text {
                anno.label(s.label.as_str()).legend(move |(x, y)| {
                    Rectangle::new([(x, y - 5), (x + 12, y + 5)], c.filled())
                });
            }
        }
        if text {
            for (i, name) in self.categories.iter().enumerate() {
                let (x, y) = chart.backend_coord(&(i as f64, lo));
                root.draw(&Text::new(
                    name.clone(),
                    (x, y + 8),
                    text_style(13).pos(Pos::new(HPos::Center, VPos::Top)),
                ))
                .map_err(e)?;
            }
            chart
                .configure_series_labels()
                .label_font(text_style(11))
                .background_style(WHITE.mix(0.85))
                .border_style(RGBColor(200, 200, 200))
                .position(SeriesLabelPosition::UpperRight)
                .draw()
                .map_err(e)?;
        }
        Ok(())
    }
}
