//! `bridgev2w bench`: speed against peers measured in the same run. Each
//! subcommand's flags are the library bench's options (but `model`'s
//! precisions): it runs the bench and prints its report.

mod flow;
mod kinematics;
mod loader;
mod masks;
mod metrics;
mod model;

use anyhow::Result;

#[derive(Debug, clap::Subcommand)]
pub enum BenchCommand {
    /// Mask rendering: this renderer vs pybullet's getCameraImage (TinyRenderer) on
    /// pybullet's own franka_panda/panda.urdf with its OBJ meshes.
    Masks(bridgev2w_embodiment::bench::MasksBenchOptions),
    /// Forward kinematics poses/s and warm-started IK time per solve (built-in Franka).
    Kinematics(bridgev2w_embodiment::bench::KinematicsBenchOptions),
    /// PSNR + SSIM frames/s: bridgev2w-eval vs scikit-image on the same frames.
    Metrics(bridgev2w_eval::bench::MetricsBenchOptions),
    /// One transformer forward and one VAE encode/decode: this crate vs diffusers
    /// on the same configs, shapes, threads and precision (random weights).
    Model(model::ModelBench),
    /// Clip loader throughput (clips/s): decoding + masks (stored, rendered calc,
    /// cached calc) and batch assembly, on a dataset or a generated synthetic one.
    Loader(bridgev2w_train::bench::LoaderBenchOptions),
    /// The flow loss's decode and gradient through the VAE: autograd through the
    /// whole decode vs the recorded batch-by-batch backward, whole or unit by unit;
    /// seconds and peak memory.
    Flow(bridgev2w_train::bench::FlowBenchOptions),
}

pub fn run(cmd: &BenchCommand) -> Result<()> {
    match cmd {
        BenchCommand::Masks(a) => masks::run(a),
        BenchCommand::Kinematics(a) => kinematics::run(a),
        BenchCommand::Metrics(a) => metrics::run(a),
        BenchCommand::Model(a) => model::run(a),
        BenchCommand::Loader(a) => loader::run(a),
        BenchCommand::Flow(a) => flow::run(a),
    }
}
