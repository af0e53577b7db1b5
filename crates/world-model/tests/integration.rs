//! The integration tests of `world-model` that can share a process, as one
//! test binary (one link instead of one per file, and one pool of test
//! threads for all of them). The files keep their names; a test is
//! `FILE::NAME` (`cargo test -p CRATE --test integration FILE::`).
//! Separate binaries (Cargo.toml `[[test]]`): `fuzz_checkpoint.rs` (a global
//! allocator of its own), `bridge.rs` and `bridge_predict.rs` (they seed
//! libtorch's global generator and draw from it twice, under a lock that
//! tests in other files do not take).

mod common;

mod lora_export;
mod nets_i3d;
mod nets_lpips;
mod nets_raft;
mod parity_scheduler;
mod parity_transformer;
mod parity_vae;
mod prompt_embedding;
