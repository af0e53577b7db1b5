//! The synthetic world's planning and policy-evaluation experiments as
//! library calls, each from a plain options struct to a report struct that
//! renders itself as markdown (the command line and the Python package are
//! thin layers over these):
//!
//! * [`planning`]: goal-image CEM-MPC on many task instances, next to the
//!   random-action baseline on the same instances ([`plan_summary`]);
//! * [`rollout`]: policy evaluation by world-model rollouts
//!   ([`rollout_report`]);
//! * [`drift`]: how far autoregressive rollouts drift from the world over
//!   many chunks ([`drift_study`]);
//! * [`fidelity_study`]: whether a model orders candidate actions as the
//!   world does ([`fidelity_study()`]);
//! * [`report`]: all of them as the `planning` sections of `docs/results.md`
//!   ([`plan_report`]), with their figures ([`report_figures`]).
//!
//! Their sizes are checked before anything is allocated ([`sizes`]).
//!
//! The world model of each is named by [`ModelOptions`] and loaded once
//! ([`LoadedModel`]).

pub mod drift;
pub mod fidelity_study;
pub mod judge_calibration;
mod models;
pub mod planning;
pub mod report;
pub mod report_figures;
pub mod rollout;
pub mod sizes;

pub use drift::{drift_study, DriftOptions, DriftReport};
pub use fidelity_study::{fidelity_study, FidelityOptions, FidelityStudy};
pub use models::{LoadedModel, ModelOptions, Sampling};
pub use planning::{plan_summary, PlanOptions, PlanSummary};
pub use report::{plan_report, PlanReportOptions, ReportModel};
pub use rollout::{rollout_report, rollout_report_with, RolloutOptions};

pub use bridgev2w_io::seed::trial_seed;

/// Mean and sample standard deviation (0 for one value).
pub fn mean_std(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    let var = if v.len() > 1 {
        v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0)
    } else {
        0.0
    };
    (m, var.sqrt())
}
