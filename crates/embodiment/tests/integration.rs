//! The integration tests of `embodiment` that can share a process, as one
//! test binary (one link instead of one per file, and one pool of test
//! threads for all of them). The files keep their names; a test is
//! `FILE::NAME` (`cargo test -p CRATE --test integration FILE::`).
//! Separate binaries (Cargo.toml `[[test]]`): `fuzz_inputs.rs` (a global
//! allocator of its own), `mesh_fuzz.rs` and `urdf_fuzz.rs` (run alone by
//! scripts/fuzz.sh).

#[path = "support/cameras.rs"]
mod cameras;

mod agibot_samples;
mod camera;
mod fuzz_script;
mod kinematics;
mod masks;
mod mesh_formats;
mod raster;
mod real_robots;
mod urdf;
