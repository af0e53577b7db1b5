//! Nelder-Mead minimisation (gradient-free) with the dimension-adaptive
//! coefficients of Gao and Han (2012), for the calibration's 7-10
//! parameters.

/// Where [`minimize`] stopped.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Minimum {
    /// The best point.
    pub x: Vec<f64>,
    /// Its value.
    pub value: f64,
    /// Function evaluations used.
    pub evaluations: usize,
}

/// Minimises `f` from `x0` with an initial simplex of `x0 + steps[i] e_i`,
/// stopping after `max_evaluations` or when the simplex's values span less
/// than `tolerance`. Non-finite values count as +infinity.
pub(crate) fn minimize(
    f: &dyn Fn(&[f64]) -> f64,
    x0: &[f64],
    steps: &[f64],
    max_evaluations: usize,
    tolerance: f64,
) -> Minimum {
    let n = x0.len();
    let eval = |x: &[f64]| {
        let v = f(x);
        if v.is_finite() {
            v
        } else {
            f64::INFINITY
        }
    };
    let nf = n.max(1) as f64;
    let (alpha, beta, gamma, delta) =
        (1.0, 1.0 + 2.0 / nf, 0.75 - 1.0 / (2.0 * nf), 1.0 - 1.0 / nf);
    let mut simplex: Vec<(Vec<f64>, f64)> = Vec::with_capacity(n + 1);
    simplex.push((x0.to_vec(), eval(x0)));
    for i in 0..n {
        let mut x = x0.to_vec();
        x[i] += steps[i];
        let v = eval(&x);
        simplex.push((x, v));
    }
    let mut evaluations = n + 1;
    while evaluations < max_evaluations {
        simplex.sort_by(|a, b| a.1.total_cmp(&b.1));
        let (best, worst) = (simplex[0].1, simplex[n].1);
        if n == 0 || (worst - best).abs() <= tolerance {
            break;
        }
        let centroid: Vec<f64> = (0..n)
            .map(|j| simplex[..n].iter().map(|(x, _)| x[j]).sum::<f64>() / nf)
            .collect();
        let along = |t: f64| -> Vec<f64> {
            centroid
                .iter()
                .zip(&simplex[n].0)
                .map(|(c, w)| c + t * (c - w))
                .collect()
        };
        let reflected = along(alpha);
        let fr = eval(&reflected);
        evaluations += 1;
        if fr < best {
            let expanded = along(beta);
            let fe = eval(&expanded);
            evaluations += 1;
            simplex[n] = if fe < fr {
                (expanded, fe)
            } else {
                (reflected, fr)
            };
            continue;
        }
        if fr < simplex[n - 1].1 {
            simplex[n] = (reflected, fr);
            continue;
        }
        let (contracted, fc) = if fr < worst {
            let x = along(gamma);
            let v = eval(&x);
            (x, v)
        } else {
            let x = along(-gamma);
            let v = eval(&x);
            (x, v)
        };
        evaluations += 1;
        if fc < fr.min(worst) {
            simplex[n] = (contracted, fc);
            continue;
        }
        // Shrink towards the best point.
        let best_x = simplex[0].0.clone();
        for item in simplex.iter_mut().skip(1) {
            let x: Vec<f64> = best_x
                .iter()
                .zip(&item.0)
                .map(|(b, v)| b + delta * (v - b))
                .collect();
            let v = eval(&x);
            *item = (x, v);
        }
        evaluations += n;
    }
    simplex.sort_by(|a, b| a.1.total_cmp(&b.1));
    let (x, value) = simplex.swap_remove(0);
    Minimum {
        x,
        value,
        evaluations,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_the_minimum_of_a_rotated_quadratic() {
        let f = |x: &[f64]| {
            let (a, b, c) = (x[0] - 1.0, x[1] + 2.0, x[2] - 0.5);
            (a + 0.5 * b).powi(2) + 3.0 * b * b + 10.0 * c * c
        };
        let m = minimize(&f, &[0.0, 0.0, 0.0], &[0.5, 0.5, 0.5], 2000, 1e-14);
        assert!((m.x[0] - 1.0).abs() < 1e-4, "{:?}", m);
        assert!((m.x[1] + 2.0).abs() < 1e-4, "{:?}", m);
        assert!((m.x[2] - 0.5).abs() < 1e-4, "{:?}", m);
        assert!(m.evaluations <= 2000);
    }

    #[test]
    fn stops_at_the_evaluation_budget_and_treats_nan_as_worst() {
        let f = |x: &[f64]| {
            if x[0] > 2.0 {
                f64::NAN
            } else {
                (x[0] - 1.5).powi(2)
            }
        };
        let m = minimize(&f, &[0.0], &[1.0], 25, 0.0);
        assert!(m.evaluations <= 26, "{}", m.evaluations);
        assert!((m.x[0] - 1.5).abs() < 0.05, "{:?}", m);
    }
}
