//! The schedulers' arm of the parity fixtures (`kind: "scheduler"`).

use super::FixtureIo;
use crate::error::{Result, WorldModelError};
use crate::scheduler::{Scheduler, SchedulerConfig};
use std::path::Path;
use tch::Tensor;

/// Parity fixture arm (`kind: "scheduler"`): runs the deterministic chain of the
/// fixture and returns `timesteps`, `prev_sample_step_K` for every step, `noisy` and
/// `velocity`.
pub(super) fn fixture_outputs(model_dir: &Path, io: &FixtureIo) -> Result<Vec<(String, Tensor)>> {
    let cfg = SchedulerConfig::load(&model_dir.join("scheduler_config.json"))?;
    let mut sched = Scheduler::new(cfg)?;
    let steps = io.get("num_inference_steps")?.int64_value(&[]);
    if steps <= 0 {
        return Err(WorldModelError::input(
            "num_inference_steps",
            format!("{steps}: expected a positive count"),
        ));
    }
    let timesteps = sched.set_timesteps(steps as usize)?.to_vec();
    let mut out = vec![("timesteps".to_owned(), Tensor::from_slice(&timesteps))];
    let model_outputs = io.get("model_output")?;
    let mut sample = io.get("sample")?.shallow_clone();
    for k in 0..timesteps.len() {
        let mut draw = 0;
        let mut missing = None;
        let mut noise = |shape: &[i64]| -> Tensor {
            let name = format!("noise_step_{k}_{draw}");
            draw += 1;
            io.get(&name)
                .map(|t| t.shallow_clone())
                .unwrap_or_else(|e| {
                    missing = Some(e);
                    Tensor::full(shape, f64::NAN, (tch::Kind::Float, tch::Device::Cpu))
                })
        };
        sample = sched.step(&model_outputs.get(k as i64), &sample, &mut noise)?;
        if let Some(e) = missing {
            return Err(e);
        }
        out.push((format!("prev_sample_step_{k}"), sample.shallow_clone()));
    }
    if io.contains("add_noise_timesteps") {
        let original = io.get("original")?;
        let noise = io.get("noise")?;
        let ts = io.get("add_noise_timesteps")?;
        out.push(("noisy".to_owned(), sched.add_noise(original, noise, ts)?));
        out.push(("velocity".to_owned(), sched.velocity(original, noise, ts)?));
    }
    Ok(out)
}
