//! The scheduler config (`scheduler_config.json`) and its checks: every
//! field is checked when the config is read, and the schedule it gives must
//! be one the samplers can step (alpha-bar finite and in (0, 1)), so a bad
//! value is named by field before any work instead of surfacing as NaN
//! latents after the denoising loop.

use super::NoiseSchedule;
use crate::error::{Result, WorldModelError};
use bridgev2w_io::json::read_json;
use std::path::Path;

/// How betas are laid out over the training timesteps.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum BetaSchedule {
    /// Linear in beta (f32).
    Linear,
    /// Linear in sqrt(beta), squared (f64).
    ScaledLinear,
    /// Cosine alpha-bar (f32), betas capped at 0.999.
    SquaredcosCapV2,
}

/// What the model predicts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum PredictionType {
    /// The added noise.
    Epsilon,
    /// The clean sample.
    Sample,
    /// The velocity `sqrt(a) noise - sqrt(1 - a) x0`.
    VPrediction,
}

/// How inference timesteps are spread over the training timesteps.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum TimestepSpacing {
    /// `round(linspace(0, N - 1, n))`, descending.
    Linspace,
    /// `arange(n) * (N / n) + steps_offset`, descending.
    Leading,
    /// `round(arange(N, 0, -N / n)) - 1`.
    Trailing,
}

/// Which sampler steps the chain.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SamplerKind {
    /// `CogVideoXDDIMScheduler` (deterministic).
    Ddim,
    /// `CogVideoXDPMScheduler` (second-order, stochastic).
    Dpm,
}

fn default_train_timesteps() -> usize {
    1000
}
fn default_beta_start() -> f64 {
    0.00085
}
fn default_beta_end() -> f64 {
    0.012
}
fn default_beta_schedule() -> BetaSchedule {
    BetaSchedule::ScaledLinear
}
fn default_true() -> bool {
    true
}
fn default_prediction() -> PredictionType {
    PredictionType::Epsilon
}
fn default_spacing() -> TimestepSpacing {
    TimestepSpacing::Leading
}
fn default_snr_shift() -> f64 {
    3.0
}

/// The most training timesteps a scheduler config may name (CogVideoX's:
/// 1000): the schedule holds one value per timestep.
pub const MAX_TRAIN_TIMESTEPS: usize = 100_000;

/// Deserializes an enum field, naming the field in the error (serde's own
/// message names the value and the choices, not the field).
fn named_field<'de, D, T>(d: D, field: &str) -> std::result::Result<T, D::Error>
where
    D: serde::Deserializer<'de>,
    T: serde::Deserialize<'de>,
{
    T::deserialize(d).map_err(|e| serde::de::Error::custom(format!("field `{field}`: {e}")))
}

fn de_beta_schedule<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> std::result::Result<BetaSchedule, D::Error> {
    named_field(d, "beta_schedule")
}

fn de_prediction<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> std::result::Result<PredictionType, D::Error> {
    named_field(d, "prediction_type")
}

fn de_spacing<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> std::result::Result<TimestepSpacing, D::Error> {
    named_field(d, "timestep_spacing")
}

/// A scheduler config, as diffusers' `scheduler_config.json` (unknown fields ignored,
/// missing ones get diffusers' defaults).
#[derive(Debug, Clone, PartialEq, serde::Deserialize, serde::Serialize)]
pub struct SchedulerConfig {
    /// `CogVideoXDDIMScheduler` or `CogVideoXDPMScheduler` (absent: DDIM).
    #[serde(
        rename = "_class_name",
        default,
        skip_serializing_if = "Option::is_none"
    )]
    pub class_name: Option<String>,
    /// Training timesteps N.
    #[serde(default = "default_train_timesteps")]
    pub num_train_timesteps: usize,
    /// First beta.
    #[serde(default = "default_beta_start")]
    pub beta_start: f64,
    /// Last beta.
    #[serde(default = "default_beta_end")]
    pub beta_end: f64,
    /// Beta layout.
    #[serde(
        default = "default_beta_schedule",
        deserialize_with = "de_beta_schedule"
    )]
    pub beta_schedule: BetaSchedule,
    /// Explicit betas (override the schedule).
    #[serde(default)]
    pub trained_betas: Option<Vec<f64>>,
    /// Final step goes to alpha-bar 1 (else to alpha-bar of timestep 0).
    #[serde(default = "default_true")]
    pub set_alpha_to_one: bool,
    /// Added to `leading` timesteps.
    #[serde(default)]
    pub steps_offset: i64,
    /// What the model predicts.
    #[serde(default = "default_prediction", deserialize_with = "de_prediction")]
    pub prediction_type: PredictionType,
    /// Inference timestep spacing.
    #[serde(default = "default_spacing", deserialize_with = "de_spacing")]
    pub timestep_spacing: TimestepSpacing,
    /// Rescale to zero terminal SNR.
    #[serde(default)]
    pub rescale_betas_zero_snr: bool,
    /// SNR shift `s`: alpha-bar becomes `a / (s + (1 - s) a)`.
    #[serde(default = "default_snr_shift")]
    pub snr_shift_scale: f64,
}

impl SchedulerConfig {
    fn cogvideox(snr_shift_scale: f64) -> Self {
        Self {
            class_name: Some("CogVideoXDDIMScheduler".to_owned()),
            num_train_timesteps: 1000,
            beta_start: 0.00085,
            beta_end: 0.012,
            beta_schedule: BetaSchedule::ScaledLinear,
            trained_betas: None,
            set_alpha_to_one: true,
            steps_offset: 0,
            prediction_type: PredictionType::VPrediction,
            timestep_spacing: TimestepSpacing::Trailing,
            rescale_betas_zero_snr: true,
            snr_shift_scale,
        }
    }

    /// `THUDM/CogVideoX-5b-I2V`'s `scheduler/scheduler_config.json`.
    pub fn cogvideox_5b_i2v() -> Self {
        Self::cogvideox(1.0)
    }

    /// `THUDM/CogVideoX-2b`'s `scheduler/scheduler_config.json`.
    pub fn cogvideox_2b() -> Self {
        Self::cogvideox(3.0)
    }

    /// Reads `scheduler_config.json`.
    pub fn load(path: &Path) -> Result<Self> {
        let cfg: Self = read_json(path)?;
        cfg.validate(path)?;
        Ok(cfg)
    }

    /// The sampler named by `_class_name`.
    pub fn sampler_kind(&self) -> Result<SamplerKind> {
        match self.class_name.as_deref() {
            None | Some("CogVideoXDDIMScheduler") => Ok(SamplerKind::Ddim),
            Some("CogVideoXDPMScheduler") => Ok(SamplerKind::Dpm),
            Some(other) => Err(WorldModelError::config(
                "scheduler_config.json",
                "_class_name",
                format!("`{other}`: expected CogVideoXDDIMScheduler or CogVideoXDPMScheduler"),
            )),
        }
    }

    /// Checks every field and the schedule they give; errors name `path`.
    pub(crate) fn validate(&self, path: &Path) -> Result<()> {
        let err = |field: &str, message: String| Err(WorldModelError::config(path, field, message));
        let n = self.num_train_timesteps;
        if !(1..=MAX_TRAIN_TIMESTEPS).contains(&n) {
            return err(
                "num_train_timesteps",
                format!("{n}: expected 1..={MAX_TRAIN_TIMESTEPS} (MAX_TRAIN_TIMESTEPS; CogVideoX: 1000)"),
            );
        }
        match (&self.trained_betas, self.beta_schedule) {
            (Some(b), _) => {
                if b.len() != n {
                    return err(
                        "trained_betas",
                        format!("has {} values, num_train_timesteps is {n}", b.len()),
                    );
                }
                if let Some((i, v)) = b
                    .iter()
                    .enumerate()
                    .find(|(_, v)| !(**v > 0.0 && **v < 1.0))
                {
                    return err(
                        "trained_betas",
                        format!("value {i} is {v}: expected a beta in (0, 1)"),
                    );
                }
            }
            // The cosine schedule has no beta_start or beta_end.
            (None, BetaSchedule::SquaredcosCapV2) => {}
            (None, _) => {
                for (field, v) in [("beta_start", self.beta_start), ("beta_end", self.beta_end)] {
                    if !(v > 0.0 && v < 1.0) {
                        return err(
                            field,
                            format!("{v}: expected a beta in (0, 1) (CogVideoX: beta_start 0.00085, beta_end 0.012)"),
                        );
                    }
                }
            }
        }
        if !(self.snr_shift_scale.is_finite() && self.snr_shift_scale > 0.0) {
            return err(
                "snr_shift_scale",
                format!(
                    "{}: expected a finite number > 0 (CogVideoX: 1 or 3)",
                    self.snr_shift_scale
                ),
            );
        }
        if !(0..n as i64).contains(&self.steps_offset) {
            return err(
                "steps_offset",
                format!(
                    "{}: expected 0..{n} (a timestep offset within num_train_timesteps)",
                    self.steps_offset
                ),
            );
        }
        self.sampler_kind().map_err(|_| {
            WorldModelError::config(
                path,
                "_class_name",
                format!(
                    "`{}`: expected CogVideoXDDIMScheduler or CogVideoXDPMScheduler",
                    self.class_name.as_deref().unwrap_or_default()
                ),
            )
        })?;
        self.check_schedule(path)
    }

    /// Refuses fields whose schedule the samplers cannot step: alpha-bar
    /// must be finite and in (0, 1) at every training timestep (0 only at
    /// the last one with `rescale_betas_zero_snr`): at 1 the DDIM step
    /// divides by `1 - alpha-bar` = 0, at 0 an epsilon prediction divides by
    /// its square root and DPM's log-SNR is undefined.
    fn check_schedule(&self, path: &Path) -> Result<()> {
        let schedule = NoiseSchedule::new(self);
        let n = self.num_train_timesteps;
        let field = match (&self.trained_betas, self.beta_schedule) {
            (Some(_), _) => "trained_betas",
            (None, BetaSchedule::SquaredcosCapV2) => "num_train_timesteps",
            (None, _) => "beta_start/beta_end",
        };
        let schedule_name = serde_json::to_value(self.beta_schedule)
            .ok()
            .and_then(|v| v.as_str().map(str::to_owned))
            .unwrap_or_default();
        let from = format!(
            "beta_schedule {schedule_name}, beta_start {}, beta_end {}, {n} timesteps, snr_shift_scale {}, rescale_betas_zero_snr {}",
            self.beta_start, self.beta_end, self.snr_shift_scale, self.rescale_betas_zero_snr
        );
        let terminal_zero = |t: usize| self.rescale_betas_zero_snr && t + 1 == n;
        for (t, &a) in schedule.alphas_cumprod.iter().enumerate() {
            let problem = if !a.is_finite() {
                format!("is {a}")
            } else if a >= 1.0 {
                format!("is {a} (no noise: a beta rounds to 0 in float32)")
            } else if a <= 0.0 && !terminal_zero(t) {
                "underflows to 0 (the betas are too large for this many timesteps)".to_owned()
            } else {
                continue;
            };
            let field = if self.rescale_betas_zero_snr && !a.is_finite() {
                "rescale_betas_zero_snr"
            } else {
                field
            };
            return Err(WorldModelError::config(
                path,
                field,
                format!(
                    "alpha-bar at timestep {t} {problem}, from {from}: expected every alpha-bar in (0, 1)"
                ),
            ));
        }
        Ok(())
    }
}
