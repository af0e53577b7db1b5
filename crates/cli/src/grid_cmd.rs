//! `bridgev2w eval-grid`: side-by-side videos of one or more trained runs
//! per split ([`bridgev2w_train::grid`]): first frame | masks | each run's
//! prediction | ground truth, the first clips a row each, as
//! `OUT/<split>.gif`.

use anyhow::Result;
use bridgev2w_train::grid::{write_grids_folder, GridOptions, GridRun};
use std::path::PathBuf;

/// Arguments of `eval-grid`.
#[derive(Debug, clap::Args)]
pub struct EvalGridArgs {
    /// The first run's training configuration (TOML).
    config: PathBuf,
    /// The first run's folder (its latest checkpoint) or a checkpoint folder.
    #[arg(long)]
    run: PathBuf,
    /// Another run drawn in the next column (e.g. the ablation next to
    /// BridgeV2W): its configuration and its folder; repeat for more.
    #[arg(long, num_args = 2, value_names = ["CONFIG", "RUN"])]
    compare: Vec<PathBuf>,
    /// The folder of the GIFs: OUT/<split>.gif (written to a temporary
    /// folder beside it, then renamed; an existing one is refused unless
    /// --overwrite).
    #[arg(long)]
    out: PathBuf,
    /// Replace an existing --out (as a whole, once the grids are written).
    #[arg(long)]
    overwrite: bool,
    /// Splits of the runs' dataset, comma-separated.
    #[arg(long, default_value = "test,unseen_camera,unseen_scene")]
    splits: String,
    /// Clips per grid (rows): the first clip of the first episodes.
    #[arg(long, default_value_t = 4)]
    clips: usize,
    #[command(flatten)]
    sampling: crate::train_cmd::SamplingArgs,
    /// The weights of each run: `averaged` or `raw`.
    #[arg(long, default_value = "averaged")]
    weights: bridgev2w_train::ema::RunWeights,
}

/// `bridgev2w eval-grid`.
pub fn run(a: &EvalGridArgs) -> Result<()> {
    let mut runs = vec![GridRun {
        config: a.config.clone(),
        run: a.run.clone(),
    }];
    runs.extend(a.compare.chunks(2).map(|c| GridRun {
        config: c[0].clone(),
        run: c[1].clone(),
    }));
    let o = GridOptions {
        runs,
        splits: crate::train_cmd::split_list(&a.splits)?,
        clips: a.clips,
        sampling: a.sampling.eval_options(),
        weights: a.weights,
        out: a.out.clone(),
    };
    let progress = crate::progress::TerminalProgress::default();
    let written = write_grids_folder(&o, a.overwrite, &progress)?;
    let lines: Vec<String> = written
        .iter()
        .map(|p| format!("wrote {}", p.display()))
        .collect();
    crate::print_stdout(&(lines.join("\n") + "\n"))
}
