//! Helpers shared by the CLI's integration tests.

#![allow(dead_code)]

use std::path::Path;
use std::process::{Command, Output};

/// Runs the `bridgev2w` binary (without backtraces, as a user sees it).
pub fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_bridgev2w"))
        .env("RUST_BACKTRACE", "0")
        .args(args)
        .output()
        .expect("run bridgev2w")
}

/// A path as a `&str` argument.
pub fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}
