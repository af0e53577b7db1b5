//! The integration tests of `plan` that can share a process, as one
//! test binary (one link instead of one per file, and one pool of test
//! threads for all of them). The files keep their names; a test is
//! `FILE::NAME` (`cargo test -p CRATE --test integration FILE::`).

mod common;
#[path = "support/policy_server.rs"]
mod policy_server;

mod gripper;
mod planning;
mod served_policy;
mod synthetic_world;
