//! `bridgev2w`: the command-line tool.

mod bench;
mod calibrate_cmd;
mod convert_cmd;
mod demo;
mod eval_cmd;
mod export_lora_cmd;
mod grid_cmd;
mod masks_cmd;
mod overlay_cmd;
mod parity_cmd;
mod plan_cmd;
mod predict_cmd;
mod progress;
mod report;
mod robot_info;
mod synth_cmd;
mod train_cmd;

use anyhow::Result;
use clap::{Parser, Subcommand};

/// BridgeV2W: action-conditioned embodied world model.
#[derive(Debug, Parser)]
#[command(name = "bridgev2w", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Render embodiment masks for a joint or end-effector action trajectory.
    Masks(masks_cmd::MasksArgs),
    /// Draw rendered masks over a camera's real frames (PNG, GIF) and score them against a ground truth.
    Overlay(overlay_cmd::OverlayArgs),
    /// Calibrate a fixed camera (pose, focal lengths) from episodes' video and joints: the robot's own motion.
    Calibrate(calibrate_cmd::CalibrateArgs),
    /// Measure `calibrate` on synthetic cameras whose truth is known (position, angle, focal errors).
    CalibrateStudy(calibrate_cmd::CalibrateStudyArgs),
    /// Print a robot's links, actuated joints (the --joints column order) and end effectors.
    RobotInfo(robot_info::RobotInfoArgs),
    /// Run the built-in demo: the Franka doing a pick, masks and a GIF overlay in ./demo-out/.
    Demo(bridgev2w_train::demo::DemoOptions),
    /// Benchmarks against peers measured in the same run.
    #[command(subcommand)]
    Bench(bench::BenchCommand),
    /// Check the world model against diffusers on parity fixtures (scripts/parity/).
    Parity(parity_cmd::ParityArgs),
    /// Video metrics (PSNR, SSIM, Mask-IoU, ...) between predicted and ground-truth videos.
    Eval(eval_cmd::EvalArgs),
    /// Predict the video a mask sequence causes, from a first frame (the world model).
    Predict(predict_cmd::PredictArgs),
    /// Write a BridgeV2W weights file's backbone LoRA as diffusers' pytorch_lora_weights.safetensors.
    ExportLora(export_lora_cmd::ExportLoraArgs),
    /// Policy-evaluation metrics (MMRV, Pearson r) between real and world-model success rates.
    EvalPolicy(eval_cmd::EvalPolicyArgs),
    /// Render a synthetic tabletop dataset (RGB clips, GT masks, actions, cameras) in the LeRobot v3.0 layout.
    Synth(synth_cmd::SynthArgs),
    /// Convert raw DROID / AgiBot World episodes to a training dataset with calc masks (LeRobot v3.0).
    Convert(convert_cmd::ConvertArgs),
    /// Train BridgeV2W (ControlNet + LoRA) on a dataset with the paper's losses (CONFIG.toml).
    Train(train_cmd::TrainArgs),
    /// Score a trained run's predictions per split (PSNR, SSIM, Mask-IoU) against copying the first frame.
    EvalRun(train_cmd::EvalRunArgs),
    /// Write the video-prediction table (paper layout) of several eval-run --json files to docs/results.md.
    EvalReport(report::EvalReportArgs),
    /// Side-by-side GIFs per split: first frame | masks | each run's prediction | ground truth.
    EvalGrid(grid_cmd::EvalGridArgs),
    /// Goal-image CEM-MPC planning executed in the synthetic world, vs random actions.
    Plan(plan_cmd::plan::PlanArgs),
    /// Does a model's goal distance order candidate actions as the synthetic world does (Spearman)?
    PlanFidelity(plan_cmd::fidelity::PlanFidelityArgs),
    /// Policy evaluation by autoregressive world-model rollouts vs synthetic-world success.
    EvalPolicyRollout(plan_cmd::rollout::EvalRolloutArgs),
    /// Drift of autoregressive rollouts from the synthetic world over many chunks (PSNR/SSIM by chunk).
    EvalDrift(bridgev2w_plan::experiment::DriftOptions),
    /// Run planning on all tasks and the policy evaluation; write docs/results.md.
    PlanReport(plan_cmd::report::PlanReportArgs),
}

fn main() -> Result<()> {
    // libtorch's CPU allocator backs large tensors with transparent huge
    // pages when THP_MEM_ALLOC_ENABLE=1: fewer page faults (`bench model`
    // 5-10% faster, medians in docs/benchmarks.md). A user's own setting
    // wins; set before any thread or tensor exists. Child processes (the
    // bench's diffusers peer) inherit it, so comparisons stay like for like.
    if std::env::var_os("THP_MEM_ALLOC_ENABLE").is_none() {
        std::env::set_var("THP_MEM_ALLOC_ENABLE", "1");
    }
    // Freed tensor memory is kept for reuse instead of going back to the
    // kernel (which page-faults and zeroes it again on the next forward
    // pass): BRIDGEV2W_CPU_CACHE_MB caps the free memory it holds (default
    // a quarter of the memory within 2-8 GiB; 0 turns it off). Measured in
    // docs/benchmarks.md.
    match bridgev2w_torch_ext::cpu_cache::limit_from_env().map_err(anyhow::Error::msg)? {
        0 => {}
        limit => bridgev2w_torch_ext::cpu_cache::install(limit),
    }
    // bf16 linear layers and convolutions on a CPU without bf16 arithmetic
    // run widened to f32 (several times faster there; docs/benchmarks.md):
    // BRIDGEV2W_CPU_BF16=auto|native|f32, default auto.
    bridgev2w_world_model::cpu_bf16::init_from_env()?;
    // Linear layers outside autograd run on oneDNN with weights packed once
    // (f32 ones stay on MKL on an Intel CPU; docs/benchmarks.md):
    // BRIDGEV2W_CPU_LINEAR=auto|onednn|onednn-bf16|aten.
    bridgev2w_world_model::cpu_linear::init_from_env()?;
    // bf16 attention on a CPU with AVX512-BF16 runs on oneDNN's bf16
    // micro-kernel (docs/benchmarks.md): BRIDGEV2W_CPU_ATTENTION=auto|onednn|aten.
    bridgev2w_world_model::cpu_attention::init_from_env()?;
    let cli = Cli::parse();
    match cli.command {
        Command::Masks(a) => masks_cmd::run(&a),
        Command::Overlay(a) => overlay_cmd::run(&a),
        Command::Calibrate(a) => calibrate_cmd::run(&a),
        Command::CalibrateStudy(a) => calibrate_cmd::run_study(&a),
        Command::RobotInfo(a) => robot_info::run(&a),
        Command::Demo(a) => demo::run(&a),
        Command::Bench(b) => bench::run(&b),
        Command::Parity(a) => parity_cmd::run(&a),
        Command::Eval(a) => eval_cmd::run_eval(&a),
        Command::EvalPolicy(a) => eval_cmd::run_eval_policy(&a),
        Command::Predict(a) => predict_cmd::run(&a),
        Command::ExportLora(a) => export_lora_cmd::run(&a),
        Command::Synth(a) => synth_cmd::run(&a),
        Command::Convert(a) => convert_cmd::run(&a),
        Command::Train(a) => train_cmd::run(&a),
        Command::EvalRun(a) => train_cmd::run_eval_run(&a),
        Command::EvalReport(a) => report::run_eval_report(&a),
        Command::EvalGrid(a) => grid_cmd::run(&a),
        Command::Plan(a) => plan_cmd::plan::run(&a),
        Command::PlanFidelity(a) => plan_cmd::fidelity::run(&a),
        Command::EvalPolicyRollout(a) => plan_cmd::rollout::run(&a),
        Command::EvalDrift(a) => plan_cmd::drift::run(&a),
        Command::PlanReport(a) => plan_cmd::report::run(&a),
    }
}

/// Writes to stdout; a closed pipe (`| head`) ends the output quietly.
pub fn print_stdout(text: &str) -> Result<()> {
    use std::io::Write;
    let mut stdout = std::io::stdout().lock();
    match stdout
        .write_all(text.as_bytes())
        .and_then(|()| stdout.flush())
    {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => Err(e.into()),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    /// clap's own checks of every command's flags (unique names, valid
    /// defaults and relations), which otherwise only fire when a command
    /// is run: the options that the libraries define as flags are flattened
    /// beside the commands' own.
    #[test]
    fn every_command_line_is_well_formed() {
        use clap::CommandFactory;
        super::Cli::command().debug_assert();
    }
}
