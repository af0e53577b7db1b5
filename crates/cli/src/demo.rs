//! `bridgev2w demo`: the built-in Franka doing a pick-and-place (masks,
//! labels, PNGs, a GIF overlay), then the shipped world model's prediction
//! (`bridgev2w_train::demo`; its options are the flags).

use crate::masks_cmd::progress_bar;
use anyhow::Result;
use bridgev2w_train::demo::{run_demo, DemoOptions};

pub fn run(options: &DemoOptions) -> Result<()> {
    options.validate()?;
    let frames = options.frames as u64;
    let pb = progress_bar(frames as usize, "rendering masks");
    let tick = || {
        pb.inc(1);
        if pb.position() >= frames {
            pb.finish_and_clear();
        }
    };
    let report = run_demo(options, &tick);
    pb.finish_and_clear();
    let report = report?;
    if let Some(w) = &report.warning {
        eprintln!("{w}");
    }
    crate::print_stdout(&(report.lines().join("\n") + "\n"))
}
