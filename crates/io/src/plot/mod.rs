//! Figures of the results files (`eval-report`, `plan-report`): line
//! panels ([`lines`]), grouped bars ([`bars`]) and scatter plots with a
//! fitted line ([`scatter`]), drawn with plotters' bitmap backend and
//! written as PNG next to the results file ([`FigureDir`]). Text needs a
//! font found at run time ([`font`]); without one the figures are drawn
//! without text.

pub mod bars;
pub mod font;
pub mod lines;
pub mod scatter;

use crate::FileError;
use plotters::prelude::*;
use std::path::{Component, Path, PathBuf};

pub use font::{missing_font_warning, text_font, FONT_ENV};

/// Errors of the figures: each names the figure's file or the font.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// The font named by [`FONT_ENV`] cannot be used.
    #[error("{0}")]
    Font(String),
    /// Nothing to draw, or data that does not fit the figure.
    #[error("{}: {message}", path.display())]
    Data {
        /// The figure's file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// plotters failed to draw.
    #[error("drawing {}: {message}", path.display())]
    Draw {
        /// The figure's file.
        path: PathBuf,
        /// plotters' message.
        message: String,
    },
    /// The PNG could not be written.
    #[error(transparent)]
    File(#[from] FileError),
}

/// Result of this module.
pub type Result<T> = std::result::Result<T, PlotError>;

/// A figure: its size in pixels and how to draw it on a white canvas.
pub trait Figure {
    /// Width and height in pixels.
    fn size(&self) -> (u32, u32);
    /// Draws on `root`; `text`: whether a font is registered (without one,
    /// nothing that needs text may be drawn). An error is plotters' message
    /// or a data problem.
    fn draw(&self, root: &Canvas<'_>, text: bool) -> std::result::Result<(), String>;
}

/// The drawing area of a figure.
pub type Canvas<'a> = DrawingArea<BitMapBackend<'a>, plotters::coord::Shift>;

/// Draws `figure` and writes it to `path` as an RGB PNG (folders created,
/// written atomically), with text when a font is found ([`text_font`]).
pub fn write_png(path: &Path, figure: &dyn Figure) -> Result<()> {
    let text = text_font()?.is_some();
    write_png_with(path, figure, text)
}

/// [`write_png`] with or without text, whatever the font.
pub fn write_png_with(path: &Path, figure: &dyn Figure, text: bool) -> Result<()> {
    let (w, h) = figure.size();
    let mut buf = vec![255u8; w as usize * h as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        let drawn = root
            .fill(&WHITE)
            .map_err(|e| e.to_string())
            .and_then(|()| figure.draw(&root, text))
            .and_then(|()| root.present().map_err(|e| e.to_string()));
        drawn.map_err(|message| PlotError::Draw {
            path: path.to_path_buf(),
            message,
        })?;
    }
    let png = crate::png::encode_rgb8_small(w, h, &buf);
    crate::atomic::write_atomic_creating_dirs(path, &png)?;
    Ok(())
}

/// A written figure's size and the share of non-white pixels in its middle
/// half (the plot area): what a check that a figure is not blank reads.
pub fn ink_share(path: &Path) -> Result<((u32, u32), f64)> {
    let bad = |message: String| PlotError::Data {
        path: path.to_path_buf(),
        message,
    };
    let bytes = std::fs::read(path).map_err(|e| bad(e.to_string()))?;
    let (w, h, rgb) = crate::png::decode_rgb8(&bytes).map_err(bad)?;
    let (mut inked, mut all) = (0usize, 0usize);
    for y in h / 4..3 * h / 4 {
        for x in w / 4..3 * w / 4 {
            let i = (y * w + x) as usize * 3;
            all += 1;
            inked += usize::from(rgb[i..i + 3] != [255, 255, 255]);
        }
    }
    Ok(((w, h), inked as f64 / all.max(1) as f64))
}

/// Where a results file's figures go and how the file links them: the
/// folder named after the file, `figures/` in it (`docs/results.md` ->
/// `docs/results/figures/`, linked as `results/figures/NAME`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FigureDir {
    /// The folder the PNGs are written to.
    pub dir: PathBuf,
    /// The results file they are linked from.
    pub results: PathBuf,
}

impl FigureDir {
    /// The figures of `results` (a markdown file).
    pub fn next_to(results: &Path) -> Self {
        Self {
            dir: results.with_extension("").join("figures"),
            results: results.to_path_buf(),
        }
    }

    /// The file of figure `name` (e.g. `loss-curves.png`).
    pub fn path(&self, name: &str) -> PathBuf {
        self.dir.join(name)
    }

    /// The markdown image of figure `name`, with `alt` text.
    pub fn image(&self, name: &str, alt: &str) -> String {
        format!("![{alt}]({})", link_from(&self.results, &self.path(name)))
    }
}

/// The relative link from markdown file `from` to `target` (`/`-separated;
/// `..` where `target` is outside `from`'s folder). Both are taken as they
/// are when both are relative or both absolute, else made absolute from the
/// working folder first.
pub fn link_from(from: &Path, target: &Path) -> String {
    let absolute = |p: &Path| {
        if p.is_absolute() {
            p.to_path_buf()
        } else {
            std::env::current_dir().map_or_else(|_| p.to_path_buf(), |d| d.join(p))
        }
    };
    let (from, target) = if from.is_absolute() == target.is_absolute() {
        (from.to_path_buf(), target.to_path_buf())
    } else {
        (absolute(from), absolute(target))
    };
    let parts = |p: &Path| -> Vec<String> {
        let mut out: Vec<String> = Vec::new();
        for c in p.components() {
            match c {
                Component::CurDir => {}
                Component::ParentDir if out.last().is_some_and(|l| l != "..") => {
                    out.pop();
                }
                c => out.push(c.as_os_str().to_string_lossy().into_owned()),
            }
        }
        out
    };
    let base = parts(from.parent().unwrap_or(Path::new("")));
    let to = parts(&target);
    let common = base.iter().zip(&to).take_while(|(a, b)| a == b).count();
    let mut link: Vec<String> = vec!["..".to_string(); base.len() - common];
    link.extend(to[common..].iter().cloned());
    link.join("/")
}

/// Distinct colours (Tableau 10), picked by index.
pub fn color(i: usize) -> RGBColor {
    const P: [(u8, u8, u8); 10] = [
        (31, 119, 180),
        (255, 127, 14),
        (44, 160, 44),
        (214, 39, 40),
        (148, 103, 189),
        (140, 86, 75),
        (227, 119, 194),
        (127, 127, 127),
        (188, 189, 34),
        (23, 190, 207),
    ];
    let (r, g, b) = P[i % P.len()];
    RGBColor(r, g, b)
}

/// The text style of size `px` (in the registered family).
pub(crate) fn text_style(px: u32) -> TextStyle<'static> {
    (font::FAMILY, px).into_font().color(&BLACK)
}

/// A chart builder on `area` in the house style: with `text`, the `title`
/// as its caption and room for the labels (`x_label_px` below the chart,
/// 60 pixels left of it); without, thin borders only.
pub(crate) fn chart_builder<'a, 'b, DB: DrawingBackend>(
    area: &'a DrawingArea<DB, plotters::coord::Shift>,
    margin_px: u32,
    title: &str,
    x_label_px: u32,
    text: bool,
) -> ChartBuilder<'a, 'b, DB> {
    let mut builder = ChartBuilder::on(area);
    builder.margin(margin_px);
    if text {
        builder
            .caption(title, text_style(16))
            .x_label_area_size(x_label_px)
            .y_label_area_size(60);
    } else {
        builder.x_label_area_size(8).y_label_area_size(8);
    }
    builder
}

/// The grid's minor and major lines.
pub(crate) const GRID_LIGHT: RGBColor = RGBColor(235, 235, 235);
pub(crate) const GRID_BOLD: RGBColor = RGBColor(215, 215, 215);

/// A chart over two `f64` axes.
pub(crate) type Chart2d<'a, DB> = ChartContext<
    'a,
    DB,
    Cartesian2d<plotters::coord::types::RangedCoordf64, plotters::coord::types::RangedCoordf64>,
>;

/// Draws `chart`'s grid in the house style: light lines, and with `text` six
/// labels per axis written by `x_fmt` / `y_fmt` and the axes described by
/// `x_desc` / `y_desc`; without, no labels.
pub(crate) fn draw_grid<DB: DrawingBackend>(
    chart: &mut Chart2d<'_, DB>,
    text: bool,
    (x_desc, y_desc): (&str, &str),
    x_fmt: &dyn Fn(&f64) -> String,
    y_fmt: &dyn Fn(&f64) -> String,
) -> std::result::Result<(), String> {
    let mut mesh = chart.configure_mesh();
    mesh.light_line_style(GRID_LIGHT).bold_line_style(GRID_BOLD);
    if text {
        mesh.label_style(text_style(12))
            .axis_desc_style(text_style(13))
            .x_desc(x_desc)
            .y_desc(y_desc)
            .x_label_formatter(x_fmt)
            .y_label_formatter(y_fmt)
            .x_labels(6)
            .y_labels(6);
    } else {
        mesh.x_labels(0).y_labels(0);
    }
    mesh.draw().map_err(|e| e.to_string())
}

/// The range `[lo, hi]` of `values` (finite ones), padded by 5% (and to a
/// non-empty span when all are equal); `None` when none is finite.
pub(crate) fn padded_range(values: impl IntoIterator<Item = f64>) -> Option<(f64, f64)> {
    let (lo, hi) = values
        .into_iter()
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
    if lo > hi {
        return None;
    }
    let pad = if hi > lo {
        0.05 * (hi - lo)
    } else {
        0.5 * lo.abs().max(1.0)
    };
    Some((lo - pad, hi + pad))
}

/// A number as an axis label: up to 3 significant digits, no trailing zeros.
pub(crate) fn tick(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        return "0".into();
    }
    let digits = (2 - v.abs().log10().floor() as i32).clamp(0, 6) as usize;
    let s = format!("{v:.digits$}");
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod path_tests {
    use super::*;

    #[test]
    fn figures_sit_in_the_folder_named_after_the_results_file() {
        let f = FigureDir::next_to(Path::new("docs/results.md"));
        assert_eq!(f.dir, Path::new("docs/results/figures"));
        assert_eq!(
            f.image("loss.png", "Loss"),
            "![Loss](results/figures/loss.png)"
        );
        assert_eq!(
            link_from(
                Path::new("docs/results.md"),
                Path::new("runs/r/grids/test.gif")
            ),
            "../runs/r/grids/test.gif"
        );
        assert_eq!(
            link_from(Path::new("/a/b/r.md"), Path::new("/a/c/./d.gif")),
            "../c/d.gif"
        );
        assert_eq!(
            link_from(Path::new("r.md"), Path::new("x/y.gif")),
            "x/y.gif"
        );
    }

    #[test]
    fn ticks_and_ranges() {
        assert_eq!(tick(0.1234), "0.123");
        assert_eq!(tick(25.0), "25");
        assert_eq!(tick(1500.0), "1500");
        assert_eq!(tick(0.5), "0.5");
        assert_eq!(padded_range([1.0, 3.0]), Some((0.9, 3.1)));
        assert_eq!(padded_range([2.0]), Some((1.0, 3.0)));
        assert_eq!(padded_range([f64::NAN]), None);
    }
}

#[cfg(test)]
pub(crate) mod tests;
