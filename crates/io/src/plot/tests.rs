//! Each figure kind written, decoded, of the expected size and not blank,
//! with text when a font is found (see also `tests/plot_without_font.rs`).

#![allow(clippy::unwrap_used)]

use super::bars::{BarFigure, Bars};
use super::lines::{Line, LineFigure, Panel};
use super::scatter::{least_squares, PointSet, ScatterFigure};
use super::*;

pub(crate) fn line_figure() -> LineFigure {
    let panel = |title: &str, log_y| Panel {
        title: title.into(),
        x_desc: "step".into(),
        y_desc: "loss".into(),
        log_y,
        lines: vec![
            Line::new(
                "loss",
                (1..50).map(|i| (i as f64, 1.0 / i as f64)).collect(),
                0,
            ),
            Line {
                dashed: true,
                markers: true,
                ..Line::new("bound", vec![(1.0, 0.05), (49.0, 0.05)], 1)
            },
        ],
    };
    LineFigure {
        panels: vec![panel("vae", true), panel("prior", false), panel("x", false)],
        columns: 2,
        panel_size: (200, 150),
    }
}

pub(crate) fn bar_figure() -> BarFigure {
    BarFigure {
        title: "planning".into(),
        y_desc: "success".into(),
        categories: vec!["reach".into(), "push".into()],
        series: vec![
            Bars {
                label: "planner".into(),
                values: vec![0.8, 0.4],
                color: 0,
            },
            Bars {
                label: "random".into(),
                values: vec![0.1, 0.0],
                color: 7,
            },
        ],
        y_range: (0.0, 1.0),
        size: (240, 180),
    }
}

pub(crate) fn scatter_figure() -> ScatterFigure {
    ScatterFigure {
        title: "policies".into(),
        x_desc: "world model".into(),
        y_desc: "real".into(),
        sets: vec![PointSet {
            label: "perfect (r = 0.9)".into(),
            points: vec![(0.9, 1.0), (0.5, 0.6), (0.1, 0.2)],
            color: 0,
        }],
        range: (-0.05, 1.05),
        size: (200, 200),
    }
}

#[test]
fn every_kind_is_written_at_its_size_and_not_blank() {
    let tmp = tempfile::tempdir().unwrap();
    let figures: [(&str, &dyn Figure, (u32, u32)); 3] = [
        ("lines.png", &line_figure(), (400, 300)),
        ("bars.png", &bar_figure(), (240, 180)),
        ("scatter.png", &scatter_figure(), (200, 200)),
    ];
    for (name, fig, size) in figures {
        let path = tmp.path().join("figures").join(name);
        write_png(&path, fig).unwrap();
        let (got, share) = ink_share(&path).unwrap();
        assert_eq!(got, size, "{name}");
        assert!(share > 0.01, "{name}: {share} of the plot area drawn");
    }
}

#[test]
fn bad_data_names_the_figure() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("bars.png");
    let mut fig = bar_figure();
    fig.series[1].values.pop();
    let e = write_png(&path, &fig).unwrap_err().to_string();
    assert!(
        e.contains("bars.png") && e.contains("1 values for 2 categories"),
        "{e}"
    );
    let empty = LineFigure {
        panels: vec![Panel {
            lines: vec![Line::new("nan", vec![(0.0, f64::NAN)], 0)],
            ..line_figure().panels[0].clone()
        }],
        ..line_figure()
    };
    let e = write_png(&path, &empty).unwrap_err().to_string();
    assert!(e.contains("no finite points"), "{e}");
    assert!(!path.exists());
}

#[test]
fn the_fitted_line_is_least_squares() {
    let (a, b) = least_squares(&[(0.0, 1.0), (1.0, 3.0), (2.0, 5.0)]).unwrap();
    assert!((a - 1.0).abs() < 1e-12 && (b - 2.0).abs() < 1e-12);
    assert_eq!(least_squares(&[(0.5, 0.0), (0.5, 1.0)]), None);
    assert_eq!(least_squares(&[(0.5, 0.0)]), None);
}

#[test]
fn the_scatter_legend_is_a_strip_below_the_chart() {
    // A set's colour appears in the legend strip (its line), and a point in
    // the chart's top-left corner, where the legend used to sit, is drawn.
    if !matches!(text_font(), Ok(Some(_))) {
        return; // no legend without a font (tests/plot_without_font.rs)
    }
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("scatter.png");
    let mut fig = scatter_figure();
    fig.size = (320, 320);
    fig.sets[0].points = vec![(0.0, 1.0), (1.0, 0.0)];
    fig.sets.push(PointSet {
        label: "trained (r = 0)".into(),
        points: vec![(0.0, 0.5)],
        color: 1,
    });
    write_png(&path, &fig).unwrap();
    let (w, h, rgb) = crate::png::decode_rgb8(&std::fs::read(&path).unwrap()).unwrap();
    let c = color(1);
    let has = |ys: std::ops::Range<u32>, xs: std::ops::Range<u32>| {
        ys.clone().any(|y| {
            xs.clone().any(|x| {
                let i = (y * w + x) as usize * 3;
                rgb[i..i + 3] == [c.0, c.1, c.2]
            })
        })
    };
    let strip = 3 * 18 + 8;
    assert!(
        has(h - strip..h, 0..w),
        "no legend line in the bottom strip"
    );
    let c0 = color(0);
    let top_left = (0..h / 3).any(|y| {
        (0..w / 3).any(|x| {
            let i = (y * w + x) as usize * 3;
            rgb[i..i + 3] == [c0.0, c0.1, c0.2]
        })
    });
    assert!(top_left, "the point at (0, 1) is hidden");
}
