//! Figures without a font: drawn without any text. This process registers
//! no font, so text drawn by mistake would fail (plotters finds no family).

#![cfg(feature = "plot")]
#![allow(clippy::unwrap_used)]

use bridgev2w_io::plot::bars::{BarFigure, Bars};
use bridgev2w_io::plot::lines::{Line, LineFigure, Panel};
use bridgev2w_io::plot::scatter::{PointSet, ScatterFigure};
use bridgev2w_io::plot::{write_png_with, Figure};

#[test]
fn every_kind_is_drawn_without_text() {
    let tmp = tempfile::tempdir().unwrap();
    let lines = LineFigure {
        panels: vec![Panel {
            title: "t".into(),
            x_desc: "x".into(),
            y_desc: "y".into(),
            log_y: true,
            lines: vec![Line::new("a", vec![(0.0, 1.0), (1.0, 0.1)], 0)],
        }],
        columns: 1,
        panel_size: (120, 90),
    };
    let bars = BarFigure {
        title: "t".into(),
        y_desc: "y".into(),
        categories: vec!["a".into()],
        series: vec![Bars {
            label: "s".into(),
            values: vec![0.5],
            color: 0,
        }],
        y_range: (0.0, 1.0),
        size: (120, 90),
    };
    let scatter = ScatterFigure {
        title: "t".into(),
        x_desc: "x".into(),
        y_desc: "y".into(),
        sets: vec![PointSet {
            label: "s".into(),
            points: vec![(0.2, 0.3), (0.8, 0.7)],
            color: 0,
        }],
        range: (0.0, 1.0),
        size: (120, 120),
    };
    let figures: [&dyn Figure; 3] = [&lines, &bars, &scatter];
    for (i, fig) in figures.into_iter().enumerate() {
        let path = tmp.path().join(format!("{i}.png"));
        write_png_with(&path, fig, false).unwrap();
        let (w, h, rgb) = bridgev2w_io::png::decode_rgb8(&std::fs::read(&path).unwrap()).unwrap();
        assert_eq!((w, h), fig.size());
        assert!(rgb.iter().any(|&v| v != 255));
    }
    // The same with text fails here, where no font is registered: the
    // no-text path above really draws none.
    let e = write_png_with(&tmp.path().join("t.png"), &bars, true).unwrap_err();
    assert!(e.to_string().contains("t.png"), "{e}");
}
