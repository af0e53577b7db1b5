//! The sampling loop against a perfect denoiser, guidance, strength,
//! progress, and divergence errors.

#![allow(clippy::unwrap_used)]

use super::*;
use crate::scheduler::{SamplerKind, SchedulerConfig};
use tch::Device;

/// A perfect v-predictor for a known clean sample x0: from x_t it recovers the
/// noise and returns sqrt(a) eps - sqrt(1 - a) x0. Unconditional calls predict
/// toward zero instead, so guidance is observable.
struct Oracle {
    x0: Tensor,
    alphas: Vec<f64>,
}

impl Denoiser for Oracle {
    fn velocity(
        &self,
        latent_in: &Tensor,
        timestep: &Tensor,
        guidance: Guidance,
    ) -> Result<Tensor> {
        let c = latent_in.size()[2] / 2;
        let xt = latent_in.narrow(2, 0, c);
        let a = self.alphas[timestep.int64_value(&[0]) as usize];
        let target = match guidance {
            Guidance::Conditional => self.x0.shallow_clone(),
            Guidance::Unconditional => self.x0.zeros_like(),
        };
        let eps = (&xt - &target * a.sqrt()) / (1.0 - a).sqrt().max(1e-12);
        Ok(eps * a.sqrt() - target * (1.0 - a).sqrt())
    }
}

fn run(kind: SamplerKind, guidance: f64) -> (Tensor, Tensor) {
    let mut cfg = SchedulerConfig::cogvideox_5b_i2v();
    cfg.rescale_betas_zero_snr = false; // keep 1 - a > 0 for the oracle's inversion
    let mut sched = Scheduler::new(cfg).unwrap().with_kind(kind);
    let alphas = sched.schedule().alphas_cumprod.clone();
    tch::manual_seed(3);
    let x0 = Tensor::randn([1, 3, 4, 2, 2], (Kind::Float, Device::Cpu));
    let oracle = Oracle {
        x0: x0.shallow_clone(),
        alphas,
    };
    let image = Tensor::zeros([1, 3, 4, 2, 2], (Kind::Float, Device::Cpu));
    let opts = SampleOptions {
        steps: 10,
        guidance_scale: guidance,
        dynamic_cfg: false,
        seed: 7,
        first_frame: FirstFrame::Generated,
        ..SampleOptions::default()
    };
    (
        sample_latents(&oracle, &mut sched, &image, &opts).unwrap(),
        x0,
    )
}

#[test]
fn ddim_and_dpm_with_a_perfect_denoiser_reach_the_clean_sample() {
    for kind in [SamplerKind::Ddim, SamplerKind::Dpm] {
        let (out, x0) = run(kind, 1.0);
        let err = (out - &x0).abs().max().double_value(&[]);
        assert!(err < 1e-3, "{kind:?}: {err}");
    }
}

#[test]
fn guidance_extrapolates_away_from_the_unconditional_prediction() {
    // cond -> x0, uncond -> 0: with scale g the result is g * x0 (velocity is linear
    // in the target and DDIM is linear in the velocity).
    let (out, x0) = run(SamplerKind::Ddim, 3.0);
    let err = (out - &x0 * 3.0).abs().max().double_value(&[]);
    assert!(err < 1e-2, "{err}");
}

#[test]
fn a_replaced_first_frame_ends_as_the_image_latent() {
    let mut cfg = SchedulerConfig::cogvideox_5b_i2v();
    cfg.rescale_betas_zero_snr = false; // keep 1 - a > 0 for the oracle's inversion
    let mut sched = Scheduler::new(cfg).unwrap().with_kind(SamplerKind::Ddim);
    let alphas = sched.schedule().alphas_cumprod.clone();
    tch::manual_seed(5);
    let x0 = Tensor::randn([1, 3, 4, 2, 2], (Kind::Float, Device::Cpu));
    let oracle = Oracle {
        x0: x0.shallow_clone(),
        alphas,
    };
    // The image latent in frame 0 differs from what the denoiser predicts.
    let image = Tensor::zeros([1, 3, 4, 2, 2], (Kind::Float, Device::Cpu));
    let _ = image.narrow(1, 0, 1).fill_(0.5);
    let opts = SampleOptions {
        steps: 10,
        guidance_scale: 1.0,
        first_frame: FirstFrame::Replaced,
        ..SampleOptions::default()
    };
    let out = sample_latents(&oracle, &mut sched, &image, &opts).unwrap();
    let first = (out.narrow(1, 0, 1) - 0.5).abs().max().double_value(&[]);
    assert_eq!(first, 0.0);
    let rest = (out.narrow(1, 1, 2) - x0.narrow(1, 1, 2))
        .abs()
        .max()
        .double_value(&[]);
    assert!(rest < 1e-3, "{rest}");
    assert_eq!(
        "replaced".parse::<FirstFrame>().unwrap(),
        FirstFrame::Replaced
    );
    let e = "both".parse::<FirstFrame>().unwrap_err().to_string();
    assert!(e.contains("generated, replaced"), "{e}");
}

/// Counts what a [`Progress`] is told.
#[derive(Default)]
struct Counter {
    starts: std::sync::Mutex<Vec<(usize, String)>>,
    ticks: std::sync::atomic::AtomicUsize,
    finishes: std::sync::atomic::AtomicUsize,
}

impl Progress for Counter {
    fn start(&self, total: usize, label: &str) {
        self.starts.lock().unwrap().push((total, label.to_owned()));
    }
    fn tick(&self) {
        self.ticks.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
    }
    fn finish(&self) {
        self.finishes
            .fetch_add(1, std::sync::atomic::Ordering::SeqCst);
    }
}

#[test]
fn progress_is_ticked_once_per_step() {
    use std::sync::atomic::Ordering::SeqCst;
    let mut cfg = SchedulerConfig::cogvideox_5b_i2v();
    cfg.rescale_betas_zero_snr = false;
    let alphas = Scheduler::new(cfg.clone())
        .unwrap()
        .schedule()
        .alphas_cumprod
        .clone();
    let oracle = Oracle {
        x0: Tensor::zeros([2, 3, 4, 2, 2], (Kind::Float, Device::Cpu)),
        alphas,
    };
    let image = Tensor::zeros([2, 3, 4, 2, 2], (Kind::Float, Device::Cpu));
    // Guidance (two denoiser calls per step) and a replaced first frame
    // (more noise per step) still tick once per step.
    for (steps, guidance, first_frame) in [
        (7, 1.0, FirstFrame::Generated),
        (3, 4.0, FirstFrame::Replaced),
    ] {
        let mut sched = Scheduler::new(cfg.clone()).unwrap();
        let counter = Counter::default();
        let opts = SampleOptions {
            steps,
            guidance_scale: guidance,
            first_frame,
            ..SampleOptions::default()
        };
        let with =
            sample_latents_with_progress(&oracle, &mut sched, &image, &opts, &counter).unwrap();
        assert_eq!(
            *counter.starts.lock().unwrap(),
            [(steps, DENOISING.to_owned())]
        );
        assert_eq!(counter.ticks.load(SeqCst), steps);
        assert_eq!(counter.finishes.load(SeqCst), 1);
        // Reporting changes nothing.
        let mut sched = Scheduler::new(cfg.clone()).unwrap();
        let without = sample_latents(&oracle, &mut sched, &image, &opts).unwrap();
        assert!(with.equal(&without));
    }
    // A failing loop still finishes its stage.
    let counter = Counter::default();
    let mut sched = Scheduler::new(cfg).unwrap();
    struct Failing;
    impl Denoiser for Failing {
        fn velocity(&self, _: &Tensor, _: &Tensor, _: Guidance) -> Result<Tensor> {
            Err(WorldModelError::input("denoiser", "fails"))
        }
    }
    let opts = SampleOptions {
        steps: 2,
        guidance_scale: 1.0,
        ..SampleOptions::default()
    };
    assert!(sample_latents_with_progress(&Failing, &mut sched, &image, &opts, &counter).is_err());
    assert_eq!(counter.ticks.load(SeqCst), 0);
    assert_eq!(counter.finishes.load(SeqCst), 1);
}

/// Records the timesteps and the noisy latents it is called with, and
/// predicts like the oracle.
struct Recording {
    oracle: Oracle,
    calls: std::sync::Mutex<Vec<(i64, Tensor)>>,
}

impl Denoiser for Recording {
    fn velocity(&self, latent_in: &Tensor, timestep: &Tensor, g: Guidance) -> Result<Tensor> {
        let c = latent_in.size()[2] / 2;
        self.calls
            .lock()
            .unwrap()
            .push((timestep.int64_value(&[0]), latent_in.narrow(2, 0, c).copy()));
        self.oracle.velocity(latent_in, timestep, g)
    }
}

#[test]
fn a_partial_strength_starts_from_the_noised_first_frame() {
    let mut cfg = SchedulerConfig::cogvideox_5b_i2v();
    cfg.rescale_betas_zero_snr = false; // keep 1 - a > 0 for the oracle's inversion
    let alphas = Scheduler::new(cfg.clone())
        .unwrap()
        .schedule()
        .alphas_cumprod
        .clone();
    tch::manual_seed(11);
    let x0 = Tensor::randn([1, 3, 4, 2, 2], (Kind::Float, Device::Cpu));
    // Image latents: frame 0 set, later frames zeros (first-frame conditioning).
    let image = Tensor::zeros([1, 3, 4, 2, 2], (Kind::Float, Device::Cpu));
    let z0 = Tensor::randn([1, 1, 4, 2, 2], (Kind::Float, Device::Cpu));
    image.narrow(1, 0, 1).copy_(&z0);
    for kind in [SamplerKind::Ddim, SamplerKind::Dpm] {
        let all = Scheduler::new(cfg.clone())
            .unwrap()
            .set_timesteps(10)
            .unwrap()
            .to_vec();
        for (strength, run) in [(0.5, 5), (0.31, 4), (0.01, 1), (1.0, 10)] {
            let rec = Recording {
                oracle: Oracle {
                    x0: x0.shallow_clone(),
                    alphas: alphas.clone(),
                },
                calls: Default::default(),
            };
            let opts = SampleOptions {
                steps: 10,
                guidance_scale: 1.0,
                seed: 9,
                strength,
                ..SampleOptions::default()
            };
            assert_eq!(opts.steps_run(), run);
            let mut sched = Scheduler::new(cfg.clone()).unwrap().with_kind(kind);
            let out = sample_latents(&rec, &mut sched, &image, &opts).unwrap();
            let calls = rec.calls.lock().unwrap();
            // Only the last `run` timesteps are denoised ...
            let seen: Vec<i64> = calls.iter().map(|(t, _)| *t).collect();
            assert_eq!(seen, all[10 - run..], "{kind:?} {strength}");
            // ... starting from the image latent in every frame, noised to
            // the first of them (pure noise at strength 1).
            tch::manual_seed(9);
            let eps = Tensor::randn([1, 3, 4, 2, 2], (Kind::Float, Device::Cpu));
            let expected = if run < 10 {
                let a = alphas[all[10 - run] as usize];
                z0.expand([1, 3, 4, 2, 2], false) * a.sqrt() + eps * (1.0 - a).sqrt()
            } else {
                eps
            };
            let start = (&calls[0].1 - expected).abs().max().double_value(&[]);
            assert!(start < 1e-5, "{kind:?} {strength}: {start}");
            // A perfect denoiser still ends at its clean sample.
            let err = (out - &x0).abs().max().double_value(&[]);
            assert!(err < 1e-3, "{kind:?} {strength}: {err}");
        }
    }
    for bad in [0.0, -0.5, 1.5, f64::NAN] {
        let opts = SampleOptions {
            strength: bad,
            ..SampleOptions::default()
        };
        let mut sched = Scheduler::new(cfg.clone()).unwrap();
        let oracle = Oracle {
            x0: x0.shallow_clone(),
            alphas: alphas.clone(),
        };
        let e = sample_latents(&oracle, &mut sched, &image, &opts)
            .unwrap_err()
            .to_string();
        assert!(e.contains("strength") && e.contains("(0, 1]"), "{e}");
    }
}

/// Predicts zeros, then `value` from call `from` on.
struct Breaks(f64, usize, std::sync::atomic::AtomicUsize);

impl Denoiser for Breaks {
    fn velocity(&self, x: &Tensor, _: &Tensor, _: Guidance) -> Result<Tensor> {
        let call = self.2.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        let v = x.narrow(2, 0, x.size()[2] / 2).zeros_like();
        Ok(if call >= self.1 { v + self.0 } else { v })
    }
}

#[test]
fn latents_that_diverge_name_the_step_and_what_to_check() {
    let image = Tensor::zeros([1, 3, 4, 2, 2], (Kind::Float, Device::Cpu));
    let opts = SampleOptions {
        steps: 4,
        guidance_scale: 1.0,
        ..SampleOptions::default()
    };
    let run = |d: &Breaks, image: &Tensor| {
        let mut sched = Scheduler::new(SchedulerConfig::cogvideox_5b_i2v()).unwrap();
        match sample_latents(d, &mut sched, image, &opts) {
            Ok(x) => panic!("no error: {x}"),
            Err(e) => e.to_string(),
        }
    };
    let e = run(&Breaks(f64::NAN, 1, Default::default()), &image);
    assert!(
        e.contains("step 2 of 4")
            && e.contains("prediction was not finite")
            && e.contains("weights"),
        "{e}"
    );
    // A finite prediction that overflows in the step names the scheduler's fields.
    let e = run(&Breaks(f64::from(f32::MAX), 0, Default::default()), &image);
    assert!(
        e.contains("step 2 of 4") && e.contains("beta_end") && e.contains("3.4"),
        "{e}"
    );
    let e = run(
        &Breaks(0.0, 0, Default::default()),
        &(image.shallow_clone() / 0.0),
    );
    assert!(
        e.contains("image latents") && e.contains("scaling_factor"),
        "{e}"
    );
}

#[test]
fn bad_guidance_is_an_error() {
    let mut sched = Scheduler::new(SchedulerConfig::cogvideox_2b()).unwrap();
    let oracle = Oracle {
        x0: Tensor::zeros([1], (Kind::Float, Device::Cpu)),
        alphas: vec![],
    };
    let image = Tensor::zeros([1, 1, 2, 1, 1], (Kind::Float, Device::Cpu));
    let opts = SampleOptions {
        guidance_scale: 0.5,
        ..SampleOptions::default()
    };
    assert!(sample_latents(&oracle, &mut sched, &image, &opts).is_err());
}
