//! What tch 0.24 does not expose, kept to the minimum of unsafe code:
//!
//! * [`autocast`]: libtorch's automatic mixed precision with a chosen device
//!   type (CPU or CUDA) and dtype (bf16, fp16), through a small C++ shim over
//!   `ATen/autocast_mode.h` (tch's own `tch::autocast` is CUDA-only and fixed
//!   to fp16). The safe API is an RAII [`AutocastGuard`] that restores the
//!   previous state when dropped, also on an early return or a panic.
//! * [`nccl`]: NCCL loaded at run time with `dlopen` (no link-time
//!   dependency, so CPU-only machines build and run the same binary).

pub mod autocast;
pub mod nccl;

pub use autocast::{autocast, AutocastDevice, AutocastDtype, AutocastGuard};

/// Errors of this crate.
#[derive(Debug, thiserror::Error)]
pub enum TorchExtError {
    /// libtorch's autocast state could not be read or changed.
    #[error("autocast: {0}")]
    Autocast(String),
    /// NCCL could not be loaded or one of its calls failed.
    #[error("nccl: {0}")]
    Nccl(String),
}

/// Result of this crate.
pub type Result<T> = std::result::Result<T, TorchExtError>;
