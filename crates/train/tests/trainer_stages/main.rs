//! Trainer tests on a tiny synthetic dataset (`random:tiny` backbone), one
//! test binary in three files: the mask sources (`masks`), the stages and
//! losses beyond the paper's fine-tuning (`stages`: RAFT's flow loss, the VAE
//! / prior stages, the evaluation, VAE tiles) and the ways one step runs
//! (`modes`: gradient checkpointing, bf16 autocast, data-parallel shards).
//! libtorch's generator is process-global, so the tests that train run one
//! at a time (`lock`).

#![allow(clippy::unwrap_used)]

#[path = "../common/mod.rs"]
mod common;

mod masks;
mod modes;
mod stages;
