//! The CogVideoX noise schedulers, numerically as diffusers' `CogVideoXDDIMScheduler`
//! and `CogVideoXDPMScheduler`.
//!
//! Noise schedule: betas (`scaled_linear`: squares of a linspace of square roots,
//! `linear`, `squaredcos_cap_v2`, or given), `alphas_cumprod` shifted to a lower
//! signal-to-noise ratio by `snr_shift_scale` (`a / (s + (1 - s) a)`), optionally
//! rescaled to zero terminal SNR (Lin et al. 2023, algorithm 1). Inference timesteps
//! by `leading`, `linspace` or `trailing` spacing. Both samplers take a v-prediction
//! (or epsilon / sample) model output and step from timestep `t` to
//! `t - num_train_timesteps / num_inference_steps` (diffusers' rule, also for trailing
//! spacing); the final step goes to `final_alpha_cumprod` (1 with `set_alpha_to_one`).
//!
//! The schedule's scalars are computed in f64 (`scaled_linear` is f64 in diffusers
//! too; for the f32 schedules the betas and the cumulative product are rounded to f32
//! as diffusers computes them) and applied to tensors as scalars.

use crate::error::{Result, WorldModelError};
use std::path::Path;
use tch::Tensor;

mod config;
#[cfg(test)]
mod tests;

pub use config::{
    BetaSchedule, PredictionType, SamplerKind, SchedulerConfig, TimestepSpacing,
    MAX_TRAIN_TIMESTEPS,
};

/// Rounds through f32 (diffusers keeps these schedules in float32).
fn f32r(x: f64) -> f64 {
    x as f32 as f64
}

/// torch.linspace's evaluation order (from both ends toward the middle).
fn linspace(start: f64, end: f64, n: usize) -> Vec<f64> {
    if n == 1 {
        return vec![start];
    }
    let step = (end - start) / (n - 1) as f64;
    let half = n / 2;
    (0..n)
        .map(|i| {
            if i < half {
                start + step * i as f64
            } else {
                end - step * (n - 1 - i) as f64
            }
        })
        .collect()
}

/// The noise schedule: alpha-bar per training timestep.
#[derive(Debug, Clone)]
pub struct NoiseSchedule {
    /// `alphas_cumprod` after SNR shift and optional zero-SNR rescale.
    pub alphas_cumprod: Vec<f64>,
    /// Alpha-bar after the last step.
    pub final_alpha_cumprod: f64,
}

impl NoiseSchedule {
    /// Computes the schedule of a config.
    pub fn new(cfg: &SchedulerConfig) -> Self {
        let n = cfg.num_train_timesteps;
        // f32 schedules are rounded at every stored stage, as torch float32 tensors are.
        let (betas, is_f32): (Vec<f64>, bool) = match (&cfg.trained_betas, cfg.beta_schedule) {
            (Some(b), _) => (b.iter().map(|&x| f32r(x)).collect(), true),
            (None, BetaSchedule::Linear) => (
                linspace(f32r(cfg.beta_start), f32r(cfg.beta_end), n)
                    .into_iter()
                    .map(f32r)
                    .collect(),
                true,
            ),
            (None, BetaSchedule::ScaledLinear) => (
                linspace(cfg.beta_start.sqrt(), cfg.beta_end.sqrt(), n)
                    .into_iter()
                    .map(|x| x * x)
                    .collect(),
                false,
            ),
            (None, BetaSchedule::SquaredcosCapV2) => {
                let alpha_bar = |t: f64| {
                    ((t + 0.008) / 1.008 * std::f64::consts::PI / 2.0)
                        .cos()
                        .powi(2)
                };
                (
                    (0..n)
                        .map(|i| {
                            let t1 = i as f64 / n as f64;
                            let t2 = (i + 1) as f64 / n as f64;
                            f32r((1.0 - alpha_bar(t2) / alpha_bar(t1)).min(0.999))
                        })
                        .collect(),
                    true,
                )
            }
        };
        let round = |x: f64| if is_f32 { f32r(x) } else { x };
        let mut cumprod = 1.0f64;
        let s = if is_f32 {
            f32r(cfg.snr_shift_scale)
        } else {
            cfg.snr_shift_scale
        };
        let mut alphas_cumprod: Vec<f64> = betas
            .iter()
            .map(|&b| {
                cumprod = round(cumprod * round(1.0 - b));
                cumprod
            })
            .map(|a| round(a / round(s + round(round(1.0 - s) * a))))
            .collect();
        if cfg.rescale_betas_zero_snr {
            let sqrt: Vec<f64> = alphas_cumprod.iter().map(|a| round(a.sqrt())).collect();
            let first = sqrt[0];
            let last = sqrt[n - 1];
            let scale = round(first / round(first - last));
            alphas_cumprod = sqrt
                .iter()
                .map(|&x| {
                    let y = round(round(x - last) * scale);
                    round(y * y)
                })
                .collect();
        }
        let final_alpha_cumprod = if cfg.set_alpha_to_one {
            1.0
        } else {
            alphas_cumprod[0]
        };
        Self {
            alphas_cumprod,
            final_alpha_cumprod,
        }
    }

    /// Alpha-bar at a training timestep (negative: the final alpha-bar).
    pub fn alpha_bar(&self, t: i64) -> Result<f64> {
        if t < 0 {
            return Ok(self.final_alpha_cumprod);
        }
        self.alphas_cumprod.get(t as usize).copied().ok_or_else(|| {
            WorldModelError::input(
                "timestep",
                format!(
                    "{t} is outside the {} training timesteps",
                    self.alphas_cumprod.len()
                ),
            )
        })
    }
}

/// Inference timesteps (descending) for `num_inference_steps` steps.
pub fn inference_timesteps(cfg: &SchedulerConfig, num_inference_steps: usize) -> Result<Vec<i64>> {
    let n = cfg.num_train_timesteps;
    if num_inference_steps == 0 || num_inference_steps > n {
        return Err(WorldModelError::input(
            "num_inference_steps",
            format!("{num_inference_steps}: expected 1..={n} (the training timesteps)"),
        ));
    }
    let k = num_inference_steps;
    Ok(match cfg.timestep_spacing {
        TimestepSpacing::Linspace => linspace(0.0, (n - 1) as f64, k)
            .into_iter()
            .rev()
            .map(|x| x.round_ties_even() as i64)
            .collect(),
        TimestepSpacing::Leading => {
            let ratio = (n / k) as i64;
            let last = (k as i64 - 1) * ratio + cfg.steps_offset;
            if !(0..n as i64).contains(&last) {
                return Err(WorldModelError::config(
                    "scheduler config",
                    "steps_offset",
                    format!(
                        "{}: with leading spacing and {k} inference steps the first timestep is {last}, outside the {n} training timesteps; expected steps_offset 0..={}",
                        cfg.steps_offset,
                        n as i64 - 1 - (k as i64 - 1) * ratio
                    ),
                ));
            }
            (0..k as i64)
                .rev()
                .map(|i| i * ratio + cfg.steps_offset)
                .collect()
        }
        TimestepSpacing::Trailing => {
            // numpy: arange(N, 0, -N/k) has ceil(N / (N/k)) elements.
            let ratio = n as f64 / k as f64;
            let count = ((n as f64) / ratio).ceil() as usize;
            (0..count)
                .map(|i| (n as f64 - i as f64 * ratio).round_ties_even() as i64 - 1)
                .collect()
        }
    })
}

/// A CogVideoX sampler: the schedule, the inference timesteps and the sampler state.
#[derive(Debug)]
pub struct Scheduler {
    cfg: SchedulerConfig,
    kind: SamplerKind,
    schedule: NoiseSchedule,
    timesteps: Vec<i64>,
    /// DPM: the previous step's predicted clean sample.
    old_pred_original: Option<Tensor>,
    step_index: usize,
}

impl Scheduler {
    /// A sampler for a config (its `_class_name` picks DDIM or DPM).
    pub fn new(cfg: SchedulerConfig) -> Result<Self> {
        cfg.validate(Path::new("scheduler config"))?;
        let kind = cfg.sampler_kind()?;
        Ok(Self {
            schedule: NoiseSchedule::new(&cfg),
            cfg,
            kind,
            timesteps: Vec::new(),
            old_pred_original: None,
            step_index: 0,
        })
    }

    /// Overrides the sampler kind (DDIM or DPM) keeping the schedule.
    pub fn with_kind(mut self, kind: SamplerKind) -> Self {
        self.kind = kind;
        self
    }

    /// The config.
    pub fn config(&self) -> &SchedulerConfig {
        &self.cfg
    }

    /// The sampler kind.
    pub fn kind(&self) -> SamplerKind {
        self.kind
    }

    /// The noise schedule.
    pub fn schedule(&self) -> &NoiseSchedule {
        &self.schedule
    }

    /// Sets `num_inference_steps` and resets the sampler state.
    pub fn set_timesteps(&mut self, num_inference_steps: usize) -> Result<&[i64]> {
        let timesteps = inference_timesteps(&self.cfg, num_inference_steps)?;
        if self.cfg.prediction_type == PredictionType::Epsilon {
            // Alpha-bar 0 (the zero-SNR terminal): x0 = (x - sqrt(1 - a) eps) / sqrt(a).
            for &t in &timesteps {
                if self.schedule.alpha_bar(t)? <= 0.0 {
                    return Err(WorldModelError::config(
                        "scheduler config",
                        "prediction_type",
                        format!(
                            "epsilon with rescale_betas_zero_snr = true: alpha-bar is 0 at inference timestep {t}, where an epsilon prediction gives no sample (a division by zero); expected prediction_type v_prediction (CogVideoX's) or rescale_betas_zero_snr = false"
                        ),
                    ));
                }
            }
        }
        self.timesteps = timesteps;
        self.old_pred_original = None;
        self.step_index = 0;
        Ok(&self.timesteps)
    }

    /// Starts the chain at inference step `k` (after [`Scheduler::set_timesteps`]),
    /// as a chain that starts from a partly noised sample does: the first
    /// step that runs is then first order.
    pub fn skip_steps(&mut self, k: usize) -> Result<()> {
        if k >= self.timesteps.len() {
            return Err(WorldModelError::input(
                "skip_steps",
                format!(
                    "{k}: expected fewer than the {} inference timesteps",
                    self.timesteps.len()
                ),
            ));
        }
        self.step_index = k;
        self.old_pred_original = None;
        Ok(())
    }

    /// The inference timesteps (after [`Scheduler::set_timesteps`]).
    pub fn timesteps(&self) -> &[i64] {
        &self.timesteps
    }

    fn prev_timestep(&self, t: i64) -> i64 {
        let k = self.timesteps.len().max(1);
        t - (self.cfg.num_train_timesteps / k) as i64
    }

    fn pred_original(&self, model_output: &Tensor, sample: &Tensor, a_t: f64) -> Tensor {
        let b_t = 1.0 - a_t;
        match self.cfg.prediction_type {
            PredictionType::Epsilon => (sample - model_output * b_t.sqrt()) / a_t.sqrt(),
            PredictionType::Sample => model_output.shallow_clone(),
            PredictionType::VPrediction => sample * a_t.sqrt() - model_output * b_t.sqrt(),
        }
    }

    /// One DDIM step from timestep `t`: returns (previous sample, predicted x0).
    pub fn step_ddim(
        &self,
        model_output: &Tensor,
        t: i64,
        sample: &Tensor,
    ) -> Result<(Tensor, Tensor)> {
        check_same_shape(model_output, sample)?;
        let a_t = self.schedule.alpha_bar(t)?;
        let a_prev = self.schedule.alpha_bar(self.prev_timestep(t))?;
        let x0 = self.pred_original(model_output, sample, a_t);
        let c_sample = ((1.0 - a_prev) / (1.0 - a_t)).sqrt();
        let c_x0 = a_prev.sqrt() - a_t.sqrt() * c_sample;
        Ok((sample * c_sample + &x0 * c_x0, x0))
    }

    /// One DPM-Solver step from timestep `t` (`t_back`: the previous, larger
    /// timestep; `old_x0`: its predicted x0). `noise(shape)` draws standard normal
    /// noise: once per step, twice on second-order steps (diffusers' draw order).
    pub fn step_dpm(
        &self,
        model_output: &Tensor,
        old_x0: Option<&Tensor>,
        t: i64,
        t_back: Option<i64>,
        sample: &Tensor,
        noise: &mut dyn FnMut(&[i64]) -> Tensor,
    ) -> Result<(Tensor, Tensor)> {
        check_same_shape(model_output, sample)?;
        let prev_t = self.prev_timestep(t);
        let a_t = self.schedule.alpha_bar(t)?;
        let a_prev = self.schedule.alpha_bar(prev_t)?;
        let x0 = self.pred_original(model_output, sample, a_t);
        let lambda = |a: f64| (a / (1.0 - a)).sqrt().ln();
        let h = lambda(a_prev) - lambda(a_t);
        let mult1 = ((1.0 - a_prev) / (1.0 - a_t)).sqrt() * (-h).exp();
        let mult2 = (-2.0 * h).exp_m1() * a_prev.sqrt();
        let mult_noise = (1.0 - a_prev).sqrt() * (1.0 - (-2.0 * h).exp()).sqrt();
        let shape = sample.size();
        let first_noise = noise(&shape);
        let first = sample * mult1 - &x0 * mult2 + first_noise * mult_noise;
        let (Some(old_x0), Some(t_back)) = (old_x0, t_back) else {
            return Ok((first, x0));
        };
        if prev_t < 0 {
            return Ok((first, x0));
        }
        let r = (lambda(a_t) - lambda(self.schedule.alpha_bar(t_back)?)) / h;
        let mult3 = 1.0 + 1.0 / (2.0 * r);
        let mult4 = 1.0 / (2.0 * r);
        let denoised = &x0 * mult3 - old_x0 * mult4;
        let second_noise = noise(&shape);
        Ok((
            sample * mult1 - denoised * mult2 + second_noise * mult_noise,
            x0,
        ))
    }

    /// Steps the chain once with the next inference timestep (as the CogVideoX
    /// pipelines do), returning the previous sample.
    pub fn step(
        &mut self,
        model_output: &Tensor,
        sample: &Tensor,
        noise: &mut dyn FnMut(&[i64]) -> Tensor,
    ) -> Result<Tensor> {
        let i = self.step_index;
        let t = *self.timesteps.get(i).ok_or_else(|| {
            WorldModelError::input(
                "step",
                format!(
                    "step {i} beyond the {} inference timesteps (call set_timesteps first)",
                    self.timesteps.len()
                ),
            )
        })?;
        let prev = match self.kind {
            SamplerKind::Ddim => self.step_ddim(model_output, t, sample)?.0,
            SamplerKind::Dpm => {
                let t_back = (i > 0).then(|| self.timesteps[i - 1]);
                let (prev, x0) = self.step_dpm(
                    model_output,
                    self.old_pred_original.as_ref(),
                    t,
                    t_back,
                    sample,
                    noise,
                )?;
                self.old_pred_original = Some(x0);
                prev
            }
        };
        self.step_index += 1;
        Ok(prev)
    }

    /// Alpha-bar of each batch item's timestep (`timesteps` `[B]`), shaped
    /// `[B, 1, ..., 1]` to broadcast over `like`, in `like`'s dtype and device.
    pub fn alpha_bar_like(&self, timesteps: &Tensor, like: &Tensor) -> Result<Tensor> {
        self.per_sample(timesteps, like)
    }

    fn per_sample(&self, timesteps: &Tensor, like: &Tensor) -> Result<Tensor> {
        let ts: Vec<i64> =
            Vec::<i64>::try_from(timesteps.to_kind(tch::Kind::Int64).flatten(0, -1))?;
        let values = ts
            .iter()
            .map(|&t| {
                if t < 0 {
                    Err(WorldModelError::input(
                        "timesteps",
                        format!("{t} is negative"),
                    ))
                } else {
                    self.schedule.alpha_bar(t)
                }
            })
            .collect::<Result<Vec<f64>>>()?;
        let mut shape = vec![values.len() as i64];
        shape.extend(std::iter::repeat_n(1, like.dim().saturating_sub(1)));
        // [B] -> [B, 1, ..., 1] broadcasting over the sample dims
        Ok(Tensor::from_slice(&values)
            .to_kind(like.kind())
            .to_device(like.device())
            .reshape(shape.as_slice()))
    }

    /// Forward diffusion: `sqrt(a_t) x0 + sqrt(1 - a_t) noise`, one timestep per batch item.
    pub fn add_noise(
        &self,
        original: &Tensor,
        noise: &Tensor,
        timesteps: &Tensor,
    ) -> Result<Tensor> {
        check_same_shape(noise, original)?;
        // diffusers casts alpha-bar to the sample dtype before the square roots.
        let a = self.per_sample(timesteps, original)?;
        Ok(a.sqrt() * original + (-&a + 1.0).sqrt() * noise)
    }

    /// The v-prediction target: `sqrt(a_t) noise - sqrt(1 - a_t) x0`.
    pub fn velocity(&self, sample: &Tensor, noise: &Tensor, timesteps: &Tensor) -> Result<Tensor> {
        check_same_shape(noise, sample)?;
        let a = self.per_sample(timesteps, sample)?;
        Ok(a.sqrt() * noise - (-&a + 1.0).sqrt() * sample)
    }
}

fn check_same_shape(a: &Tensor, b: &Tensor) -> Result<()> {
    if a.size() != b.size() {
        return Err(WorldModelError::input(
            "model_output",
            format!(
                "shape {:?} differs from the sample's {:?}",
                a.size(),
                b.size()
            ),
        ));
    }
    Ok(())
}
