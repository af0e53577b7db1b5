//! The integration tests of `data` that can share a process, as one
//! test binary (one link instead of one per file, and one pool of test
//! threads for all of them). The files keep their names; a test is
//! `FILE::NAME` (`cargo test -p CRATE --test integration FILE::`).
//! Separate binaries (Cargo.toml `[[test]]`, each with a global allocator
//! that measures the peak): `fuzz_h5.rs`, `fuzz_lerobot.rs`, `fuzz_mp4.rs`,
//! `video_stream.rs`.

mod calibrate;
mod calibrate_marks;
mod confined_paths;
mod convert_inputs;
mod ctrl_world;
mod declared_shapes;
mod lerobot_io;
mod names_not_paths;
mod pyav_videos;
mod raw_readers;
mod raw_real_layouts;
mod real_overlays;
mod real_videos;
mod synth_world;
