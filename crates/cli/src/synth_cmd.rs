//! `bridgev2w synth`: the synthetic tabletop dataset (LeRobot v3.0).

use crate::masks_cmd::progress_bar;
use anyhow::{bail, Result};
use bridgev2w_data::synth::{plan, write_dataset, Engine, Perturbation, SynthConfig, Task};
use std::path::PathBuf;

/// Arguments of `synth`.
#[derive(Debug, clap::Args)]
pub struct SynthArgs {
    /// Output dataset directory (must not exist; written to a temporary folder beside it, then renamed).
    #[arg(long)]
    out: PathBuf,
    /// Built-in robot of the synthetic world: franka, franka-robotiq or dual-arm.
    #[arg(long, default_value = "franka")]
    robot: String,
    /// Episodes per split: one number for all four splits, or four
    /// comma-separated numbers for train,test,unseen_camera,unseen_scene.
    #[arg(long, default_value = "8,2,2,2")]
    episodes_per_split: String,
    /// Frames per clip.
    #[arg(long, default_value_t = 25)]
    frames: usize,
    /// Image width (pixels, even).
    #[arg(long, default_value_t = 96)]
    width: u32,
    /// Image height (pixels, even).
    #[arg(long, default_value_t = 64)]
    height: u32,
    /// Frames per second of the videos.
    #[arg(long, default_value_t = 10)]
    fps: u32,
    /// Dataset seed (same seed, same bytes).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Comma-separated tasks (reach, push, pick_place, play), assigned round-robin;
    /// repeat a task to weigh it (e.g. `reach,push,pick_place,play,play,play`).
    #[arg(long, default_value = "reach,push,pick_place")]
    tasks: String,
    /// Perturbed demonstrations: this fraction of the train split's reach,
    /// push and pick_place episodes get one offset added to every action's
    /// position (normal, --perturb-mm per axis); the world executes them,
    /// so some fail the task (recorded per episode in meta/synth.json).
    #[arg(long, default_value_t = 0.0, value_name = "FRACTION")]
    perturbed_fraction: f64,
    /// Standard deviation of the perturbed demonstrations' offset (mm).
    #[arg(long, default_value_t = 30.0, value_name = "MM")]
    perturb_mm: f64,
    /// What simulates and renders: `builtin` (this project's world: contact
    /// rules, flat shading; fast) or `mujoco` (MuJoCo's physics and renderer,
    /// the robot's real meshes; needs scripts/setup-mujoco-venv.sh; the
    /// masks checked against MuJoCo's segmentation).
    #[arg(long, default_value_t = Engine::Builtin)]
    engine: Engine,
}

fn parse_counts(s: &str) -> Result<[usize; 4]> {
    let v: Vec<usize> = s
        .split(',')
        .map(|x| x.trim().parse::<usize>())
        .collect::<Result<_, _>>()
        .map_err(|e| anyhow::anyhow!("--episodes-per-split {s:?}: {e}"))?;
    match v.as_slice() {
        [n] => Ok([*n; 4]),
        [a, b, c, d] => Ok([*a, *b, *c, *d]),
        _ => bail!("--episodes-per-split {s:?}: give 1 or 4 comma-separated numbers (train,test,unseen_camera,unseen_scene)"),
    }
}

pub fn run(args: &SynthArgs) -> Result<()> {
    let tasks = args
        .tasks
        .split(',')
        .map(|t| {
            Task::parse(t.trim()).ok_or_else(|| {
                anyhow::anyhow!("--tasks: unknown task {t:?} (reach, push, pick_place, play)")
            })
        })
        .collect::<Result<Vec<_>>>()?;
    let config = SynthConfig {
        robot: args.robot.clone(),
        frames: args.frames,
        width: args.width,
        height: args.height,
        fps: args.fps,
        seed: args.seed,
        tasks,
        episodes_per_split: parse_counts(&args.episodes_per_split)?,
        perturb: Perturbation {
            fraction: args.perturbed_fraction,
            offset_mm: args.perturb_mm,
        },
        engine: args.engine,
    };
    config.validate()?;
    let n = plan(&config).len();
    if n == 0 {
        bail!(
            "--episodes-per-split {}: no episodes to generate",
            args.episodes_per_split
        );
    }
    let pb = progress_bar(n, "rendering episodes");
    let summary = write_dataset(&config, &args.out, &|| pb.inc(1))?;
    pb.finish_and_clear();
    crate::print_stdout(&summary.report(&config))
}
