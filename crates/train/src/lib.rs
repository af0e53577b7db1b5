//! Training BridgeV2W: the paper's losses and the trainer (`bridgev2w train`).
//!
//! * [`losses::diffusion_loss`]: the v-prediction objective in `x0` space.
//! * [`losses::dynamics_loss`]: latent dynamics consistency over offsets `1..=K`.
//! * [`flow`]: the optical-flow loss (direction + magnitude on moving pixels)
//!   with a frozen, differentiable [`flow::FlowEstimator`] (RAFT, or a light
//!   Lucas-Kanade stand-in for CPU runs).
//! * [`score`]: video metrics between folders of predicted and ground-truth
//!   videos (`bridgev2w eval`); [`report`]: the video-prediction tables of
//!   `eval-run` results (`bridgev2w eval-report`).

pub mod action;
pub mod augment;
pub mod bench;
pub mod checkpoint;
pub mod config;
pub mod data;
pub mod decoded_flow;
pub mod demo;
pub mod distributed;
pub mod ema;
pub mod eval_run;
pub mod evaluate;
pub mod flow;
pub mod grid;
pub mod losses;
pub mod optim;
pub mod predict_files;
pub mod report;
pub mod run_dir;
pub mod score;
pub mod segmenter;
pub mod tensorboard;
pub mod trainer;

/// Errors of the training code.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// An input tensor or option that does not fit.
    #[error("{what}: {message}")]
    Input {
        /// What was wrong.
        what: String,
        /// Why, with the value and what was expected.
        message: String,
    },
    /// A loss term or the gradient norm became NaN or infinite.
    #[error("step {step}: non-finite {term} ({value}); training stopped, the checkpoints written before this step are kept. Check train.lr (lower it, or raise train.warmup_steps), train.grad_clip (0 turns clipping off) and the loss weights (train.lambda_dyn, train.lambda_flow, train.motion_loss_weight), then resume from a checkpoint")]
    NonFinite {
        /// The 0-based step.
        step: usize,
        /// Which term ("diffusion", "dynamics", "flow", "total", "gradient norm").
        term: String,
        /// Its value.
        value: f64,
    },
    /// A file could not be read or written.
    #[error("{}: {error}", path.display())]
    Io {
        /// The file.
        path: std::path::PathBuf,
        /// The error.
        error: std::io::Error,
    },
    /// An error while doing something named.
    #[error("{what}")]
    Context {
        /// What was being done.
        what: String,
        /// The error.
        #[source]
        source: Box<TrainError>,
    },
    /// A synthetic dataset's settings.
    #[error(transparent)]
    Synth(#[from] bridgev2w_data::synth::SynthError),
    /// Writing a synthetic dataset.
    #[error(transparent)]
    WriteDataset(#[from] bridgev2w_data::synth::WriteDatasetError),
    /// From the world model.
    #[error(transparent)]
    WorldModel(#[from] bridgev2w_world_model::error::WorldModelError),
    /// From the autocast / NCCL extensions.
    #[error(transparent)]
    TorchExt(#[from] bridgev2w_torch_ext::TorchExtError),
    /// From libtorch.
    #[error("torch: {0}")]
    Torch(#[from] tch::TchError),
    /// A run whose estimated memory exceeds what the machine has (refused
    /// before the data is read).
    #[error(transparent)]
    Memory(#[from] bridgev2w_io::memory::MemoryError),
    /// The device (or the CPU) ran out of memory.
    #[error("out of memory in {during}: {figures}\n{advice}")]
    OutOfMemory {
        /// What was running, with its shapes.
        during: String,
        /// libtorch's account: the allocation that failed and the memory in use.
        figures: String,
        /// What lowers the memory of what was running.
        advice: &'static str,
    },
}

impl TrainError {
    pub(crate) fn input(what: impl Into<String>, message: impl Into<String>) -> Self {
        Self::Input {
            what: what.into(),
            message: message.into(),
        }
    }
}

/// Runs `f`; a panic inside it (libtorch's ops panic on their errors, a
/// device's out-of-memory among them) becomes [`TrainError::Torch`] with
/// its message, without "panicked at" on stderr.
pub(crate) fn guarded<T>(f: impl FnOnce() -> Result<T>) -> Result<T> {
    bridgev2w_io::quiet_panic::catch_quiet(f)
        .unwrap_or_else(|panic| Err(TrainError::Torch(tch::TchError::Torch(panic))))
}

/// What lowers a training step's memory, for [`TrainError::OutOfMemory`].
pub const TRAIN_MEMORY_ADVICE: &str = "To lower a step's memory: `gradient_checkpointing = true` and `autocast = \"bf16\"` in [train], a smaller `train.batch_size`, fewer `data.frames` or a smaller `data.height` x `data.width`; with the flow loss on, smaller VAE tiles (`model.vae_tile = \"144x200\"`; a run may resume with them); on CUDA, PYTORCH_CUDA_ALLOC_CONF=expandable_segments:True lets libtorch's caching allocator reuse memory it holds in pieces";

/// What lowers `bench flow`'s memory, for [`TrainError::OutOfMemory`].
pub const BENCH_FLOW_MEMORY_ADVICE: &str =
    "Lower --frames or the size, tile the decode (--tile, e.g. 240x360), use --precision bf16 or --modes stepwise";

impl TrainError {
    /// An out-of-memory error from libtorch (directly or through the world
    /// model) as [`Self::OutOfMemory`] while `during()` (what ran, with its
    /// shapes), with `advice` (e.g. [`TRAIN_MEMORY_ADVICE`]); other errors
    /// unchanged.
    pub fn on_out_of_memory(self, during: impl FnOnce() -> String, advice: &'static str) -> Self {
        use bridgev2w_world_model::error::{out_of_memory_figures, WorldModelError};
        let figures = match &self {
            Self::Torch(e) | Self::WorldModel(WorldModelError::Torch(e)) => {
                out_of_memory_figures(&e.to_string())
            }
            Self::WorldModel(WorldModelError::OutOfMemory { figures, .. }) => Some(figures.clone()),
            _ => None,
        };
        match figures {
            Some(figures) => Self::OutOfMemory {
                during: during(),
                figures,
                advice,
            },
            None => self,
        }
    }

    /// Wraps an error with what was being done.
    pub(crate) fn context(what: String) -> impl FnOnce(TrainError) -> TrainError {
        move |e| TrainError::Context {
            what,
            source: Box::new(e),
        }
    }
}

/// Result of the training code.
pub type Result<T> = std::result::Result<T, TrainError>;
