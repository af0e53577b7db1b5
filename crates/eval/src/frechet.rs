//! The Frechet distance between two Gaussians (the statistic of FID/FVD):
//!
//! `d^2 = |mu1 - mu2|^2 + Tr(S1 + S2 - 2 (S1^1/2 S2 S1^1/2)^1/2)`
//!
//! computed with symmetric eigen-decompositions only (no general matrix
//! square root), so it is stable for singular covariances. Note that FVD
//! values depend on the number of samples and on the feature extractor's
//! implementation: compare numbers computed the same way.

use crate::{MetricError, Result};
use nalgebra::{DMatrix, DVector, SymmetricEigen};

/// Mean and covariance of feature vectors.
#[derive(Debug, Clone, PartialEq)]
pub struct Gaussian {
    /// Mean, `[d]`.
    pub mean: DVector<f64>,
    /// Covariance, `[d, d]` (symmetric positive semi-definite).
    pub cov: DMatrix<f64>,
}

impl Gaussian {
    /// Fits mean and unbiased covariance (`1 / (n - 1)`, like `numpy.cov`)
    /// to `n >= 2` feature vectors of equal length.
    pub fn fit(features: &[Vec<f64>]) -> Result<Self> {
        let n = features.len();
        if n < 2 {
            return Err(MetricError::Invalid(format!(
                "a covariance needs at least 2 feature vectors, got {n}"
            )));
        }
        let d = features[0].len();
        if let Some((i, f)) = features.iter().enumerate().find(|(_, f)| f.len() != d) {
            return Err(MetricError::ShapeMismatch {
                what: format!("feature vector {i}"),
                left: d.to_string(),
                right: f.len().to_string(),
            });
        }
        let x = DMatrix::from_fn(n, d, |i, j| features[i][j]);
        let mean = DVector::from_fn(d, |j, _| x.column(j).mean());
        let centred = DMatrix::from_fn(n, d, |i, j| x[(i, j)] - mean[j]);
        let cov = centred.transpose() * &centred / (n as f64 - 1.0);
        Ok(Self { mean, cov })
    }
}

/// Square root of a symmetric positive semi-definite matrix through its
/// eigen-decomposition (negative eigenvalues from rounding clamp to 0).
fn sqrt_psd(m: &DMatrix<f64>) -> DMatrix<f64> {
    let sym = (m + m.transpose()) * 0.5;
    let eig = SymmetricEigen::new(sym);
    let roots = eig.eigenvalues.map(|v| v.max(0.0).sqrt());
    &eig.eigenvectors * DMatrix::from_diagonal(&roots) * eig.eigenvectors.transpose()
}

/// The squared Frechet distance between two Gaussians of the same dimension.
pub fn frechet_distance(a: &Gaussian, b: &Gaussian) -> Result<f64> {
    let d = a.mean.len();
    let shapes = [a.cov.shape(), b.cov.shape()];
    if b.mean.len() != d || shapes.iter().any(|&s| s != (d, d)) {
        return Err(MetricError::ShapeMismatch {
            what: "Gaussians of the Frechet distance".into(),
            left: format!("mean {}, cov {:?}", d, a.cov.shape()),
            right: format!("mean {}, cov {:?}", b.mean.len(), b.cov.shape()),
        });
    }
    if a.mean
        .iter()
        .chain(b.mean.iter())
        .chain(a.cov.iter())
        .chain(b.cov.iter())
        .any(|v| !v.is_finite())
    {
        return Err(MetricError::Invalid(
            "Frechet distance: a mean or covariance entry is not finite".into(),
        ));
    }
    let diff = &a.mean - &b.mean;
    let root_a = sqrt_psd(&a.cov);
    let inner = &root_a * &b.cov * &root_a;
    // Tr((S1^1/2 S2 S1^1/2)^1/2) = sum of the square roots of its eigenvalues.
    let inner = (&inner + inner.transpose()) * 0.5;
    let tr_cross: f64 = SymmetricEigen::new(inner)
        .eigenvalues
        .iter()
        .map(|v| v.max(0.0).sqrt())
        .sum();
    Ok(diff.dot(&diff) + a.cov.trace() + b.cov.trace() - 2.0 * tr_cross)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn one_dimension_closed_form() {
        // d^2 = (m1 - m2)^2 + (s1 - s2)^2.
        let g = |m: f64, s: f64| Gaussian {
            mean: DVector::from_element(1, m),
            cov: DMatrix::from_element(1, 1, s * s),
        };
        let d = frechet_distance(&g(1.0, 2.0), &g(-0.5, 0.5)).unwrap();
        assert!((d - (1.5f64.powi(2) + 1.5f64.powi(2))).abs() < 1e-12, "{d}");
        assert!(frechet_distance(&g(0.3, 0.7), &g(0.3, 0.7)).unwrap().abs() < 1e-12);
    }

    #[test]
    fn commuting_covariances_closed_form() {
        // S1 = Q diag(a) Q^T, S2 = Q diag(b) Q^T:
        // d^2 = |dm|^2 + sum (sqrt(a_i) - sqrt(b_i))^2.
        let angle: f64 = 0.7;
        let (c, s) = (angle.cos(), angle.sin());
        let q = DMatrix::from_row_slice(3, 3, &[c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0]);
        let (ea, eb) = ([4.0, 1.0, 0.25], [1.0, 9.0, 0.0]);
        let cov =
            |e: [f64; 3]| &q * DMatrix::from_diagonal(&DVector::from_row_slice(&e)) * q.transpose();
        let a = Gaussian {
            mean: DVector::from_row_slice(&[1.0, 2.0, 3.0]),
            cov: cov(ea),
        };
        let b = Gaussian {
            mean: DVector::from_row_slice(&[0.0, 2.0, 5.0]),
            cov: cov(eb),
        };
        let expected = 1.0
            + 4.0
            + ea.iter()
                .zip(&eb)
                .map(|(x, y): (&f64, &f64)| (x.sqrt() - y.sqrt()).powi(2))
                .sum::<f64>();
        let d = frechet_distance(&a, &b).unwrap();
        assert!((d - expected).abs() < 1e-9, "{d} vs {expected}");
        // Symmetric in its arguments.
        assert!((frechet_distance(&b, &a).unwrap() - d).abs() < 1e-9);
    }

    #[test]
    fn fit_matches_hand_computation() {
        let g = Gaussian::fit(&[vec![0.0, 1.0], vec![2.0, 1.0], vec![4.0, 4.0]]).unwrap();
        assert_eq!(g.mean.as_slice(), &[2.0, 2.0]);
        // Unbiased: var x = (4 + 0 + 4) / 2 = 4, var y = (1 + 1 + 4) / 2 = 3,
        // cov = (2 + 0 + 4) / 2 = 3.
        assert_eq!(g.cov.as_slice(), &[4.0, 3.0, 3.0, 3.0]);
        assert!(Gaussian::fit(&[vec![1.0]]).is_err());
        assert!(Gaussian::fit(&[vec![1.0], vec![1.0, 2.0]]).is_err());
    }

    #[test]
    fn shape_mismatch_is_an_error() {
        let a = Gaussian {
            mean: DVector::zeros(2),
            cov: DMatrix::identity(2, 2),
        };
        let b = Gaussian {
            mean: DVector::zeros(3),
            cov: DMatrix::identity(3, 3),
        };
        assert!(matches!(
            frechet_distance(&a, &b),
            Err(MetricError::ShapeMismatch { .. })
        ));
    }
}
