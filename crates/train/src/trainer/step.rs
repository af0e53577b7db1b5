//! The training step (one optimizer update) and the training loop with its metrics
//! file and checkpoint schedule.

use super::checkpoint_io::{save_named, write_atomic};
use super::{check_finite, io_err, StepMetrics, Trainer};
use crate::config::Stage;
use crate::data::Batch;
use crate::run_dir::{self, ExistingRun};
use crate::tensorboard::SummaryValue;
use crate::{Result, TrainError};
use bridgev2w_torch_ext::{autocast, cuda_memory};
use std::io::Write;
use std::path::Path;
use std::time::Instant;

impl Trainer {
    /// One optimizer step on the next batch; the NaN/inf guard runs before
    /// any parameter changes.
    pub fn train_step(&mut self) -> Result<StepMetrics> {
        let step = self.step;
        let batch = self.batch(step)?;
        self.update(&batch, step)
    }

    /// One optimizer update on `batch` with the random draws (and learning
    /// rate, epoch) of step `step`; counts as a completed step. Tests use it
    /// to overfit one fixed batch. An error of libtorch's (its ops panic on
    /// them) is returned, and an out-of-memory reported with what the step
    /// ran ([`TrainError::OutOfMemory`]).
    pub fn update(&mut self, batch: &Batch, step: usize) -> Result<StepMetrics> {
        crate::guarded(|| self.update_unguarded(batch, step)).map_err(|e| {
            e.on_out_of_memory(
                || self.describe_step(batch, step),
                crate::TRAIN_MEMORY_ADVICE,
            )
        })
    }

    /// What step `step` on `batch` runs, for error messages.
    fn describe_step(&self, batch: &Batch, step: usize) -> String {
        let t = &self.cfg.train;
        let s = batch.video.size(); // [B, 3, T, H, W]
        let (clips, frames, height, width) = match s.as_slice() {
            [b, _, f, h, w] => (*b, *f, *h, *w),
            _ => (0, 0, 0, 0),
        };
        let precision = match self.autocast {
            Some(d) => format!("{d:?} autocast"),
            None => "f32".to_owned(),
        };
        let flow = if self.flow_weight_at(step) > 0.0 {
            format!(
                "on ({} backward through the VAE)",
                crate::decoded_flow::FlowBackward::for_training(t.gradient_checkpointing)
            )
        } else {
            "off".to_owned()
        };
        format!(
            "training step {step} ({clips} clip(s) of {frames} frames at {height}x{width}, {precision} on {:?}, gradient checkpointing {}, flow loss {flow})",
            self.model.device(),
            if t.gradient_checkpointing { "on" } else { "off" },
        )
    }

    /// [`Self::update`] without its panic guard.
    fn update_unguarded(&mut self, batch: &Batch, step: usize) -> Result<StepMetrics> {
        let start = Instant::now();
        self.opt.zero_grad();
        let device = self.model.device();
        let cuda = match device {
            tch::Device::Cuda(i) => Some(i),
            _ => None,
        };
        // The allocator's peaks are figures for the metrics only: a failure
        // to read them leaves them out, never stops training.
        if let Some(i) = cuda {
            let _ = cuda_memory::reset_peak(i);
        }
        // The forward passes under autocast; the backward outside it (as
        // PyTorch recommends), except the checkpointed blocks' replay, which
        // must recompute them in the forward's precision.
        let l = autocast(device, self.autocast, || self.losses(batch, step))??;
        let loss = l.total.double_value(&[]);
        check_finite(step, "total", loss)?;
        l.total.backward();
        if let Some(record) = l.checkpointed {
            let model = &self.model.transformer.model;
            autocast(device, self.autocast, || record.backward(model))??;
        }
        let mut scalars = [loss, l.diffusion, l.dynamics, l.flow, l.recon, l.kl];
        self.average_gradients(&mut scalars)?;
        let [loss, diffusion, dynamics, flow, recon, kl] = scalars;
        check_finite(step, "total (all ranks)", loss)?;
        let grad_norm = self.opt.clip_grad_norm(self.cfg.train.grad_clip);
        check_finite(step, "gradient norm", grad_norm)?;
        let lr = self.cfg.lr_at(step);
        self.opt.step(lr);
        if let Some(ema) = &mut self.ema {
            ema.update(self.opt.params(), step);
        }
        self.step += 1;
        let cuda_peak = cuda.and_then(|i| cuda_memory::memory(i).ok().flatten());
        let mib = |bytes: u64| bytes as f64 / (1 << 20) as f64;
        Ok(StepMetrics {
            step,
            epoch: step / self.steps_per_epoch(),
            loss,
            diffusion,
            dynamics,
            flow,
            flow_weight: l.flow_weight,
            lr,
            grad_norm,
            dropped: l.dropped,
            secs: start.elapsed().as_secs_f64(),
            recon,
            kl,
            cuda_peak_allocated_mib: cuda_peak.map(|m| mib(m.peak_allocated)),
            cuda_peak_reserved_mib: cuda_peak.map(|m| mib(m.peak_reserved)),
        })
    }

    /// Lets [`Self::run`] replace a run that `train.out` already holds (its
    /// config, metrics, checkpoints and final weights; other files stay).
    /// Without it (and without [`Self::resume`]) such a folder is refused.
    pub fn overwrite_existing_run(&mut self) {
        if self.existing_run == ExistingRun::Refuse {
            self.existing_run = ExistingRun::Overwrite;
        }
    }

    /// Trains to [`Self::total_steps`], appending to `OUT/metrics.jsonl` and
    /// to a TensorBoard event file in `OUT/tensorboard/` (every metric as a
    /// scalar; at each checkpoint a [`Self::preview`] image),
    /// checkpointing every `checkpoint_every` steps and at the end
    /// (`OUT/checkpoints/step-NNNNNNNN`, `OUT/checkpoints/latest`), and
    /// writing `OUT/final/weights.safetensors`. `on_step` sees every step's metrics.
    /// A non-finite loss or gradient stops the run with an error naming the
    /// step and the term; the checkpoints written before stay as they were.
    /// The run holds `OUT`'s lock throughout ([`run_dir::claim`]): a second
    /// trainer into `OUT` is refused, naming this one's process.
    pub fn run(&mut self, on_step: &mut dyn FnMut(&StepMetrics)) -> Result<Vec<StepMetrics>> {
        if !self.is_primary() {
            // Other ranks: the same steps (their all-reduce is rank 0's), no files.
            let total = self.total_steps();
            let mut all = Vec::new();
            while self.step < total {
                let m = self.train_step()?;
                on_step(&m);
                all.push(m);
            }
            return Ok(all);
        }
        let out = self.cfg.train.out.clone();
        // Held to the end of the run: another trainer into `out` stops.
        let _lock = run_dir::claim(&out, &self.cfg, self.existing_run)?;
        // From here on the folder is this run's own.
        self.existing_run = ExistingRun::Continue;
        std::fs::create_dir_all(&out).map_err(|e| io_err(&out, e))?;
        let cfg_text = self.cfg.to_toml()?;
        write_atomic(&out.join("config.toml"), cfg_text.as_bytes())?;
        let metrics_path = out.join("metrics.jsonl");
        truncate_metrics(&metrics_path, self.step)?;
        let mut metrics_file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&metrics_path)
            .map_err(|e| io_err(&metrics_path, e))?;
        let mut events = crate::tensorboard::EventWriter::create(&out.join("tensorboard"))?;
        let total = self.total_steps();
        let every = self.cfg.train.checkpoint_every;
        let mut all = Vec::new();
        while self.step < total {
            let m = self.train_step()?;
            let line = serde_json::to_string(&m)
                .map_err(|e| TrainError::input("metrics", e.to_string()))?;
            writeln!(metrics_file, "{line}").map_err(|e| io_err(&metrics_path, e))?;
            events.write(m.step, &scalars(&m)?)?;
            on_step(&m);
            all.push(m);
            if (every > 0 && self.step % every == 0) || self.step == total {
                self.save_checkpoint()?;
                if let Some((width, height, pixels)) = self.preview()? {
                    let png = bridgev2w_io::png::encode_rgb8(width, height, &pixels);
                    events.write(
                        self.step,
                        &[(
                            "preview/truth_over_prediction".into(),
                            SummaryValue::Png { width, height, png },
                        )],
                    )?;
                }
            }
        }
        // The final weights (and backbone) are the averages, if any; the
        // last checkpoint keeps the raw parameters.
        self.use_averaged_weights();
        let fin = out.join("final");
        std::fs::create_dir_all(&fin).map_err(|e| io_err(&fin, e))?;
        self.model.save_weights(&fin.join("weights.safetensors"))?;
        if self.cfg.train.stage != Stage::Bridgev2w {
            self.save_trained_backbone(&fin.join("backbone"))?;
        }
        if let Some(vs) = &self.action_vs {
            save_named(
                vs.variables().into_iter().collect(),
                &fin.join("action_encoder.safetensors"),
            )?;
        }
        Ok(all)
    }
}

/// Every number of a step's metrics as a `train/<name>` scalar (booleans as
/// 0 or 1), the step itself aside.
fn scalars(m: &StepMetrics) -> Result<Vec<(String, SummaryValue)>> {
    let v = serde_json::to_value(m).map_err(|e| TrainError::input("metrics", e.to_string()))?;
    let mut out = Vec::new();
    if let Some(o) = v.as_object() {
        for (k, x) in o {
            let value = match x {
                serde_json::Value::Number(n) => n.as_f64(),
                serde_json::Value::Bool(b) => Some(f64::from(u8::from(*b))),
                _ => None,
            };
            if let (Some(value), true) = (value, k != "step") {
                out.push((format!("train/{k}"), SummaryValue::Scalar(value)));
            }
        }
    }
    Ok(out)
}

/// Keeps the metrics lines of steps before `step` (a resumed run rewrites the rest).
fn truncate_metrics(path: &Path, step: usize) -> Result<()> {
    if !path.is_file() {
        return Ok(());
    }
    let text = std::fs::read_to_string(path).map_err(|e| io_err(path, e))?;
    let kept: String = text
        .lines()
        .filter(|l| {
            serde_json::from_str::<serde_json::Value>(l)
                .ok()
                .and_then(|v| v["step"].as_u64())
                .is_some_and(|s| (s as usize) < step)
        })
        .map(|l| format!("{l}\n"))
        .collect();
    write_atomic(path, kept.as_bytes())
}
