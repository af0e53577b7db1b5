//! `bridgev2w eval-drift`: how far autoregressive rollouts drift from the
//! synthetic world over many chunks ([`bridgev2w_plan::experiment::drift`]).

use super::{parse_split, parse_task, progress, ModelArgs};
use anyhow::Result;
use bridgev2w_data::synth::{Split, Task};
use bridgev2w_plan::experiment::{drift_study, DriftOptions};

#[derive(Debug, Clone, clap::Args)]
pub struct DriftArgs {
    /// reach, push or pick_place: whose expert episodes are replayed.
    #[arg(long, value_parser = parse_task, default_value = "pick_place")]
    pub task: Task,
    /// Episodes (task instances of the split).
    #[arg(long, default_value_t = 4)]
    pub trials: usize,
    #[command(flatten)]
    pub model: ModelArgs,
    /// Chunks per rollout, each predicted from the model's own last frame
    /// (5: five times the clip).
    #[arg(long, default_value_t = 5)]
    pub chunks: usize,
    /// Also roll out with the static scene kept outside the swept region,
    /// dilated by this many pixels (the lever against drift), side by side.
    #[arg(long, value_name = "MARGIN_PX")]
    pub compare_keep_static: Option<u32>,
    /// Split of the task instances.
    #[arg(long, default_value = "test", value_parser = parse_split)]
    pub split: Split,
    /// Seed of the world.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

pub fn run(a: &DriftArgs) -> Result<()> {
    let o = DriftOptions {
        task: a.task,
        trials: a.trials,
        model: (&a.model).into(),
        chunks: a.chunks,
        keep_static_margin_px: a.compare_keep_static,
        split: a.split,
        seed: a.seed,
    };
    let r = drift_study(&o, &mut progress)?;
    crate::print_stdout(&r.markdown())
}
