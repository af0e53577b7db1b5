//! The integration tests of `cli` that can share a process, as one
//! test binary (one link instead of one per file, and one pool of test
//! threads for all of them). The files keep their names; a test is
//! `FILE::NAME` (`cargo test -p CRATE --test integration FILE::`).

mod common;
#[path = "../../plan/tests/support/policy_server.rs"]
mod policy_server;

// The longest tests, mostly on one core (the Python package: its build,
// pytest and guides, about 4 minutes; the GPU checklist's dry run, about 2),
// named to start first (libtest starts tests in name order): they overlap
// the others instead of running alone at the end.
#[path = "python_package.rs"]
mod a1_python_package;
#[path = "gpu_checklist.rs"]
mod a2_gpu_checklist;

mod cli;
mod docs_commands;
mod docs_links;
mod eval_cmd;
mod flags_refused;
mod lerobot_package;
mod masks_cameras;
mod model_names;
mod output_ownership;
mod parity_cmd;
mod plan_cmd;
mod predict_cmd;
mod reproduce_real_script;
mod reproduce_script;
mod served_policy_cmd;
mod setup_venv;
mod sizes_refused;
mod synth_mujoco;
mod train_cmd;
mod train_dp_cmd;
