//! Seeded, reproducible randomness: one home for the seed mixing and the
//! normal draws every crate uses, so a seed means the same stream
//! everywhere.
//!
//! * [`SplitMix64`]: a tiny generator (Steele, Lea and Flood's SplitMix64:
//!   a Weyl sequence with step [`GOLDEN_GAMMA`] and the [`mix64`] finaliser);
//! * [`mix64`]: the finaliser alone, a bijective mixing of 64 bits;
//! * [`derive_seed`]: a well-mixed seed from several parts (seed, step,
//!   purpose, ...);
//! * [`trial_seed`]: the seed of trial `i` of an experiment;
//! * [`box_muller`] and [`standard_normal`]: N(0, 1) draws from uniforms.

use rand::Rng;

/// 2^64 / golden ratio: SplitMix64's Weyl step, and the multiplier that
/// spreads consecutive integers over the 64-bit range.
pub const GOLDEN_GAMMA: u64 = 0x9E37_79B9_7F4A_7C15;

/// SplitMix64's finaliser (a bijection of `u64` with good avalanche).
#[inline]
pub fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A small deterministic PRNG (SplitMix64) for IK restarts, benchmarks and
/// tests; not for cryptography.
#[derive(Debug, Clone)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    /// A generator from a seed.
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    /// Next 64 random bits.
    #[inline]
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(GOLDEN_GAMMA);
        mix64(self.0)
    }

    /// Uniform in `[0, 1)` (53 bits).
    #[inline]
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in `[lo, hi)`.
    #[inline]
    pub fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.next_f64()
    }
}

/// A well-mixed seed from `parts` (e.g. `[seed, step, purpose]`): each part
/// is folded into the state, which is then mixed by [`mix64`].
pub fn derive_seed(parts: &[u64]) -> u64 {
    let mut h: u64 = GOLDEN_GAMMA;
    for &p in parts {
        h ^= p.wrapping_add(GOLDEN_GAMMA).wrapping_add(h << 6);
        h = h.wrapping_add(GOLDEN_GAMMA);
        h = mix64(h);
    }
    h
}

/// The seed of trial `trial` of an experiment seeded `seed`: the trial's
/// index spread by [`GOLDEN_GAMMA`], so neighbouring trials' streams differ
/// in many bits.
#[inline]
pub fn trial_seed(seed: u64, trial: u64) -> u64 {
    seed ^ trial.wrapping_mul(GOLDEN_GAMMA)
}

/// The Box-Muller transform: one N(0, 1) value from `u1` in `(0, 1]` and
/// `u2` in `[0, 1)`.
#[inline]
pub fn box_muller(u1: f64, u2: f64) -> f64 {
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}

/// One N(0, 1) draw from `rng` ([`box_muller`] of two uniform draws).
#[inline]
pub fn standard_normal(rng: &mut impl Rng) -> f64 {
    let u1: f64 = rng.gen_range(f64::MIN_POSITIVE..1.0);
    let u2: f64 = rng.gen_range(0.0..1.0);
    box_muller(u1, u2)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn splitmix64_matches_the_reference_stream() {
        // The first outputs of SplitMix64 seeded 1234567 (the reference C
        // implementation by Vigna).
        let mut g = SplitMix64::new(1_234_567);
        assert_eq!(g.next_u64(), 6_457_827_717_110_365_317);
        assert_eq!(g.next_u64(), 3_203_168_211_198_807_973);
        let x = g.next_f64();
        assert!((0.0..1.0).contains(&x));
    }

    #[test]
    fn normal_draws_have_unit_moments() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let n = 20_000;
        let v: Vec<f64> = (0..n).map(|_| standard_normal(&mut rng)).collect();
        let mean = v.iter().sum::<f64>() / n as f64;
        let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64;
        assert!(
            mean.abs() < 0.03 && (var - 1.0).abs() < 0.05,
            "{mean} {var}"
        );
        assert!((box_muller(1.0, 0.3)).abs() < 1e-12);
    }

    #[test]
    fn derived_seeds_differ_by_every_part() {
        let a = derive_seed(&[1, 2, 3]);
        assert_ne!(a, derive_seed(&[1, 2, 4]));
        assert_ne!(a, derive_seed(&[0, 2, 3]));
        assert_eq!(a, derive_seed(&[1, 2, 3]));
        assert_eq!(trial_seed(5, 0), 5);
    }
}
