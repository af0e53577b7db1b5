//! Trainer tests on a tiny synthetic dataset (`random:tiny` backbone, 9
//! frames at 64x96): a run's life (overfitting, exact resume, moving
//! averages, refusals, the NaN guard) and the conditioning branches. The
//! data sources, stages, precisions and data parallelism are in
//! `trainer_stages/`. libtorch's generator is process-global, so the
//! tests that train run one at a time (`lock`).

#![allow(clippy::unwrap_used)]

mod common;

use bridgev2w_train::trainer::{resolve_checkpoint, Trainer};
use bridgev2w_train::TrainError;
use common::{config, controlnet_grad_sum, grad_abs_sum, lock, tensors};
use std::path::Path;
use tch::Kind;

#[test]
fn overfits_a_fixed_batch() {
    let _g = lock();
    let tmp = tempfile::tempdir().unwrap();
    let mut c = config(tmp.path());
    c.train.condition_dropout = 0.0;
    c.train.warmup_steps = 0;
    c.train.lr = 3e-3;
    let mut t = Trainer::new(c).unwrap();
    let batch = t.batch(0).unwrap();
    // Same batch, same timestep and noise (the draws of step 0) every update.
    let losses: Vec<f64> = (0..30).map(|_| t.update(&batch, 0).unwrap().loss).collect();
    let (first, last) = (losses[0], losses[29]);
    assert!(
        last < 0.7 * first,
        "loss did not decrease enough: {first} -> {last} ({losses:?})"
    );
}

#[test]
fn resume_repeats_the_uninterrupted_run() {
    let _g = lock();
    let tmp = tempfile::tempdir().unwrap();
    let full: Vec<f64> = {
        let mut t = Trainer::new(config(&tmp.path().join("full"))).unwrap();
        t.run(&mut |_| {}).unwrap().iter().map(|m| m.loss).collect()
    };
    assert_eq!(full.len(), 6);
    let part = tmp.path().join("part");
    let mut c = config(&part);
    c.train.max_steps = 3;
    let first: Vec<f64> = {
        let mut t = Trainer::new(c).unwrap();
        t.run(&mut |_| {}).unwrap().iter().map(|m| m.loss).collect()
    };
    // A fresh process-like start: new trainer, resumed from the run folder.
    let mut t = Trainer::new(config(&part)).unwrap();
    t.resume(&part).unwrap();
    assert_eq!(t.step, 3);
    let rest: Vec<f64> = t.run(&mut |_| {}).unwrap().iter().map(|m| m.loss).collect();
    let resumed: Vec<f64> = first.into_iter().chain(rest).collect();
    for (i, (a, b)) in full.iter().zip(&resumed).enumerate() {
        assert!(
            (a - b).abs() <= 1e-6 * a.abs().max(1.0),
            "step {i}: uninterrupted {a} vs resumed {b}"
        );
    }
    // The metrics file holds each step once.
    let lines = std::fs::read_to_string(part.join("metrics.jsonl")).unwrap();
    assert_eq!(lines.lines().count(), 6);
    assert!(part.join("final/weights.safetensors").is_file());
}

#[test]
fn moving_averages_resume_with_the_run_and_are_its_final_weights() {
    let _g = lock();
    let tmp = tempfile::tempdir().unwrap();
    let with_ema = |out: &Path, steps: usize| {
        let mut c = config(out);
        c.train.ema_decay = 0.5;
        c.train.max_steps = steps;
        c
    };
    let full = tmp.path().join("full");
    Trainer::new(with_ema(&full, 6))
        .unwrap()
        .run(&mut |_| {})
        .unwrap();
    let part = tmp.path().join("part");
    Trainer::new(with_ema(&part, 3))
        .unwrap()
        .run(&mut |_| {})
        .unwrap();
    assert!(part
        .join("checkpoints/step-00000003/ema.safetensors")
        .is_file());
    let mut t = Trainer::new(with_ema(&part, 6)).unwrap();
    t.resume(&part).unwrap();
    t.run(&mut |_| {}).unwrap();
    // The averages of the resumed run are those of the uninterrupted one.
    let ema_full = tensors(&full.join("checkpoints/step-00000006/ema.safetensors"));
    let ema_part = tensors(&part.join("checkpoints/step-00000006/ema.safetensors"));
    assert_eq!(ema_full.len(), ema_part.len());
    for ((n, a), (_, b)) in ema_full.iter().zip(&ema_part) {
        let d = a
            .iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max);
        assert!(d <= 1e-6, "{n}: the resumed average differs by {d}");
    }
    // The final weights are the averages; the checkpoint keeps the raw
    // parameters, which differ from them.
    let fin: std::collections::BTreeMap<_, _> = tensors(&full.join("final/weights.safetensors"))
        .into_iter()
        .collect();
    let raw: std::collections::BTreeMap<_, _> =
        tensors(&full.join("checkpoints/step-00000006/weights.safetensors"))
            .into_iter()
            .collect();
    let mut averaged = 0;
    let mut moved = 0;
    for (name, avg) in &ema_full {
        let key = name.split_once('.').map_or(name.as_str(), |(_, k)| k);
        let Some(w) = fin.get(key).or_else(|| fin.get(name)) else {
            continue;
        };
        averaged += 1;
        assert_eq!(w, avg, "{name}: the final weight is not the average");
        if raw.get(key).or_else(|| raw.get(name)) != Some(avg) {
            moved += 1;
        }
    }
    assert!(
        averaged > 0,
        "no averaged tensor found in the final weights"
    );
    assert!(moved > 0, "the averages equal the raw parameters");
    // A config that averages cannot resume a checkpoint without averages.
    let plain = tmp.path().join("plain");
    let mut c = config(&plain);
    c.train.max_steps = 3;
    Trainer::new(c).unwrap().run(&mut |_| {}).unwrap();
    let e = Trainer::new(with_ema(&plain, 6))
        .unwrap()
        .resume(&plain)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("ema.safetensors") && e.contains("ema_decay"),
        "{e}"
    );
}

#[test]
fn a_second_run_into_the_same_out_is_refused_unless_resumed_or_overwritten() {
    let _g = lock();
    let tmp = tempfile::tempdir().unwrap();
    let mut c = config(tmp.path());
    c.train.max_steps = 4;
    c.train.checkpoint_every = 2;
    c.train.keep_checkpoints = 1;
    Trainer::new(c.clone()).unwrap().run(&mut |_| {}).unwrap();
    let metrics = std::fs::read_to_string(tmp.path().join("metrics.jsonl")).unwrap();
    let weights = std::fs::read(tmp.path().join("final/weights.safetensors")).unwrap();
    // The lost run of issue 20: a new run without --resume.
    let mut short = c.clone();
    short.train.max_steps = 2;
    let err = Trainer::new(short.clone())
        .unwrap()
        .run(&mut |_| {})
        .unwrap_err()
        .to_string();
    assert!(err.contains("already holds a run"), "{err}");
    assert_eq!(
        std::fs::read_to_string(tmp.path().join("metrics.jsonl")).unwrap(),
        metrics
    );
    assert_eq!(
        std::fs::read(tmp.path().join("final/weights.safetensors")).unwrap(),
        weights
    );
    assert_eq!(
        resolve_checkpoint(tmp.path()).unwrap().file_name().unwrap(),
        "step-00000004"
    );
    // Resuming with another learning rate mixes two runs: refused too.
    let mut other = c.clone();
    other.train.lr *= 2.0;
    other.train.max_steps = 6;
    let mut t = Trainer::new(other).unwrap();
    t.resume(tmp.path()).unwrap();
    let err = t.run(&mut |_| {}).unwrap_err().to_string();
    assert!(err.contains("train.lr"), "{err}");
    // Starting over on request: a fresh run whose checkpoints survive pruning.
    let mut t = Trainer::new(short).unwrap();
    t.overwrite_existing_run();
    t.run(&mut |_| {}).unwrap();
    let ck = resolve_checkpoint(tmp.path()).unwrap();
    assert!(ck.join("state.json").is_file(), "{}", ck.display());
    assert!(ck.ends_with("step-00000002"), "{}", ck.display());
    let lines = std::fs::read_to_string(tmp.path().join("metrics.jsonl")).unwrap();
    assert_eq!(lines.lines().count(), 2);
}

#[test]
fn a_checkpoint_step_beyond_any_run_is_refused() {
    let _g = lock();
    let tmp = tempfile::tempdir().unwrap();
    let mut c = config(tmp.path());
    c.train.max_steps = 3;
    Trainer::new(c.clone()).unwrap().run(&mut |_| {}).unwrap();
    let ck = resolve_checkpoint(tmp.path()).unwrap();
    let state = ck.join("state.json");
    let text = std::fs::read_to_string(&state).unwrap();
    let crafted = text.replace("\"step\":3", &format!("\"step\":{}", u64::MAX));
    assert_ne!(crafted, text, "{text}");
    std::fs::write(&state, crafted).unwrap();
    let err = Trainer::new(c.clone())
        .unwrap()
        .resume(tmp.path())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("state.json") && err.contains("beyond"),
        "{err}"
    );
    // A checkpoint whose folder name says another step than its state.json
    // (issue 69): refused naming the folder, the field and both values.
    std::fs::write(&state, &text).unwrap();
    let renamed = ck.with_file_name("step-00000005");
    std::fs::rename(&ck, &renamed).unwrap();
    std::fs::write(tmp.path().join("checkpoints/latest"), "step-00000005").unwrap();
    let err = Trainer::new(c)
        .unwrap()
        .resume(tmp.path())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains(&*renamed.to_string_lossy())
            && err.contains("`step` is 3")
            && err.contains("named for step 5"),
        "{err}"
    );
}

#[test]
fn nan_guard_stops_and_keeps_the_last_good_checkpoint() {
    let _g = lock();
    let tmp = tempfile::tempdir().unwrap();
    let mut c = config(tmp.path());
    c.train.checkpoint_every = 2;
    c.train.inject_nan_at_step = Some(3);
    let mut t = Trainer::new(c.clone()).unwrap();
    let err = t.run(&mut |_| {}).unwrap_err();
    match &err {
        TrainError::NonFinite { step, term, .. } => {
            assert_eq!((*step, term.as_str()), (3, "diffusion"));
        }
        other => panic!("expected NonFinite, got {other}"),
    }
    let msg = err.to_string();
    assert!(
        msg.contains("step 3") && msg.contains("diffusion") && msg.contains("train.lr"),
        "{msg}"
    );
    // Parameters were not touched by the bad step.
    for (name, p) in t.opt.params() {
        let finite = p.isfinite().all().int64_value(&[]) != 0;
        assert!(finite, "{name} is not finite");
    }
    let ck = resolve_checkpoint(tmp.path()).unwrap();
    assert!(ck.ends_with("step-00000002"), "{}", ck.display());
    c.train.inject_nan_at_step = None;
    let mut t2 = Trainer::new(c).unwrap();
    t2.resume(tmp.path()).unwrap();
    assert_eq!(t2.step, 2);
    for (name, p) in t2.opt.params() {
        assert!(p.isfinite().all().int64_value(&[]) != 0, "{name}");
    }
    // Training goes on from the kept checkpoint (taken after 2 steps).
    let m = t2.train_step().unwrap();
    assert!(m.loss.is_finite());
}

#[test]
fn condition_dropout_one_gives_the_controlnet_no_gradient() {
    let _g = lock();
    let tmp = tempfile::tempdir().unwrap();
    for (p, expect_zero) in [(1.0, true), (0.0, false)] {
        let mut c = config(tmp.path());
        c.train.condition_dropout = p;
        let mut t = Trainer::new(c).unwrap();
        let batch = t.batch(0).unwrap();
        t.opt.zero_grad();
        let l = t.losses(&batch, 0).unwrap();
        assert_eq!(l.dropped, expect_zero);
        l.total.backward();
        let g = controlnet_grad_sum(&t);
        if expect_zero {
            assert_eq!(g, 0.0, "p = 1: ControlNet gradient {g}");
        } else {
            assert!(g > 0.0, "p = 0: the ControlNet gets no gradient");
        }
    }
}

#[test]
fn flow_loss_switches_on_at_e_switch() {
    let _g = lock();
    let tmp = tempfile::tempdir().unwrap();
    let mut c = config(tmp.path());
    c.train.e_switch = 1; // 2 episodes, batch 1: epoch 1 starts at step 2
    let t = Trainer::new(c.clone()).unwrap();
    assert_eq!(t.steps_per_epoch(), 2);
    for step in 0..2 {
        let l = t.losses(&t.batch(step).unwrap(), step).unwrap();
        assert_eq!((l.flow_weight, l.flow), (0.0, 0.0), "step {step}");
    }
    let b = t.batch(2).unwrap();
    let l = t.losses(&b, 2).unwrap();
    assert_eq!(l.flow_weight, 0.05);
    assert!(l.flow.is_finite() && l.flow > 0.0, "flow {}", l.flow);
    // The flow term carries gradients into the adapters through the decoder.
    l.total.backward();
    // Ablation: flow_loss = false keeps it off.
    c.ablation.flow_loss = false;
    let t = Trainer::new(c).unwrap();
    let l = t.losses(&b, 2).unwrap();
    assert_eq!((l.flow_weight, l.flow), (0.0, 0.0));
}

#[test]
fn action_mlp_ablation_trains_the_action_encoder() {
    let _g = lock();
    let tmp = tempfile::tempdir().unwrap();
    let mut c = config(tmp.path());
    c.ablation.mask_action = false;
    c.train.condition_dropout = 0.0;
    let mut t = Trainer::new(c).unwrap();
    assert!(t
        .opt
        .params()
        .iter()
        .all(|(n, _)| !n.starts_with("adapters.controlnet.")));
    let batch = t.batch(0).unwrap();
    t.opt.zero_grad();
    let l = t.losses(&batch, 0).unwrap();
    l.total.backward();
    let g = grad_abs_sum(&t, "action.");
    assert!(g > 0.0, "the action MLP gets no gradient");
    let m = t.train_step().unwrap();
    assert!(m.loss.is_finite());
}

#[test]
fn non_zero_init_branch_changes_the_output_at_start() {
    let _g = lock();
    let tmp = tempfile::tempdir().unwrap();
    let mut c = config(tmp.path());
    c.train.condition_dropout = 0.0;
    let zero = Trainer::new(c.clone()).unwrap();
    c.ablation.controlnet = false;
    let nonzero = Trainer::new(c).unwrap();
    let named = |t: &Trainer| -> f64 {
        t.opt
            .params()
            .iter()
            .filter(|(n, _)| n.contains("out_projectors"))
            .map(|(_, p)| p.abs().sum(Kind::Double).double_value(&[]))
            .sum()
    };
    assert_eq!(named(&zero), 0.0);
    assert!(named(&nonzero) > 0.0);
}

/// A step that runs out of memory is an error naming the step's shapes and
/// what lowers its memory (libtorch's CPU allocator refusing here; a panic
/// of an op's is caught as well: the unit test of `guarded`). The trainer
/// goes on training afterwards.
#[test]
fn a_step_that_runs_out_of_memory_is_an_error_naming_the_step() {
    let _g = lock();
    let tmp = tempfile::tempdir().unwrap();
    let mut t = Trainer::new(config(tmp.path())).unwrap();
    let batch = t.batch(0).unwrap();
    // 2^20 clips as stride-0 views of the first: nothing is allocated until
    // a layer's output, petabytes, which no allocator gives.
    let n = 1_i64 << 20;
    let wide = |x: &tch::Tensor| {
        let mut size = x.size();
        size[0] = n;
        x.narrow(0, 0, 1).expand(size.as_slice(), false)
    };
    let mut huge = t.batch(0).unwrap();
    huge.first_frames = wide(&batch.first_frames);
    huge.video = wide(&batch.video);
    huge.masks = wide(&batch.masks);
    huge.actions = wide(&batch.actions);
    huge.episodes = vec![batch.episodes[0]; n as usize];
    let e = t.update(&huge, 0).unwrap_err();
    let text = e.to_string();
    assert!(matches!(e, TrainError::OutOfMemory { .. }), "{text}");
    assert!(
        text.contains("training step 0 (1048576 clip(s) of 9 frames at 64x96")
            && text.contains("memory")
            && text.contains("gradient_checkpointing = true")
            && !text.contains("frame #"),
        "{text}"
    );
    assert!(t.update(&batch, 0).unwrap().loss.is_finite());
}
