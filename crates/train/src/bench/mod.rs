//! The training crate's benches, each measured against a peer in the same run:
//!
//! * [`loader`]: clip-loader throughput (`bench loader`);
//! * [`flow`]: the flow loss's decode and backward, time and peak memory of
//!   each [`crate::decoded_flow::FlowBackward`] mode (`bench flow`).

pub mod flow;
pub mod loader;

pub use flow::{bench_flow, FlowBenchOptions, FlowBenchReport, FlowBenchRow};
pub use loader::{bench_loader, LoaderBenchOptions, LoaderBenchReport, OpenTiming};
