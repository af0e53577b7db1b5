//! What tch 0.24 does not expose, kept to the minimum of unsafe code:
//!
//! * [`autocast`]: libtorch's automatic mixed precision with a chosen device
//!   type (CPU or CUDA) and dtype (bf16, fp16), through a small C++ shim over
//!   `ATen/autocast_mode.h` (tch's own `tch::autocast` is CUDA-only and fixed
//!   to fp16). The safe API is an RAII [`AutocastGuard`] that restores the
//!   previous state when dropped, also on an early return or a panic.
//! * [`c10d`]: PyTorch's distributed engine in libtorch (TCPStore, the
//!   Gloo and NCCL process groups) through a C++ shim, for data-parallel
//!   training.
//! * [`cpu_attention`]: softmax attention in bf16 on oneDNN's bf16
//!   micro-kernel, for x86 CPUs with AVX512-BF16 (libtorch's own runs its
//!   bf16 products as f32 there).
//! * [`cpu_cache`]: a caching CPU allocator for libtorch (freed blocks
//!   reused instead of returned to the kernel and page-faulted in again).
//! * [`onednn`]: oneDNN's inference linear layer (prepacked weights, a
//!   fused tanh GELU), which libtorch registers but tch does not expose.

pub mod autocast;
pub mod c10d;
pub mod cpu_attention;
pub mod cpu_cache;
pub mod cuda_memory;
pub mod onednn;

pub use autocast::{autocast, AutocastDevice, AutocastDtype, AutocastGuard};

/// Errors of this crate.
#[derive(Debug, thiserror::Error)]
pub enum TorchExtError {
    /// libtorch's autocast state could not be read or changed.
    #[error("autocast: {0}")]
    Autocast(String),
    /// A c10d store or collective failed (the C++ exception's message).
    #[error("c10d: {0}")]
    C10d(String),
    /// A oneDNN op failed (the C++ exception's message).
    #[error("{0}")]
    OneDnn(String),
    /// The CUDA allocator's figures could not be read.
    #[error("{0}")]
    Cuda(String),
}

/// Result of this crate.
pub type Result<T> = std::result::Result<T, TorchExtError>;
