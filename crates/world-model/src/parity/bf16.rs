//! bf16 parity: the Rust model in bfloat16 against diffusers in bfloat16, both
//! measured against diffusers' float32 output.
//!
//! bf16 keeps 8 significant bits, so neither side matches f32 closely: what is
//! checked is that this implementation loses no more accuracy than diffusers
//! does. For each output, with `ref` diffusers' f32 value (`NAME` in
//! `io.safetensors`) and `peer` diffusers' bf16 value (`NAME_bf16`, written by
//! `make_parity_fixture.py ... --bf16`):
//!
//! * ours: the error of this crate's bf16 output against `ref`;
//! * diffusers: the error of `peer` against `ref`;
//!
//! each as `max_rel = max |x - ref| / max |ref|` and
//! `rms_rel = rms(x - ref) / rms(ref)`. An output passes when both of ours
//! are at most [`BF16_FACTOR`] times diffusers' plus [`BF16_EPSILON`]
//! ([`Bf16Output::within`]).

use super::{fixture_computed, FixtureIo};
use crate::device::Precision;
use crate::error::{Result, WorldModelError};
use std::path::Path;
use tch::{Kind, Tensor};

/// How many times diffusers' own bf16 error ours may reach.
pub const BF16_FACTOR: f64 = 1.5;

/// Added to the bound (relative error): room for rounding where diffusers'
/// own error is near zero, small against the errors bf16 makes (about 1e-2
/// on the fixtures of `tests/parity_bf16.rs`).
pub const BF16_EPSILON: f64 = 1e-3;

/// The error of a bf16 output against diffusers' f32 one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bf16Error {
    /// `max |x - ref| / max |ref|`.
    pub max_rel: f64,
    /// `rms(x - ref) / rms(ref)`.
    pub rms_rel: f64,
}

impl Bf16Error {
    /// The error of `got` against `want` (same shape; any float kind).
    fn of(got: &Tensor, want: &Tensor) -> Self {
        let got = got.to_device(tch::Device::Cpu).to_kind(Kind::Double);
        let want = want.to_kind(Kind::Double);
        if want.numel() == 0 {
            return Self {
                max_rel: 0.0,
                rms_rel: 0.0,
            };
        }
        let diff = &got - &want;
        let rms = |t: &Tensor| t.square().mean(Kind::Double).sqrt().double_value(&[]);
        let ratio = |num: f64, den: f64| if den > 0.0 { num / den } else { num };
        Self {
            max_rel: ratio(
                diff.abs().max().double_value(&[]),
                want.abs().max().double_value(&[]),
            ),
            rms_rel: ratio(rms(&diff), rms(&want)),
        }
    }
}

/// One output compared in bf16.
#[derive(Debug, Clone, PartialEq)]
pub struct Bf16Output {
    /// Output name in `io.safetensors` (diffusers' f32 value; `NAME_bf16` its bf16 one).
    pub name: String,
    /// Its shape.
    pub shape: Vec<i64>,
    /// This crate's bf16 output against diffusers' f32 output.
    pub ours: Bf16Error,
    /// diffusers' bf16 output against its f32 output.
    pub diffusers: Bf16Error,
}

impl Bf16Output {
    /// Whether ours is within `factor` times diffusers' error plus `epsilon`,
    /// in both statistics (and finite).
    pub fn within(&self, factor: f64, epsilon: f64) -> bool {
        let ok = |ours: f64, theirs: f64| ours.is_finite() && ours <= factor * theirs + epsilon;
        ok(self.ours.max_rel, self.diffusers.max_rel)
            && ok(self.ours.rms_rel, self.diffusers.rms_rel)
    }
}

/// The result of running one fixture in bf16.
#[derive(Debug, Clone, PartialEq)]
pub struct Bf16Report {
    /// The fixture's kind (`transformer` or `vae`).
    pub kind: String,
    /// Every output that has a bf16 counterpart.
    pub outputs: Vec<Bf16Output>,
}

/// Runs a transformer or VAE fixture made with `--bf16` with the Rust model in
/// bf16 on the CPU, and compares each output that has a `NAME_bf16`
/// counterpart (see the module docs).
pub fn run_fixture_bf16(dir: &Path) -> Result<Bf16Report> {
    let c = fixture_computed(dir, Precision::Bf16)?;
    let outputs = compare_bf16(&c.io, &c.outputs)?;
    let kind = c.kind;
    if outputs.is_empty() {
        return Err(WorldModelError::input(
            "parity fixture",
            format!(
                "{}: no bf16 outputs (NAME_bf16) to compare: make it with `make_parity_fixture.py {kind} ... --bf16`",
                dir.display()
            ),
        ));
    }
    Ok(Bf16Report { kind, outputs })
}

/// The computed outputs that have a `NAME_bf16` counterpart, each against
/// `NAME`, and the counterpart against `NAME`.
fn compare_bf16(io: &FixtureIo, computed: &[(String, Tensor)]) -> Result<Vec<Bf16Output>> {
    let mut out = Vec::new();
    for (name, got) in computed {
        let peer_name = format!("{name}_bf16");
        if !io.contains(&peer_name) {
            continue;
        }
        let (want, peer) = (io.get(name)?, io.get(&peer_name)?);
        for (what, t) in [("computed", got), (peer_name.as_str(), peer)] {
            if t.size() != want.size() {
                return Err(WorldModelError::input(
                    name.as_str(),
                    format!(
                        "shape {:?} ({what}), diffusers' f32 output has {:?}",
                        t.size(),
                        want.size()
                    ),
                ));
            }
        }
        out.push(Bf16Output {
            name: name.clone(),
            shape: want.size(),
            ours: Bf16Error::of(got, want),
            diffusers: Bf16Error::of(peer, want),
        });
    }
    Ok(out)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn errors_are_relative_to_the_reference_and_the_bound_is_one_sided() {
        let want = Tensor::from_slice(&[1.0f32, -2.0, 4.0, 0.0]);
        let got = Tensor::from_slice(&[1.0f32, -2.0, 4.5, 0.0]);
        let e = Bf16Error::of(&got, &want);
        assert!((e.max_rel - 0.125).abs() < 1e-12, "{e:?}");
        // rms(diff) = 0.25, rms(want) = sqrt(21 / 4).
        assert!(
            (e.rms_rel - 0.25 / (21.0f64 / 4.0).sqrt()).abs() < 1e-12,
            "{e:?}"
        );
        let o = |ours: f64, theirs: f64| Bf16Output {
            name: "x".into(),
            shape: vec![4],
            ours: Bf16Error {
                max_rel: ours,
                rms_rel: ours,
            },
            diffusers: Bf16Error {
                max_rel: theirs,
                rms_rel: theirs,
            },
        };
        assert!(
            o(0.0, 0.01).within(1.5, 0.0),
            "more accurate than diffusers passes"
        );
        assert!(o(0.015, 0.01).within(1.5, 0.0));
        assert!(!o(0.016, 0.01).within(1.5, 0.0), "sloppier than 1.5x fails");
        assert!(o(0.016, 0.01).within(1.5, 1e-3));
        assert!(!o(f64::NAN, 0.01).within(1.5, 1.0), "NaN fails");
    }
}
