//! The Cross-Entropy Method over action sequences, as the paper's Algorithm
//! "CEM-MPC planning": per horizon step a Gaussian `N(mu_h, Sigma_h)` over the
//! 6-D pose increment (translation xyz in metres, rotation rpy in radians)
//! and a Bernoulli `pi_h` over the gripper; `S` samples, `k` elites, `T`
//! refinements; elites refit the per-step mean, covariance and gripper
//! probability. Options: translation-only search, discretised steps,
//! a fixed (heuristic) gripper, and the rotation refinements
//! (rotation-first search, sample reallocation, axis-wise decomposition).

use crate::error::{PlanError, Result};
use nalgebra::{Matrix6, Vector6};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

/// The paper's translational discretisation step (metres).
pub const TRANSLATION_STEP_M: f64 = 0.05;
/// The paper's rotational discretisation step (radians; 20 degrees).
pub const ROTATION_STEP_RAD: f64 = 20.0 * std::f64::consts::PI / 180.0;

/// Index of roll, pitch and yaw in a 6-D increment.
const ROLL: usize = 3;
const PITCH: usize = 4;
const YAW: usize = 5;

/// How the rotational dimensions are searched (the paper's refinements for
/// rotation-heavy tasks).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RotationSearch {
    /// All dimensions together (plain CEM).
    Joint,
    /// Rotation first with translation frozen at its mean, then everything.
    RotationFirst,
    /// Yaw, then pitch, then roll, each alone, then translation.
    AxisWise,
}
bridgev2w_world_model::named_enum!(RotationSearch, crate::PlanError, crate::PlanError::input, "rotation search", {
    Joint => "joint",
    RotationFirst => "rotation-first",
    AxisWise => "axis-wise",
});

/// How the gripper is chosen.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum GripperMode {
    /// Sampled from the per-step Bernoulli and refit from the elites.
    Search,
    /// Fixed to this command (the gripper heuristic), not searched.
    Fixed(f64),
}

/// CEM settings.
#[derive(Debug, Clone, PartialEq)]
pub struct CemConfig {
    /// Samples per iteration `S`.
    pub samples: usize,
    /// Elites `k`.
    pub elites: usize,
    /// Refinements `T` (per search phase).
    pub iterations: usize,
    /// Horizon `H` (actions per candidate).
    pub horizon: usize,
    /// Initial standard deviation of each translational increment (metres).
    pub init_translation_std_m: f64,
    /// Initial standard deviation of each rotational increment (radians).
    pub init_rotation_std_rad: f64,
    /// Initial gripper probability `pi_h`.
    pub init_gripper_prob: f64,
    /// Search translation only (rotational increments are zero).
    pub translation_only: bool,
    /// Round increments to [`TRANSLATION_STEP_M`] and [`ROTATION_STEP_RAD`].
    pub discretize: bool,
    /// Rotation refinement.
    pub rotation_search: RotationSearch,
    /// Sample reallocation: this fraction of the `S` samples perturbs only
    /// the rotational dimensions (translation at its mean); 0 = off.
    pub rotation_sample_fraction: f64,
    /// Carry each iteration's elites (with their costs) into the next
    /// iteration's elite selection (iCEM's "keep elites"; off in the
    /// paper's algorithm). A good rare sample then cannot be lost when the
    /// next iteration's samples are all worse.
    pub keep_elites: bool,
    /// Evaluate the distribution's mean itself as one of each iteration's
    /// `S` samples (iCEM). In the first iteration of an MPC step the mean is
    /// the zero increment: staying put is then a candidate, and a step that
    /// no sample improves on holds the pose instead of moving away.
    pub include_mean: bool,
}

impl Default for CemConfig {
    fn default() -> Self {
        Self {
            samples: 32,
            elites: 4,
            iterations: 3,
            horizon: 3,
            init_translation_std_m: 0.04,
            init_rotation_std_rad: 0.2,
            init_gripper_prob: 0.5,
            translation_only: true,
            discretize: false,
            rotation_search: RotationSearch::Joint,
            rotation_sample_fraction: 0.0,
            keep_elites: false,
            include_mean: false,
        }
    }
}

impl CemConfig {
    /// Checks the settings: horizon >= 1, 1 <= k <= S, T >= 1, finite stds.
    pub fn validate(&self) -> Result<()> {
        if self.horizon == 0 {
            return Err(PlanError::ZeroHorizon);
        }
        if self.elites == 0 || self.elites > self.samples {
            return Err(PlanError::Elites {
                elites: self.elites,
                samples: self.samples,
            });
        }
        if self.iterations == 0 {
            return Err(PlanError::Invalid(
                "CEM iterations must be at least 1".into(),
            ));
        }
        let stds = [self.init_translation_std_m, self.init_rotation_std_rad];
        if stds.iter().any(|s| !(s.is_finite() && *s >= 0.0)) {
            return Err(PlanError::Invalid(format!(
                "initial standard deviations {stds:?} must be finite and >= 0"
            )));
        }
        if !(0.0..=1.0).contains(&self.init_gripper_prob)
            || !(0.0..=1.0).contains(&self.rotation_sample_fraction)
        {
            return Err(PlanError::Invalid(
                "gripper probability and rotation sample fraction must be in [0, 1]".into(),
            ));
        }
        Ok(())
    }

    /// The search phases: which increment dimensions vary, for how many
    /// iterations each.
    pub fn phases(&self) -> Vec<([bool; 6], usize)> {
        let t = self.iterations;
        let trans = [true, true, true, false, false, false];
        let axis = |i: usize| {
            let mut a = [false; 6];
            a[i] = true;
            a
        };
        if self.translation_only {
            return vec![(trans, t)];
        }
        match self.rotation_search {
            RotationSearch::Joint => vec![([true; 6], t)],
            RotationSearch::RotationFirst => {
                vec![([false, false, false, true, true, true], t), ([true; 6], t)]
            }
            RotationSearch::AxisWise => vec![
                (axis(YAW), t),
                (axis(PITCH), t),
                (axis(ROLL), t),
                (trans, t),
            ],
        }
    }
}

/// The sampling distribution of one horizon step.
#[derive(Debug, Clone, PartialEq)]
pub struct StepDistribution {
    /// Mean increment `mu_h` (xyz metres, rpy radians).
    pub mean: Vector6<f64>,
    /// Covariance `Sigma_h`.
    pub cov: Matrix6<f64>,
    /// Gripper probability `pi_h` of "closed".
    pub gripper_prob: f64,
}

impl StepDistribution {
    /// The initial distribution: zero mean, diagonal covariance.
    pub fn initial(cfg: &CemConfig) -> Self {
        let rot_std = if cfg.translation_only {
            0.0
        } else {
            cfg.init_rotation_std_rad
        };
        let t2 = cfg.init_translation_std_m.powi(2);
        let r2 = rot_std.powi(2);
        Self {
            mean: Vector6::zeros(),
            cov: Matrix6::from_diagonal(&Vector6::new(t2, t2, t2, r2, r2, r2)),
            gripper_prob: cfg.init_gripper_prob,
        }
    }
}

/// One candidate action sequence: per horizon step a 6-D increment and a
/// gripper command.
#[derive(Debug, Clone, PartialEq)]
pub struct Candidate {
    /// Per step: `[dx, dy, dz, droll, dpitch, dyaw]` (metres, radians).
    pub increments: Vec<[f64; 6]>,
    /// Per step: gripper command (0 or 1).
    pub gripper: Vec<f64>,
}

/// Rounds an increment to the paper's grid.
pub fn discretize(inc: &mut [f64; 6]) {
    for (i, v) in inc.iter_mut().enumerate() {
        let step = if i < 3 {
            TRANSLATION_STEP_M
        } else {
            ROTATION_STEP_RAD
        };
        *v = (*v / step).round() * step;
    }
}

/// One draw of N(0, 1) (Box-Muller; the project's one normal sampler).
pub use bridgev2w_io::seed::standard_normal;

/// Draws one candidate: on the `active` dimensions from the step Gaussians
/// (the covariance restricted to them), elsewhere the mean.
pub fn sample_candidate(
    dists: &[StepDistribution],
    active: &[bool; 6],
    cfg: &CemConfig,
    gripper: GripperMode,
    rng: &mut ChaCha8Rng,
) -> Candidate {
    let mut increments = Vec::with_capacity(dists.len());
    let mut grip = Vec::with_capacity(dists.len());
    for d in dists {
        let mut cov = d.cov;
        for i in 0..6 {
            for j in 0..6 {
                if !(active[i] && active[j]) {
                    cov[(i, j)] = 0.0;
                }
            }
            cov[(i, i)] += 1e-12;
        }
        let l = nalgebra::Cholesky::new(cov).map_or_else(
            || Matrix6::from_diagonal(&cov.diagonal().map(|v| v.max(0.0).sqrt())),
            |c| c.l(),
        );
        let z = Vector6::from_fn(|i, _| if active[i] { standard_normal(rng) } else { 0.0 });
        let x = d.mean + l * z;
        let mut inc = [0.0; 6];
        for (i, v) in inc.iter_mut().enumerate() {
            *v = if active[i] { x[i] } else { d.mean[i] };
        }
        if cfg.discretize {
            discretize(&mut inc);
        }
        increments.push(inc);
        grip.push(match gripper {
            GripperMode::Search => {
                f64::from(u8::from(rng.gen_bool(d.gripper_prob.clamp(0.0, 1.0))))
            }
            GripperMode::Fixed(g) => g,
        });
    }
    Candidate {
        increments,
        gripper: grip,
    }
}

/// The indices of the `k` lowest costs (NaN costs rank last), best first.
pub fn elite_indices(costs: &[f64], k: usize) -> Vec<usize> {
    let mut idx: Vec<usize> = (0..costs.len()).collect();
    let key = |c: f64| if c.is_nan() { f64::INFINITY } else { c };
    idx.sort_by(|&a, &b| key(costs[a]).total_cmp(&key(costs[b])));
    idx.truncate(k);
    idx
}

/// Refits each step's distribution to the elites on the `active`
/// dimensions: the empirical mean, the empirical covariance (divided by
/// `k`, the maximum-likelihood estimate) and, when the gripper is searched,
/// `pi_h` = the fraction of elites with the gripper closed. Inactive
/// dimensions keep their mean and (co)variances.
pub fn refit(
    dists: &mut [StepDistribution],
    elites: &[&Candidate],
    active: &[bool; 6],
    search_gripper: bool,
) {
    let k = elites.len() as f64;
    if elites.is_empty() {
        return;
    }
    for (h, d) in dists.iter_mut().enumerate() {
        let xs: Vec<Vector6<f64>> = elites
            .iter()
            .map(|c| Vector6::from_column_slice(&c.increments[h]))
            .collect();
        let mean = xs.iter().fold(Vector6::zeros(), |a, x| a + x) / k;
        let cov = xs.iter().fold(Matrix6::zeros(), |a, x| {
            a + (x - mean) * (x - mean).transpose()
        }) / k;
        for i in 0..6 {
            if !active[i] {
                continue;
            }
            d.mean[i] = mean[i];
            for j in 0..6 {
                if active[j] {
                    d.cov[(i, j)] = cov[(i, j)];
                }
            }
        }
        if search_gripper {
            d.gripper_prob = elites.iter().filter(|c| c.gripper[h] >= 0.5).count() as f64 / k;
        }
    }
}

/// What one CEM optimisation did.
#[derive(Debug, Clone, PartialEq)]
pub struct CemResult {
    /// The refined per-step distributions.
    pub distributions: Vec<StepDistribution>,
    /// The extracted plan `A*_h = [mu_h, 1{pi_h >= 0.5}]` (discretised if asked).
    pub plan: Candidate,
    /// Lowest cost per iteration (all phases in order).
    pub best_cost_per_iteration: Vec<f64>,
    /// The best candidate seen and its cost.
    pub best: (Candidate, f64),
}

/// Runs CEM: `evaluate` scores a batch of `S` candidates (lower is better)
/// and is called once per iteration.
pub fn optimize(
    cfg: &CemConfig,
    gripper: GripperMode,
    rng: &mut ChaCha8Rng,
    evaluate: &mut dyn FnMut(&[Candidate]) -> Result<Vec<f64>>,
) -> Result<CemResult> {
    cfg.validate()?;
    let mut dists = vec![StepDistribution::initial(cfg); cfg.horizon];
    let mut trace = Vec::new();
    let mut best: Option<(Candidate, f64)> = None;
    let search_gripper = gripper == GripperMode::Search;
    let mut carried: Vec<(Candidate, f64)> = Vec::new();
    for (active, iterations) in cfg.phases() {
        let has_rotation = active[3..].iter().any(|&a| a);
        let has_translation = active[..3].iter().any(|&a| a);
        let n_rot_only = if has_rotation && has_translation {
            (cfg.rotation_sample_fraction * cfg.samples as f64).round() as usize
        } else {
            0
        };
        let rot_only = [false, false, false, active[3], active[4], active[5]];
        for _ in 0..iterations {
            let candidates: Vec<Candidate> = (0..cfg.samples)
                .map(|s| {
                    if s == 0 && cfg.include_mean {
                        return extract_plan(&dists, cfg, gripper);
                    }
                    let a = if s < n_rot_only { &rot_only } else { &active };
                    sample_candidate(&dists, a, cfg, gripper, rng)
                })
                .collect();
            let costs = evaluate(&candidates)?;
            if costs.len() != candidates.len() {
                return Err(PlanError::Invalid(format!(
                    "the evaluator returned {} costs for {} candidates",
                    costs.len(),
                    candidates.len()
                )));
            }
            // The selection pool: this iteration's samples, then the
            // carried elites of the previous iteration.
            let mut pool: Vec<(Candidate, f64)> = candidates.into_iter().zip(costs).collect();
            pool.append(&mut carried);
            let pool_costs: Vec<f64> = pool.iter().map(|(_, c)| *c).collect();
            let elite = elite_indices(&pool_costs, cfg.elites);
            if let Some(&b) = elite.first() {
                trace.push(pool_costs[b]);
                if best.as_ref().is_none_or(|(_, c)| pool_costs[b] < *c) {
                    best = Some(pool[b].clone());
                }
            }
            let elites: Vec<&Candidate> = elite.iter().map(|&i| &pool[i].0).collect();
            refit(&mut dists, &elites, &active, search_gripper);
            if cfg.keep_elites {
                carried = elite.iter().map(|&i| pool[i].clone()).collect();
            }
        }
    }
    let plan = extract_plan(&dists, cfg, gripper);
    let best = best.unwrap_or_else(|| (plan.clone(), f64::INFINITY));
    Ok(CemResult {
        distributions: dists,
        plan,
        best_cost_per_iteration: trace,
        best,
    })
}

/// `A*_h = [mu_h(1:3), mu_h(4:6), 1{pi_h >= 0.5}]` (or the fixed gripper).
pub fn extract_plan(
    dists: &[StepDistribution],
    cfg: &CemConfig,
    gripper: GripperMode,
) -> Candidate {
    let mut increments = Vec::with_capacity(dists.len());
    let mut grip = Vec::with_capacity(dists.len());
    for d in dists {
        let mut inc = [0.0; 6];
        inc.copy_from_slice(d.mean.as_slice());
        if cfg.discretize {
            discretize(&mut inc);
        }
        increments.push(inc);
        grip.push(match gripper {
            GripperMode::Search => f64::from(u8::from(d.gripper_prob >= 0.5)),
            GripperMode::Fixed(g) => g,
        });
    }
    Candidate {
        increments,
        gripper: grip,
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn refit_matches_the_closed_form_on_a_tiny_example() {
        let cfg = CemConfig {
            horizon: 1,
            ..CemConfig::default()
        };
        let mut d = vec![StepDistribution::initial(&cfg)];
        let c = |x: [f64; 6], g: f64| Candidate {
            increments: vec![x],
            gripper: vec![g],
        };
        let a = c([1.0, 2.0, 0.0, 0.0, 0.0, 0.0], 1.0);
        let b = c([3.0, 0.0, 0.0, 0.0, 0.0, 0.0], 0.0);
        refit(&mut d, &[&a, &b], &[true; 6], true);
        // mean (2, 1); deviations (-1, 1), (1, -1): cov = [[1, -1], [-1, 1]].
        assert_eq!(d[0].mean[0], 2.0);
        assert_eq!(d[0].mean[1], 1.0);
        assert_eq!(d[0].cov[(0, 0)], 1.0);
        assert_eq!(d[0].cov[(1, 1)], 1.0);
        assert_eq!(d[0].cov[(0, 1)], -1.0);
        assert_eq!(d[0].cov[(2, 2)], 0.0);
        assert_eq!(d[0].gripper_prob, 0.5);
        // Inactive dimensions keep theirs.
        let mut e = vec![StepDistribution::initial(&cfg)];
        refit(
            &mut e,
            &[&a, &b],
            &[false, true, false, false, false, false],
            false,
        );
        assert_eq!(e[0].mean[0], 0.0);
        assert_eq!(e[0].cov[(0, 0)], cfg.init_translation_std_m.powi(2));
        assert_eq!(e[0].mean[1], 1.0);
        assert_eq!(e[0].gripper_prob, cfg.init_gripper_prob);
    }

    #[test]
    fn elites_are_the_lowest_costs_and_nan_ranks_last() {
        assert_eq!(elite_indices(&[3.0, f64::NAN, 1.0, 2.0], 3), vec![2, 3, 0]);
    }

    #[test]
    fn cem_finds_the_minimum_of_a_quadratic() {
        let target = [0.1, -0.05, 0.02];
        let cfg = CemConfig {
            horizon: 2,
            samples: 64,
            elites: 8,
            iterations: 8,
            ..CemConfig::default()
        };
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut calls = 0;
        let r = optimize(&cfg, GripperMode::Search, &mut rng, &mut |cs| {
            calls += 1;
            Ok(cs
                .iter()
                .map(|c| {
                    let sum: Vec<f64> = (0..3)
                        .map(|i| c.increments.iter().map(|x| x[i]).sum::<f64>())
                        .collect();
                    // Gripper closed at the end is cheaper.
                    (0..3).map(|i| (sum[i] - target[i]).abs()).sum::<f64>()
                        + 0.1 * (1.0 - c.gripper[1])
                })
                .collect())
        })
        .unwrap();
        assert_eq!(calls, 8);
        for (i, t) in target.iter().enumerate() {
            let got: f64 = r.plan.increments.iter().map(|x| x[i]).sum();
            assert!((got - t).abs() < 0.01, "axis {i}: {got} vs {t}");
        }
        assert_eq!(r.plan.gripper[1], 1.0);
        // Translation only: rotations stay exactly zero.
        assert!(r.plan.increments.iter().all(|x| x[3..] == [0.0; 3]));
    }

    #[test]
    fn kept_elites_make_the_best_cost_monotone() {
        // A needle: one narrow well far from the initial mean, a gentle slope
        // elsewhere. Without carry-over a lucky sample in the well can be
        // outvoted and lost; with it the trace never gets worse.
        let cost = |c: &Candidate| {
            let x = c.increments[0][0];
            if (x - 0.15).abs() < 0.01 {
                -1.0
            } else {
                x.abs()
            }
        };
        let run = |keep: bool, seed: u64| {
            let cfg = CemConfig {
                horizon: 1,
                samples: 16,
                elites: 4,
                iterations: 6,
                init_translation_std_m: 0.1,
                keep_elites: keep,
                ..CemConfig::default()
            };
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            optimize(&cfg, GripperMode::Fixed(0.0), &mut rng, &mut |cs| {
                Ok(cs.iter().map(cost).collect())
            })
            .unwrap()
        };
        let mut lost_without = 0;
        for seed in 0..20 {
            let kept = run(true, seed);
            let t = &kept.best_cost_per_iteration;
            assert!(t.windows(2).all(|w| w[1] <= w[0]), "seed {seed}: {t:?}");
            let plain = run(false, seed);
            let p = &plain.best_cost_per_iteration;
            if p.windows(2).any(|w| w[1] > w[0]) {
                lost_without += 1;
            }
            // The best candidate seen is reported either way.
            assert_eq!(
                kept.best.1,
                *t.iter().min_by(|a, b| a.total_cmp(b)).unwrap()
            );
        }
        assert!(lost_without > 0, "plain CEM never lost its best sample");
    }

    #[test]
    fn the_mean_is_a_sample_and_wins_where_every_move_is_worse() {
        // A bowl at the origin: every nonzero move costs more than staying.
        let cost = |c: &Candidate| c.increments[0][..3].iter().map(|x| x * x).sum::<f64>();
        let run = |include_mean: bool| {
            let cfg = CemConfig {
                horizon: 1,
                samples: 8,
                elites: 2,
                iterations: 2,
                include_mean,
                ..CemConfig::default()
            };
            let mut rng = ChaCha8Rng::seed_from_u64(4);
            let mut batches = Vec::new();
            let r = optimize(&cfg, GripperMode::Fixed(1.0), &mut rng, &mut |cs| {
                batches.push(cs.to_vec());
                Ok(cs.iter().map(cost).collect())
            })
            .unwrap();
            (r, batches)
        };
        let (with, batches) = run(true);
        // S samples per iteration, the first of each the current mean: the
        // zero move first, then the refit mean.
        assert!(batches.iter().all(|b| b.len() == 8));
        assert_eq!(batches[0][0].increments[0], [0.0; 6]);
        assert_eq!(batches[0][0].gripper, vec![1.0]);
        assert_eq!(batches[1][0], extract_plan_of(&batches[0]));
        assert_eq!(with.best.1, 0.0);
        assert_eq!(with.best.0.increments[0], [0.0; 6]);
        // Without it no sample is the zero move, so the best one moves.
        let (without, batches) = run(false);
        assert!(batches
            .iter()
            .flatten()
            .all(|c| c.increments[0] != [0.0; 6]));
        assert!(without.best.1 > 0.0);
    }

    /// The mean of the two lowest-cost candidates of a bowl at the origin
    /// (the refit mean of `the_mean_is_a_sample...` after one iteration).
    fn extract_plan_of(batch: &[Candidate]) -> Candidate {
        let cost = |c: &Candidate| c.increments[0][..3].iter().map(|x| x * x).sum::<f64>();
        let costs: Vec<f64> = batch.iter().map(cost).collect();
        let e = elite_indices(&costs, 2);
        let mut inc = [0.0; 6];
        for (i, v) in inc.iter_mut().enumerate() {
            *v = (batch[e[0]].increments[0][i] + batch[e[1]].increments[0][i]) / 2.0;
        }
        Candidate {
            increments: vec![inc],
            gripper: vec![1.0],
        }
    }

    #[test]
    fn discretised_samples_lie_on_the_grid() {
        let cfg = CemConfig {
            discretize: true,
            translation_only: false,
            ..CemConfig::default()
        };
        let d = vec![StepDistribution::initial(&cfg); 3];
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        for _ in 0..20 {
            let c = sample_candidate(&d, &[true; 6], &cfg, GripperMode::Fixed(1.0), &mut rng);
            for x in &c.increments {
                for (i, v) in x.iter().enumerate() {
                    let s = if i < 3 {
                        TRANSLATION_STEP_M
                    } else {
                        ROTATION_STEP_RAD
                    };
                    assert!(((v / s) - (v / s).round()).abs() < 1e-9);
                }
            }
            assert_eq!(c.gripper, vec![1.0; 3]);
        }
    }

    #[test]
    fn rotation_refinements_schedule_the_phases() {
        let mut cfg = CemConfig {
            translation_only: false,
            iterations: 2,
            rotation_search: RotationSearch::AxisWise,
            ..CemConfig::default()
        };
        let p = cfg.phases();
        assert_eq!(p.len(), 4);
        assert_eq!(p[0].0, [false, false, false, false, false, true]); // yaw first
        cfg.rotation_search = RotationSearch::RotationFirst;
        assert_eq!(cfg.phases()[0].0, [false, false, false, true, true, true]);
        // Rotation-only phases leave translation at its (zero) mean.
        let d = vec![StepDistribution::initial(&cfg); 1];
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let c = sample_candidate(&d, &cfg.phases()[0].0, &cfg, GripperMode::Search, &mut rng);
        assert_eq!(c.increments[0][..3], [0.0; 3]);
        assert!(c.increments[0][3..].iter().any(|v| *v != 0.0));
    }

    #[test]
    fn bad_settings_are_errors() {
        let h0 = CemConfig {
            horizon: 0,
            ..CemConfig::default()
        };
        assert!(matches!(h0.validate(), Err(PlanError::ZeroHorizon)));
        let k = CemConfig {
            samples: 4,
            elites: 5,
            ..CemConfig::default()
        };
        assert!(matches!(
            k.validate(),
            Err(PlanError::Elites {
                elites: 5,
                samples: 4
            })
        ));
    }
}
