//! Policy-evaluation metrics between real-world success rates and those
//! measured with the world model, computed as SIMPLER's `metrics.py` does.

use crate::{MetricError, Result};

fn check(sim: &[f64], real: &[f64]) -> Result<()> {
    if sim.len() != real.len() {
        return Err(MetricError::ShapeMismatch {
            what: "success rates of the world model and of the real robot".into(),
            left: format!("{} policies", sim.len()),
            right: format!("{} policies", real.len()),
        });
    }
    if sim.is_empty() {
        return Err(MetricError::Invalid("no policies to compare".into()));
    }
    if let Some(v) = sim.iter().chain(real).find(|v| !v.is_finite()) {
        return Err(MetricError::Invalid(format!(
            "success rate {v}: expected a finite number"
        )));
    }
    Ok(())
}

/// Mean Maximum Rank Violation: for every policy `i`, the largest real
/// success-rate gap `|real_i - real_j|` over the policies `j` whose order
/// differs between the two evaluations (`(sim_i > sim_j) != (real_i >
/// real_j)`, strict comparisons), averaged over `i`. Lower is better; 0
/// when the world model orders the policies like the real robot.
pub fn mmrv(sim: &[f64], real: &[f64]) -> Result<f64> {
    check(sim, real)?;
    let n = sim.len();
    let total: f64 = (0..n)
        .map(|i| {
            (0..n)
                .filter(|&j| (sim[i] > sim[j]) != (real[i] > real[j]))
                .map(|j| (real[i] - real[j]).abs())
                .fold(0.0, f64::max)
        })
        .sum();
    Ok(total / n as f64)
}

/// Pearson correlation of the success rates: `sum(s r) / (sqrt(sum(s^2)
/// sum(r^2)) + 1e-8)` over the centred vectors `s`, `r`; exactly 1 when
/// the centred vectors are identical (including both constant).
pub fn pearson(sim: &[f64], real: &[f64]) -> Result<f64> {
    check(sim, real)?;
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let (ms, mr) = (mean(sim), mean(real));
    let s: Vec<f64> = sim.iter().map(|v| v - ms).collect();
    let r: Vec<f64> = real.iter().map(|v| v - mr).collect();
    if s == r {
        return Ok(1.0);
    }
    let dot: f64 = s.iter().zip(&r).map(|(a, b)| a * b).sum();
    let ss: f64 = s.iter().map(|a| a * a).sum();
    let rr: f64 = r.iter().map(|b| b * b).sum();
    Ok(dot / ((ss * rr).sqrt() + 1e-8))
}

/// Ranks `0..n` of `v` (ascending), ties sharing their mean rank.
pub fn ranks(v: &[f64]) -> Vec<f64> {
    let mut order: Vec<usize> = (0..v.len()).collect();
    order.sort_by(|&a, &b| v[a].total_cmp(&v[b]));
    let mut out = vec![0.0; v.len()];
    let mut i = 0;
    while i < order.len() {
        let mut j = i;
        while j + 1 < order.len() && v[order[j + 1]] == v[order[i]] {
            j += 1;
        }
        let mean = (i + j) as f64 / 2.0;
        for &k in &order[i..=j] {
            out[k] = mean;
        }
        i = j + 1;
    }
    out
}

/// Spearman's rank correlation: [`pearson`] of the (tie-averaged) ranks.
/// Needs two finite vectors of the same length, at least 2 values.
pub fn spearman(a: &[f64], b: &[f64]) -> Result<f64> {
    if a.len() != b.len() || a.len() < 2 {
        return Err(MetricError::Invalid(format!(
            "{} and {} values: expected two equally long vectors of at least 2",
            a.len(),
            b.len()
        )));
    }
    if let Some(v) = a.iter().chain(b).find(|v| !v.is_finite()) {
        return Err(MetricError::Invalid(format!("value {v} is not finite")));
    }
    pearson(&ranks(a), &ranks(b))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn mmrv_hand_computed() {
        // Same order: no violation.
        assert_eq!(mmrv(&[0.1, 0.5, 0.9], &[0.2, 0.4, 0.8]).unwrap(), 0.0);
        // Policies 0 and 1 swapped: each gets |0.2 - 0.6| = 0.4; policy 2
        // keeps its rank.
        let v = mmrv(&[0.5, 0.1, 0.9], &[0.2, 0.6, 0.8]).unwrap();
        assert!((v - 0.8 / 3.0).abs() < 1e-12, "{v}");
        // A tie in the world model against a real gap: (sim_i > sim_j) is
        // false both ways, so only the row whose real rate is larger counts.
        let v = mmrv(&[0.5, 0.5], &[0.2, 0.6]).unwrap();
        assert!((v - 0.2).abs() < 1e-12, "{v}");
        // Ties in the real ranking contribute 0.
        assert_eq!(mmrv(&[0.1, 0.9], &[0.5, 0.5]).unwrap(), 0.0);
    }

    #[test]
    fn pearson_closed_forms() {
        assert!((pearson(&[1.0, 2.0, 3.0], &[2.0, 4.0, 6.0]).unwrap() - 1.0).abs() < 1e-8);
        assert!((pearson(&[1.0, 2.0, 3.0], &[3.0, 2.0, 1.0]).unwrap() + 1.0).abs() < 1e-8);
        // Identical after centring: exactly 1, even for constants.
        assert_eq!(pearson(&[0.3, 0.3], &[0.7, 0.7]).unwrap(), 1.0);
        // A constant against a varying vector: 0 / (0 + 1e-8) = 0.
        assert_eq!(pearson(&[0.5, 0.5, 0.5], &[0.1, 0.2, 0.6]).unwrap(), 0.0);
        // A hand-computed value: s = [-1, 0, 1], r = [-0.5, 1, -0.5]:
        // dot = 0 -> 0.
        assert!(pearson(&[0.0, 1.0, 2.0], &[0.0, 1.5, 0.0]).unwrap().abs() < 1e-12);
    }

    #[test]
    fn bad_inputs_are_errors() {
        assert!(matches!(
            mmrv(&[0.1], &[0.1, 0.2]),
            Err(MetricError::ShapeMismatch { .. })
        ));
        assert!(pearson(&[], &[]).is_err());
        let e = mmrv(&[f64::NAN], &[0.1]).unwrap_err().to_string();
        assert!(e.contains("NaN"), "{e}");
    }

    #[test]
    fn ranks_average_ties() {
        assert_eq!(ranks(&[3.0, 1.0, 2.0]), vec![2.0, 0.0, 1.0]);
        assert_eq!(ranks(&[1.0, 5.0, 1.0, 0.0]), vec![1.5, 3.0, 1.5, 0.0]);
    }

    #[test]
    fn spearman_is_rank_based_and_checks_input() {
        // Monotone but non-linear: 1 (Pearson of the values would not be).
        let x = [1.0, 2.0, 3.0, 4.0, 5.0];
        let y: Vec<f64> = x.iter().map(|v: &f64| v.powi(5)).collect();
        assert!((spearman(&x, &y).unwrap() - 1.0).abs() < 1e-6);
        let rev: Vec<f64> = y.iter().rev().copied().collect();
        assert!((spearman(&x, &rev).unwrap() + 1.0).abs() < 1e-6);
        // Hand-computed: ranks [0,1,2,3] vs [1,0,3,2]: r = 0.6.
        let r = spearman(&[1.0, 2.0, 3.0, 4.0], &[2.0, 1.0, 4.0, 3.0]).unwrap();
        assert!((r - 0.6).abs() < 1e-6, "{r}");
        assert!(spearman(&[1.0], &[1.0]).is_err());
        assert!(spearman(&[1.0, 2.0], &[1.0]).is_err());
        assert!(spearman(&[1.0, f64::NAN], &[1.0, 2.0]).is_err());
    }
}
