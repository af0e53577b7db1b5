//! The world model a planning or policy-evaluation command uses, by name.

use crate::PlanError;
use bridgev2w_world_model::spec::{ModelSpec, RandomPreset};
use std::fmt;
use std::str::FromStr;

/// `perfect` (the synthetic world's own renderer stepping the true scene
/// state: separates the planner from the model), `random` (BridgeV2W with
/// random tiny weights, a smoke test; also `random:PRESET`) or a diffusers
/// folder (a trained BridgeV2W backbone).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PlanModel {
    /// The synthetic renderer.
    Perfect,
    /// A BridgeV2W world model.
    World(ModelSpec),
}

impl FromStr for PlanModel {
    type Err = PlanError;
    fn from_str(s: &str) -> Result<Self, PlanError> {
        match s {
            "perfect" => Ok(Self::Perfect),
            "random" => Ok(Self::World(ModelSpec::Random(RandomPreset::Tiny))),
            other => other.parse().map(Self::World).map_err(|e| {
                PlanError::input(
                    "model",
                    format!("{e}; or perfect (the synthetic renderer) or random (random:tiny)"),
                )
            }),
        }
    }
}

impl fmt::Display for PlanModel {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Perfect => f.write_str("perfect"),
            Self::World(ModelSpec::Random(RandomPreset::Tiny)) => f.write_str("random"),
            Self::World(spec) => write!(f, "{spec}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plan_models_by_name() {
        for text in [
            "perfect",
            "random",
            "random:small2x",
            "assets/demo-model/backbone",
        ] {
            let m: PlanModel = text.parse().expect("a model");
            assert_eq!(m.to_string(), text);
        }
        assert_eq!(
            "random:tiny"
                .parse::<PlanModel>()
                .expect("tiny")
                .to_string(),
            "random"
        );
        let e = "random:huge"
            .parse::<PlanModel>()
            .expect_err("no such preset")
            .to_string();
        assert!(e.contains("perfect") && e.contains("random:small2x"), "{e}");
    }
}
