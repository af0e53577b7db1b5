//! Kinematics speed on the built-in Franka: forward-kinematics poses per
//! second on one core, and the time of a warm-started IK solve along a
//! smooth trajectory.

use super::{BenchError, Result};
use crate::embodiment::Embodiment;
use crate::kinematics::{random_q, IkOptions, IkSolver, SplitMix64};
use std::fmt;
use std::time::Instant;

/// The link IK solves for.
const TCP: &str = "panda_hand_tcp";

/// How many evaluations `bench kinematics` times.
#[derive(Debug, Clone, PartialEq, Eq)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct KinematicsBenchOptions {
    /// Forward-kinematics evaluations.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = KinematicsBenchOptions::default().fk))]
    pub fk: usize,
    /// Warm-started IK solves along a smooth trajectory.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = KinematicsBenchOptions::default().ik))]
    pub ik: usize,
}

impl Default for KinematicsBenchOptions {
    fn default() -> Self {
        Self {
            fk: 2_000_000,
            ik: 20_000,
        }
    }
}

/// The measurements of `bench kinematics`; `Display` prints them.
#[derive(Debug, Clone, PartialEq)]
pub struct KinematicsBenchReport {
    /// Forward-kinematics poses per second (one core).
    pub fk_poses_per_s: f64,
    /// Links per pose.
    pub links: usize,
    /// Sum of a coordinate of every pose (keeps the work from being optimised away).
    pub checksum: f64,
    /// Microseconds per warm-started IK solve.
    pub ik_us_per_solve: f64,
    /// Solves that reached their target.
    pub ik_reached: usize,
    /// Solves.
    pub ik_solves: usize,
    /// Mean iterations per solve.
    pub ik_mean_iterations: f64,
}

impl fmt::Display for KinematicsBenchReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "forward kinematics  {:>12.0} poses/s per core  ({} links per pose; checksum {:.3})",
            self.fk_poses_per_s, self.links, self.checksum
        )?;
        writeln!(
            f,
            "inverse kinematics  {:>12.2} us per warm-started solve  ({}/{} reached, {:.2} iterations on average)",
            self.ik_us_per_solve, self.ik_reached, self.ik_solves, self.ik_mean_iterations
        )
    }
}

/// Times `options.fk` forward-kinematics evaluations of random joint vectors
/// and `options.ik` IK solves, each warm-started from the previous solution,
/// of targets from a smooth joint path.
pub fn bench_kinematics(options: &KinematicsBenchOptions) -> Result<KinematicsBenchReport> {
    let e = Embodiment::builtin("franka")?;
    let r = &e.robot;
    let mut rng = SplitMix64::new(1);
    let qs: Vec<Vec<f64>> = (0..1024).map(|_| random_q(r, &mut rng)).collect();
    let mut buf = Vec::with_capacity(r.links.len());
    let mut sink = 0.0;
    let t0 = Instant::now();
    for i in 0..options.fk {
        r.link_poses_into(&qs[i % qs.len()], &mut buf);
        sink += buf[buf.len() - 1].translation.x;
    }
    let fk_s = t0.elapsed().as_secs_f64();

    let tcp = r
        .link_index(TCP)
        .ok_or_else(|| BenchError::Invalid(format!("built-in franka: no link {TCP}")))?;
    let solver = IkSolver::new(r, tcp, None);
    let opts = IkOptions::default();
    // A smooth joint path; targets from FK; each solve warm-started from the previous solution.
    let mut q = e.home.clone();
    let targets: Vec<_> = (0..options.ik)
        .map(|i| {
            let s = i as f64 * 0.01;
            let mut qt = e.home.clone();
            qt[0] = 0.8 * s.sin();
            qt[1] = -0.5 + 0.4 * (0.7 * s).sin();
            qt[3] = -2.0 + 0.5 * (0.5 * s).cos();
            qt[5] = 1.6 + 0.4 * (0.3 * s).sin();
            r.link_pose(tcp, &qt)
        })
        .collect();
    let (mut reached, mut iters) = (0usize, 0usize);
    let t0 = Instant::now();
    for t in &targets {
        let sol = solver.solve(t, &q, &opts);
        reached += usize::from(sol.reached);
        iters += sol.iterations;
        q = sol.q;
    }
    let ik_s = t0.elapsed().as_secs_f64();
    Ok(KinematicsBenchReport {
        fk_poses_per_s: options.fk as f64 / fk_s,
        links: r.links.len(),
        checksum: sink,
        ik_us_per_solve: ik_s / options.ik as f64 * 1e6,
        ik_reached: reached,
        ik_solves: options.ik,
        ik_mean_iterations: iters as f64 / options.ik as f64,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_small_run_reaches_its_targets_and_prints_two_lines() {
        let report = bench_kinematics(&KinematicsBenchOptions { fk: 100, ik: 20 }).expect("bench");
        assert_eq!(report.ik_solves, 20);
        assert_eq!(report.ik_reached, 20, "{report:?}");
        assert!(report.fk_poses_per_s > 0.0 && report.links > 0);
        let text = report.to_string();
        assert_eq!(text.lines().count(), 2, "{text}");
        assert!(text.contains("(20/20 reached"), "{text}");
    }
}
