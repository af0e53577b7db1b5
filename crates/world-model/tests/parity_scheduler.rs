//! CogVideoX DDIM / DPM schedulers against diffusers, plus closed-form checks.

#![allow(clippy::unwrap_used)]

use crate::common;

use bridgev2w_world_model::parity::{run_fixture, DEFAULT_TOLERANCE};
use bridgev2w_world_model::scheduler::{
    inference_timesteps, NoiseSchedule, Scheduler, SchedulerConfig, TimestepSpacing,
};
use tch::{Kind, Tensor};

fn check(name: &str, args: &[&str]) {
    let dir = common::fixture(name, args);
    let report = run_fixture(&dir).unwrap();
    assert!(report.outputs.len() > 3, "{name}: too few outputs compared");
    for o in &report.outputs {
        assert!(
            o.max_rel <= DEFAULT_TOLERANCE,
            "{name}: {} max rel err {:e} (abs {:e})",
            o.name,
            o.max_rel,
            o.max_abs
        );
    }
}

#[test]
fn ddim_5b_i2v_trailing_vpred_zero_snr() {
    check(
        "sched-ddim-5b",
        &[
            "scheduler",
            "--sampler",
            "ddim",
            "--steps",
            "8",
            "--shape",
            "2,4,3,6,8",
        ],
    );
}

#[test]
fn dpm_5b_i2v_second_order_with_noise() {
    check(
        "sched-dpm-5b",
        &[
            "scheduler",
            "--sampler",
            "dpm",
            "--steps",
            "9",
            "--shape",
            "1,4,3,6,8",
        ],
    );
}

#[test]
fn ddim_and_dpm_2b_snr_shift() {
    for s in ["ddim", "dpm"] {
        check(
            &format!("sched-{s}-2b"),
            &[
                "scheduler",
                "--sampler",
                s,
                "--preset",
                "cogvideox-2b",
                "--steps",
                "7",
            ],
        );
    }
}

#[test]
fn leading_linspace_linear_cosine_epsilon_variants() {
    let variants = [
        r#"{"timestep_spacing":"leading","steps_offset":1}"#,
        r#"{"timestep_spacing":"linspace","beta_schedule":"linear","prediction_type":"epsilon","rescale_betas_zero_snr":false}"#,
        r#"{"beta_schedule":"squaredcos_cap_v2","set_alpha_to_one":false,"rescale_betas_zero_snr":false,"prediction_type":"sample"}"#,
    ];
    for (i, cfg) in variants.iter().enumerate() {
        for s in ["ddim", "dpm"] {
            check(
                &format!("sched-variant{i}-{s}"),
                &[
                    "scheduler",
                    "--sampler",
                    s,
                    "--steps",
                    "7",
                    "--shape",
                    "2,3,2,4,4",
                    "--config-json",
                    cfg,
                ],
            );
        }
    }
}

#[test]
fn trailing_timesteps_closed_form() {
    let cfg = SchedulerConfig::cogvideox_5b_i2v();
    let ts = inference_timesteps(&cfg, 50).unwrap();
    assert_eq!(ts.len(), 50);
    assert_eq!(ts[0], 999);
    assert_eq!(ts[1], 979);
    assert_eq!(ts[49], 19);
    assert!(inference_timesteps(&cfg, 0).is_err());
    assert!(inference_timesteps(&cfg, 1001).is_err());
    let mut lead = cfg.clone();
    lead.timestep_spacing = TimestepSpacing::Leading;
    assert_eq!(
        inference_timesteps(&lead, 4).unwrap(),
        vec![750, 500, 250, 0]
    );
}

#[test]
fn zero_terminal_snr_schedule() {
    let s = NoiseSchedule::new(&SchedulerConfig::cogvideox_5b_i2v());
    assert_eq!(s.alphas_cumprod.len(), 1000);
    assert!(
        s.alphas_cumprod[999].abs() < 1e-12,
        "terminal alpha-bar must be 0"
    );
    // Rescaling keeps the first alpha-bar: 1 - beta_0 with beta_0 = 0.00085.
    assert!((s.alphas_cumprod[0] - (1.0 - 0.00085)).abs() < 1e-9);
    assert!(s.alphas_cumprod.windows(2).all(|w| w[1] < w[0]));
    assert!(s.alpha_bar(1000).is_err());
    assert_eq!(s.alpha_bar(-1).unwrap(), 1.0);
}

#[test]
fn velocity_recovers_clean_sample() {
    // x_t = sqrt(a) x0 + sqrt(1-a) n, v = sqrt(a) n - sqrt(1-a) x0  =>  x0 = sqrt(a) x_t - sqrt(1-a) v
    let sched = Scheduler::new(SchedulerConfig::cogvideox_2b()).unwrap();
    let x0 = Tensor::randn([3, 4, 2, 5, 5], (Kind::Float, tch::Device::Cpu));
    let n = Tensor::randn([3, 4, 2, 5, 5], (Kind::Float, tch::Device::Cpu));
    let t = Tensor::from_slice(&[10i64, 500, 998]);
    let xt = sched.add_noise(&x0, &n, &t).unwrap();
    let v = sched.velocity(&x0, &n, &t).unwrap();
    for (i, &ti) in [10i64, 500, 998].iter().enumerate() {
        let a = sched.schedule().alpha_bar(ti).unwrap();
        let rec = xt.get(i as i64) * a.sqrt() - v.get(i as i64) * (1.0 - a).sqrt();
        let err = (rec - x0.get(i as i64)).abs().max().double_value(&[]);
        assert!(err < 1e-5, "t={ti}: {err}");
    }
    let bad = Tensor::zeros([2, 4, 2, 5, 5], (Kind::Float, tch::Device::Cpu));
    assert!(sched.add_noise(&x0, &bad, &t).is_err());
}

#[test]
fn stepping_past_the_schedule_is_an_error() {
    let mut sched = Scheduler::new(SchedulerConfig::cogvideox_5b_i2v()).unwrap();
    sched.set_timesteps(2).unwrap();
    let x = Tensor::zeros([1, 2, 1, 2, 2], (Kind::Float, tch::Device::Cpu));
    let mut noise = |s: &[i64]| Tensor::zeros(s, (Kind::Float, tch::Device::Cpu));
    let _ = sched.step(&x, &x, &mut noise).unwrap();
    let _ = sched.step(&x, &x, &mut noise).unwrap();
    let err = sched.step(&x, &x, &mut noise).unwrap_err().to_string();
    assert!(err.contains("beyond the 2 inference timesteps"), "{err}");
}
