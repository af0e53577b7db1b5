//! Scheduler configs that would give NaN latents after the denoising loop
//! are refused when read, naming the file, the field and the value
//! (issue 69, item 4).

#![allow(clippy::unwrap_used)]

use super::*;

/// `scheduler_config.json` in a temporary folder: CogVideoX-5B-I2V's
/// fields with `patch` merged over them.
fn write_config(patch: serde_json::Value) -> (tempfile::TempDir, std::path::PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("scheduler_config.json");
    let mut v = serde_json::to_value(SchedulerConfig::cogvideox_5b_i2v()).unwrap();
    for (k, x) in patch.as_object().unwrap() {
        v[k] = x.clone();
    }
    std::fs::write(&path, v.to_string()).unwrap();
    (dir, path)
}

fn load_error(patch: serde_json::Value) -> (String, std::path::PathBuf) {
    let (_dir, path) = write_config(patch);
    let e = SchedulerConfig::load(&path).unwrap_err().to_string();
    (e, path)
}

#[test]
fn a_config_as_written_loads() {
    let (_dir, path) = write_config(serde_json::json!({}));
    let cfg = SchedulerConfig::load(&path).unwrap();
    assert_eq!(cfg, SchedulerConfig::cogvideox_5b_i2v());
}

#[test]
fn too_many_training_timesteps_are_refused_before_the_schedule_is_built() {
    // 10^12 timesteps would allocate 8 TB for alpha-bar.
    let (e, path) = load_error(serde_json::json!({"num_train_timesteps": 1_000_000_000_000u64}));
    assert!(
        e.contains(&path.display().to_string())
            && e.contains("num_train_timesteps")
            && e.contains("1000000000000")
            && e.contains("1..=100000"),
        "{e}"
    );
    let (e, _) = load_error(serde_json::json!({"num_train_timesteps": 0}));
    assert!(e.contains("num_train_timesteps") && e.contains("0:"), "{e}");
    let mut ok = SchedulerConfig::cogvideox_5b_i2v();
    ok.num_train_timesteps = MAX_TRAIN_TIMESTEPS;
    assert!(Scheduler::new(ok).is_ok());
}

#[test]
fn betas_outside_zero_one_or_not_finite_are_named() {
    // JSON has no NaN: a config built in code (the Python package, tests).
    for (field, v) in [
        ("beta_end", f64::NAN),
        ("beta_end", f64::INFINITY),
        ("beta_end", 1.5),
        ("beta_start", -0.1),
        ("beta_start", 0.0),
    ] {
        let mut cfg = SchedulerConfig::cogvideox_5b_i2v();
        match field {
            "beta_end" => cfg.beta_end = v,
            _ => cfg.beta_start = v,
        }
        let e = Scheduler::new(cfg).unwrap_err().to_string();
        assert!(
            e.contains(&format!("`{field}`"))
                && e.contains(&format!("{v}:"))
                && e.contains("(0, 1)"),
            "{field} = {v}: {e}"
        );
    }
    let (e, path) = load_error(serde_json::json!({"beta_end": 2.0}));
    assert!(
        e.contains(&path.display().to_string()) && e.contains("beta_end") && e.contains("2:"),
        "{e}"
    );
    let mut cfg = SchedulerConfig::cogvideox_5b_i2v();
    cfg.num_train_timesteps = 3;
    cfg.trained_betas = Some(vec![0.1, f64::NAN, 0.2]);
    let e = Scheduler::new(cfg).unwrap_err().to_string();
    assert!(
        e.contains("trained_betas") && e.contains("value 1 is NaN"),
        "{e}"
    );
}

#[test]
fn a_schedule_the_samplers_cannot_step_is_refused_naming_its_fields() {
    // A beta that rounds to 0 in float32: alpha-bar 1 at timestep 0, where
    // DDIM divides by 1 - alpha-bar.
    let mut cfg = SchedulerConfig::cogvideox_5b_i2v();
    cfg.beta_schedule = BetaSchedule::Linear;
    cfg.rescale_betas_zero_snr = false;
    cfg.beta_start = 1e-12;
    let e = Scheduler::new(cfg).unwrap_err().to_string();
    assert!(
        e.contains("beta_start/beta_end") && e.contains("timestep 0") && e.contains("is 1"),
        "{e}"
    );
    // Betas near 1 over many timesteps: alpha-bar underflows to 0.
    let mut cfg = SchedulerConfig::cogvideox_5b_i2v();
    cfg.rescale_betas_zero_snr = false;
    cfg.beta_end = 0.999;
    cfg.num_train_timesteps = 100_000;
    let e = Scheduler::new(cfg).unwrap_err().to_string();
    assert!(
        e.contains("beta_start/beta_end") && e.contains("underflows to 0"),
        "{e}"
    );
    // One timestep: zero-SNR rescaling divides by first - last = 0.
    let mut cfg = SchedulerConfig::cogvideox_5b_i2v();
    cfg.num_train_timesteps = 1;
    let e = Scheduler::new(cfg).unwrap_err().to_string();
    assert!(
        e.contains("rescale_betas_zero_snr") && e.contains("is NaN"),
        "{e}"
    );
    for s in [0.0, -1.0, f64::NAN, f64::INFINITY] {
        let mut cfg = SchedulerConfig::cogvideox_5b_i2v();
        cfg.snr_shift_scale = s;
        let e = Scheduler::new(cfg).unwrap_err().to_string();
        assert!(
            e.contains("snr_shift_scale") && e.contains("> 0"),
            "{s}: {e}"
        );
    }
}

#[test]
fn steps_offset_and_epsilon_at_zero_snr_are_refused_before_the_first_step() {
    let (e, _) = load_error(serde_json::json!({"steps_offset": -1}));
    assert!(e.contains("steps_offset") && e.contains("-1:"), "{e}");
    // Leading spacing: an offset that pushes the first timestep past the last.
    let mut cfg = SchedulerConfig::cogvideox_5b_i2v();
    cfg.timestep_spacing = TimestepSpacing::Leading;
    cfg.steps_offset = 300;
    let mut s = Scheduler::new(cfg).unwrap();
    assert_eq!(s.set_timesteps(1).unwrap(), [300]);
    let e = s.set_timesteps(4).unwrap_err().to_string();
    assert!(
        e.contains("steps_offset") && e.contains("1050") && e.contains("0..=249"),
        "{e}"
    );
    // Epsilon with a zero terminal SNR: trailing spacing starts at it.
    let mut cfg = SchedulerConfig::cogvideox_5b_i2v();
    cfg.prediction_type = PredictionType::Epsilon;
    let e = Scheduler::new(cfg.clone())
        .unwrap()
        .set_timesteps(10)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("prediction_type") && e.contains("rescale_betas_zero_snr") && e.contains("999"),
        "{e}"
    );
    cfg.rescale_betas_zero_snr = false;
    assert!(Scheduler::new(cfg).unwrap().set_timesteps(10).is_ok());
}

#[test]
fn an_unknown_enum_value_names_its_field() {
    for (field, value) in [
        ("timestep_spacing", "uniform"),
        ("beta_schedule", "cosine"),
        ("prediction_type", "x0"),
    ] {
        let (e, path) = load_error(serde_json::json!({ field: value }));
        assert!(
            e.contains(&path.display().to_string()) && e.contains(field) && e.contains(value),
            "{e}"
        );
    }
}
