//! Side-by-side videos: for a split, the first clips a row each, first
//! frame | masks | each run's prediction | ground truth, as an animated GIF
//! (`eval-run --grids` with one run; `eval-grid` with BridgeV2W next to
//! its ablation).

pub mod image;

use self::image::{grid_row, write_grid, GridRow};
use crate::ema::RunWeights;
use crate::evaluate::{frames, mask_frames, split_data, EvalOptions};
use crate::trainer::Trainer;
use crate::{Result, TrainError};
use bridgev2w_io::frame::RgbFrame;
use bridgev2w_io::progress::Progress;
use std::path::PathBuf;

/// A run of the grid: its training configuration and its folder (latest
/// checkpoint) or a checkpoint folder.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GridRun {
    /// The run's training configuration (TOML).
    pub config: PathBuf,
    /// The run folder or a checkpoint folder.
    pub run: PathBuf,
}

/// The most clips (rows) of a grid (`eval-grid --clips`, `eval-run
/// --grid-clips`): every row's frames are held until the GIF is written.
pub const MAX_GRID_CLIPS: usize = 1024;

/// What a grid of `runs` reads, for refusing an output that overlaps it:
/// each run's folder, its configuration and the datasets it names
/// (`data.dataset`, `data.mix[].dataset`). A configuration that cannot be
/// read adds no dataset here; loading the run names its error.
pub fn grid_inputs(runs: &[GridRun]) -> Vec<PathBuf> {
    let mut inputs = Vec::new();
    for r in runs {
        inputs.push(r.run.clone());
        inputs.push(r.config.clone());
        if let Ok(cfg) = crate::config::TrainConfig::from_file(&r.config) {
            inputs.push(cfg.data.dataset.clone());
            inputs.extend(cfg.data.mix.iter().map(|m| m.dataset.clone()));
        }
    }
    inputs
}

/// What `eval-grid` draws.
#[derive(Debug, Clone)]
pub struct GridOptions {
    /// The runs, a prediction column each, in order (BridgeV2W, then its
    /// ablation); all on the same dataset and clip size.
    pub runs: Vec<GridRun>,
    /// Splits, a GIF each.
    pub splits: Vec<String>,
    /// Clips (rows) per grid: the first clip of the first episodes.
    pub clips: usize,
    /// The sampling settings (steps, guidance, seed, first frame,
    /// strength; its `max_videos` and grid fields are not used).
    pub sampling: EvalOptions,
    /// Which weights of each run.
    pub weights: RunWeights,
    /// The folder of the GIFs: `<out>/<split>.gif`.
    pub out: PathBuf,
}

/// `eval-grid`'s job: the grids of [`write_grids`] written into a new
/// folder `o.out` as a transaction (a temporary folder beside it, renamed
/// when every grid is written); an existing `o.out` is refused unless
/// `overwrite`, and one that is, contains or is inside a run, its
/// configuration or its datasets always ([`grid_inputs`]). Returns the GIFs
/// at their final paths.
pub fn write_grids_folder(
    o: &GridOptions,
    overwrite: bool,
    progress: &dyn Progress,
) -> Result<Vec<PathBuf>> {
    let inputs = grid_inputs(&o.runs);
    let inputs: Vec<&std::path::Path> = inputs.iter().map(PathBuf::as_path).collect();
    let output_err = |e: bridgev2w_io::output::OutputError| TrainError::input("out", e.to_string());
    let out = bridgev2w_io::output::OutputDir::create_for(&o.out, overwrite, &inputs)
        .map_err(output_err)?;
    let staged = GridOptions {
        out: out.path().to_path_buf(),
        ..o.clone()
    };
    let written = write_grids(&staged, progress)?;
    let dir = out.commit().map_err(output_err)?;
    Ok(written
        .iter()
        .filter_map(|p| p.file_name())
        .map(|name| dir.join(name))
        .collect())
}

/// Draws a grid per split with every run's predictions and returns the
/// GIFs written. `progress` sees each split as a stage and a tick per clip.
pub fn write_grids(o: &GridOptions, progress: &dyn Progress) -> Result<Vec<PathBuf>> {
    if o.runs.is_empty() {
        return Err(TrainError::input("runs", "expected at least one run"));
    }
    if o.clips == 0 {
        return Err(TrainError::input("clips", "must be at least 1"));
    }
    bridgev2w_io::memory::at_most("clips", o.clips as u64, MAX_GRID_CLIPS as u64, "clips")?;
    let trainers = o
        .runs
        .iter()
        .map(|r| Trainer::load_run(&r.config, &r.run, o.weights).map(|(t, _)| t))
        .collect::<Result<Vec<Trainer>>>()?;
    let mut written = Vec::new();
    for split in &o.splits {
        progress.start(o.clips, &format!("grid of {split}"));
        let path = o.out.join(format!("{split}.gif"));
        let r = split_grid(o, &trainers, split, progress)
            .and_then(|(rows, size)| write_grid(&path, &rows, size))
            .map_err(TrainError::context(format!("split {split}")));
        progress.finish();
        r?;
        written.push(path);
    }
    Ok(written)
}

/// The rows of `split`'s grid and a panel's size.
fn split_grid(
    o: &GridOptions,
    trainers: &[Trainer],
    split: &str,
    progress: &dyn Progress,
) -> Result<(Vec<GridRow>, (usize, usize))> {
    let data = trainers
        .iter()
        .map(|t| split_data(t, split))
        .collect::<Result<Vec<_>>>()?;
    let n = o.clips.min(data[0].episodes.len());
    let mut rows = Vec::new();
    for i in 0..n {
        let mut gt = None;
        let mut preds = Vec::new();
        let mut masks = Vec::new();
        for ((trainer, d), run) in trainers.iter().zip(&data).zip(&o.runs) {
            let batch = d.clips(&[(i, 0)], trainer.model.device())?;
            let truth = frames(&batch.video)?;
            match &gt {
                None => {
                    masks = mask_frames(&batch.masks)?;
                    gt = Some(truth);
                }
                Some(first) if *first != truth => {
                    return Err(TrainError::input(
                        run.config.display().to_string(),
                        format!(
                            "clip {i} of split {split} differs from the first run's ({}): the runs of a grid must share the dataset and the clip size",
                            o.runs[0].config.display()
                        ),
                    ))
                }
                Some(_) => {}
            }
            preds.push(frames(
                &trainer.predict(&batch, &o.sampling.sample_options())?,
            )?);
        }
        let gt = gt.ok_or_else(|| TrainError::input("runs", "expected at least one run"))?;
        let refs: Vec<&[RgbFrame]> = preds.iter().map(Vec::as_slice).collect();
        rows.push(grid_row(&gt, &refs, &masks));
        progress.tick();
    }
    if rows.is_empty() {
        return Err(TrainError::input(
            format!("split {split}"),
            "has no episodes",
        ));
    }
    let d = &trainers[0].data;
    Ok((rows, (d.width, d.height)))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use bridgev2w_io::output::check_no_overlap;

    /// `eval-grid --out` inside a run's dataset is refused (issue 69): the
    /// datasets its configurations name are among its inputs.
    #[test]
    fn the_inputs_of_a_grid_are_its_runs_configs_and_datasets() {
        let tmp = tempfile::tempdir().unwrap();
        let data = tmp.path().join("data");
        let config = tmp.path().join("a.toml");
        std::fs::write(
            &config,
            format!(
                "[model]\nbackbone = \"random:tiny\"\n[data]\ndataset = {:?}\n\
                 [[data.mix]]\ndataset = \"other-data\"\n",
                data.display().to_string()
            ),
        )
        .unwrap();
        let runs = [
            GridRun {
                config: config.clone(),
                run: tmp.path().join("run-a"),
            },
            GridRun {
                config: tmp.path().join("missing.toml"),
                run: tmp.path().join("run-b"),
            },
        ];
        let inputs = grid_inputs(&runs);
        assert_eq!(
            inputs,
            [
                tmp.path().join("run-a"),
                config,
                data.clone(),
                PathBuf::from("other-data"),
                tmp.path().join("run-b"),
                tmp.path().join("missing.toml"),
            ]
        );
        let inputs: Vec<&std::path::Path> = inputs.iter().map(PathBuf::as_path).collect();
        let e = check_no_overlap(&data.join("grids"), &inputs).unwrap_err();
        assert!(e.to_string().contains("is inside the input"), "{e}");
        check_no_overlap(&tmp.path().join("grids"), &inputs).unwrap();
    }
}
