//! `evaluate_policies`: policy evaluation by world-model rollouts
//! (`bridgev2w eval-policy-rollout`'s library call) with Python callables as
//! policies beside the scripted and served ones. The rollout runs with the
//! GIL released; each policy query takes it to call the callable.

use super::*;
use bridgev2w_data::synth::{Split, Task};
use bridgev2w_plan::error::PlanError;
use bridgev2w_plan::experiment::rollout::{RolloutOptions, ServedSpec};
use bridgev2w_plan::experiment::{rollout_report_with, ModelOptions};
use bridgev2w_plan::policy::Policy;
use bridgev2w_plan::{EeAction, Observation};
use pyo3::types::PyBytes;

/// A Python callable as a policy. It is called as `call(image_bytes,
/// height, width, joints, ee, step)` (the package's wrapper turns these
/// into numpy arrays and checks what the user's function returns) and
/// returns a list of `[x, y, z, roll, pitch, yaw, gripper]` rows.
struct PyPolicy {
    name: String,
    call: Py<PyAny>,
    step: usize,
}

impl std::fmt::Debug for PyPolicy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PyPolicy")
            .field("name", &self.name)
            .finish()
    }
}

/// A Python exception with its traceback, as text.
fn with_traceback(py: Python<'_>, e: &PyErr) -> String {
    let tb = e
        .traceback(py)
        .and_then(|t| t.format().ok())
        .unwrap_or_default();
    format!("{tb}{e}")
}

impl Policy for PyPolicy {
    fn name(&self) -> String {
        self.name.clone()
    }

    fn reset(&mut self, _trial: usize) {
        self.step = 0;
    }

    fn act(&mut self, obs: &Observation) -> bridgev2w_plan::error::Result<Vec<EeAction>> {
        let step = self.step;
        self.step += 1;
        let fail = |message: String| PlanError::Policy {
            policy: self.name.clone(),
            step: Some(step),
            message,
        };
        let rgb: Vec<u8> = obs.image.rgb.iter().map(|&v| u8_from_unit(v)).collect();
        let rows: Vec<Vec<f64>> = Python::attach(|py| {
            let args = (
                PyBytes::new(py, &rgb),
                obs.image.height,
                obs.image.width,
                obs.joints.clone(),
                obs.ee.to_vec(),
                step,
            );
            let out = self
                .call
                .call1(py, args)
                .map_err(|e| fail(with_traceback(py, &e)))?;
            out.extract(py)
                .map_err(|e| fail(format!("the returned actions: {e}")))
        })?;
        rows.iter()
            .enumerate()
            .map(|(i, r)| {
                <[f64; 7]>::try_from(r.as_slice()).map_err(|_| {
                    fail(format!(
                        "row {i} has {} values, expected 7 ([x, y, z, roll, pitch, yaw, gripper])",
                        r.len()
                    ))
                })
            })
            .collect()
    }
}

/// Evaluates `policies` (`(name, wrapped callable)` pairs), the scripted
/// policies of `offsets_mm` and the `served` ones (`[NAME=]ws://HOST:PORT`)
/// by rollouts in `model` (`perfect`, `random` or a model folder with
/// `weights`) and in the synthetic world; returns a dict: `policies`,
/// `predicted`, `real`, `mmrv`, `pearson`, `progress` (mean goal progress
/// per policy, or None), `failed` (`(name, error)` pairs), `overestimate`
/// (world-model minus synthetic-world success per policy), `calibration`
/// (the calibrated judge's `{floor, ratio, episodes, quantile,
/// expert_ratios}`, or None), `markdown`.
#[pyfunction]
#[pyo3(signature = (policies, task, trials, model, weights, offsets_mm, served, served_config, episode_frames, chunk, ratio, calibrate_judge, calibration_quantile, split, seed))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn evaluate_policies<'py>(
    py: Python<'py>,
    policies: Vec<(String, Py<PyAny>)>,
    task: &str,
    trials: usize,
    model: &str,
    weights: Option<PathBuf>,
    offsets_mm: Vec<f64>,
    served: Vec<String>,
    served_config: Option<PathBuf>,
    episode_frames: usize,
    chunk: usize,
    ratio: f64,
    calibrate_judge: usize,
    calibration_quantile: f64,
    split: &str,
    seed: u64,
) -> PyResult<Bound<'py, PyDict>> {
    let value = |field: &str, e: String| PyValueError::new_err(format!("{field}: {e}"));
    let task = Task::parse(task)
        .filter(|t| Task::ALL.contains(t))
        .ok_or_else(|| {
            value(
                "task",
                format!("{task:?}, expected reach, push or pick_place"),
            )
        })?;
    let split = Split::parse(split).ok_or_else(|| {
        value(
            "split",
            format!("{split:?}, expected train, test, unseen_camera or unseen_scene"),
        )
    })?;
    let served = served
        .iter()
        .map(|s| s.parse::<ServedSpec>())
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| value("served", e))?;
    if let Some(p) = served_config.as_ref().filter(|p| !p.is_file()) {
        return Err(PyFileNotFoundError::new_err(format!(
            "{}: no such file (served_config)",
            p.display()
        )));
    }
    let o = RolloutOptions {
        trials,
        model: ModelOptions {
            model: model
                .parse()
                .map_err(|e: PlanError| PyValueError::new_err(e.to_string()))?,
            weights,
            ..ModelOptions::default()
        },
        offsets_mm,
        served,
        served_config,
        episode_frames,
        chunk,
        ratio,
        calibrate_judge,
        calibration_quantile,
        split,
        seed,
        ..RolloutOptions::new(task)
    };
    let callables: Vec<PyPolicy> = policies
        .into_iter()
        .map(|(name, call)| PyPolicy {
            name,
            call,
            step: 0,
        })
        .collect();
    let report = py
        .detach(|| {
            let external = callables
                .into_iter()
                .map(|p| Box::new(p) as Box<dyn Policy>)
                .collect();
            no_panic("evaluate_policies", || {
                Ok(rollout_report_with(&o, external, &mut |line| {
                    eprintln!("{line}")
                }))
            })
        })?
        .map_err(|e| match e {
            PlanError::Input { .. } => PyValueError::new_err(e.to_string()),
            e => err(e),
        })?;
    let d = PyDict::new(py);
    d.set_item("policies", report.policies.clone())?;
    d.set_item("predicted", report.predicted.clone())?;
    d.set_item("real", report.real.clone())?;
    d.set_item("mmrv", report.mmrv)?;
    d.set_item("pearson", report.pearson)?;
    d.set_item("progress", report.progress.as_ref().map(|p| p.mean.clone()))?;
    d.set_item("failed", report.failed.clone())?;
    d.set_item("overestimate", report.overestimate())?;
    let calibration = report.calibration.as_ref().map(|c| {
        let c_dict = PyDict::new(py);
        c_dict.set_item("floor", c.floor)?;
        c_dict.set_item("ratio", c.ratio)?;
        c_dict.set_item("episodes", c.episodes)?;
        c_dict.set_item("quantile", c.quantile)?;
        c_dict.set_item("expert_ratios", c.expert_ratios.clone())?;
        Ok::<_, PyErr>(c_dict)
    });
    d.set_item("calibration", calibration.transpose()?)?;
    d.set_item("markdown", report.markdown())?;
    Ok(d)
}
