//! The ways one training step runs: gradient checkpointing, bf16 autocast
//! on the CPU, and data-parallel shards.

use crate::common::{config, lock};
use bridgev2w_train::config::Stage;
use bridgev2w_train::trainer::Trainer;
use tch::Kind;

#[test]
fn gradient_checkpointing_trains_exactly_like_the_plain_backward() {
    let _g = lock();
    let tmp = tempfile::tempdir().unwrap();
    // The mask branch with the flow loss on (gradients through the decoder),
    // the action-MLP ablation (gradients into the injected residuals), and
    // the prior stage (the whole backbone trains: embeddings, head, blocks).
    for (variant, mask_action) in [("masks", true), ("actions", false), ("prior", true)] {
        let run = |checkpointing: bool| {
            let mut c = config(&tmp.path().join(format!("{variant}-{checkpointing}")));
            c.ablation.mask_action = mask_action;
            c.train.condition_dropout = 0.0;
            c.train.max_steps = 3;
            c.train.e_switch = 0;
            c.train.gradient_checkpointing = checkpointing;
            if variant == "prior" {
                c.train.stage = Stage::Prior;
            }
            let mut t = Trainer::new(c).unwrap();
            let metrics = t.run(&mut |_| {}).unwrap();
            let params: Vec<(String, tch::Tensor)> = t
                .opt
                .params()
                .iter()
                .map(|(n, p)| (n.clone(), p.detach().copy()))
                .collect();
            (metrics, params)
        };
        let (plain, plain_params) = run(false);
        let (ckpt, ckpt_params) = run(true);
        assert!(plain.iter().all(|m| m.flow_weight > 0.0) || variant == "prior");
        for (a, b) in plain.iter().zip(&ckpt) {
            assert!(
                (a.loss - b.loss).abs() <= 1e-5 * a.loss.abs().max(1.0),
                "{variant} step {}: loss {} vs {}",
                a.step,
                a.loss,
                b.loss
            );
            assert!(
                (a.grad_norm - b.grad_norm).abs() <= 1e-4 * a.grad_norm.max(1e-6),
                "{variant} step {}: gradient norm {} vs {}",
                a.step,
                a.grad_norm,
                b.grad_norm
            );
        }
        assert_eq!(plain_params.len(), ckpt_params.len());
        for ((name, a), (_, b)) in plain_params.iter().zip(&ckpt_params) {
            let diff = (a - b).abs().max().double_value(&[]);
            assert!(diff < 1e-5, "{variant} {name}: parameters differ by {diff}");
        }
    }
}

#[test]
fn bf16_autocast_on_cpu_trains_close_to_f32_and_keeps_f32_state() {
    use bridgev2w_torch_ext::autocast::{is_enabled, AutocastDevice};
    use bridgev2w_torch_ext::AutocastDtype;
    let _g = lock();
    let tmp = tempfile::tempdir().unwrap();
    let mut c = config(&tmp.path().join("f32"));
    c.train.condition_dropout = 0.0;
    c.train.max_steps = 3;
    // `auto` on the CPU is off.
    assert_eq!(c.train.autocast, bridgev2w_train::config::Autocast::Auto);
    let mut f32_run = Trainer::new(c.clone()).unwrap();
    assert_eq!(f32_run.autocast_dtype(), None);
    c.train.autocast = bridgev2w_train::config::Autocast::Bf16;
    c.train.out = tmp.path().join("bf16");
    let mut bf16_run = Trainer::new(c.clone()).unwrap();
    assert_eq!(bf16_run.autocast_dtype(), Some(AutocastDtype::BFloat16));
    c.train.gradient_checkpointing = true;
    c.train.out = tmp.path().join("bf16-ckpt");
    let mut ckpt_run = Trainer::new(c).unwrap();
    for step in 0..3 {
        let a = f32_run.train_step().unwrap();
        let b = bf16_run.train_step().unwrap();
        let k = ckpt_run.train_step().unwrap();
        let rel = (b.loss - a.loss).abs() / a.loss.abs();
        eprintln!(
            "step {step}: f32 {:.6} bf16 {:.6} ({:.3}%) bf16+ckpt {:.6}",
            a.loss,
            b.loss,
            100.0 * rel,
            k.loss
        );
        assert!(
            b.loss.is_finite() && rel < 0.01,
            "step {step}: bf16 loss {} vs f32 {} ({:.2}%)",
            b.loss,
            a.loss,
            100.0 * rel
        );
        // Autocast was really on: bf16 rounding changes the loss.
        assert_ne!(a.loss, b.loss, "step {step}: bf16 loss equals the f32 loss");
        // Gradient checkpointing replays the blocks in bf16 too: the same
        // forward, the same (up to summation order) gradients.
        let relk = (k.loss - b.loss).abs() / b.loss.abs();
        assert!(
            relk < 1e-3,
            "step {step}: checkpointed bf16 loss {} vs {}",
            k.loss,
            b.loss
        );
        assert!(
            (k.grad_norm - b.grad_norm).abs() < 1e-2 * b.grad_norm,
            "step {step}: checkpointed bf16 grad norm {} vs {}",
            k.grad_norm,
            b.grad_norm
        );
    }
    // The state outside the step is untouched, and the parameters, their
    // gradients and the AdamW moments stay f32.
    assert!(!is_enabled(AutocastDevice::Cpu).unwrap());
    for (name, p) in bf16_run.opt.params() {
        assert_eq!(p.kind(), Kind::Float, "{name}");
        let g = p.grad();
        assert!(!g.defined() || g.kind() == Kind::Float, "grad of {name}");
    }
    for (name, t) in bf16_run.opt.state() {
        if name != "steps" {
            assert_eq!(t.kind(), Kind::Float, "{name}");
        }
    }
    // The frozen backbone is stored in bf16 (half the memory), the f32 run's
    // in f32; the trained adapters stay f32 in both.
    for (name, t) in bf16_run.model.transformer.vs.variables() {
        assert_eq!(t.kind(), Kind::BFloat16, "frozen backbone {name}");
    }
    for (name, t) in f32_run.model.transformer.vs.variables() {
        assert_eq!(t.kind(), Kind::Float, "f32 backbone {name}");
    }
    for (name, t) in bf16_run.model.adapters.variables() {
        assert_eq!(t.kind(), Kind::Float, "adapter {name}");
    }
    // Sampling (previews, evaluation) runs in the training's autocast, so
    // the bf16 backbone predicts from f32 inputs.
    let batch = bf16_run.batch(0).unwrap();
    let video = bf16_run
        .predict(
            &batch,
            &bridgev2w_world_model::pipeline::SampleOptions {
                steps: 2,
                ..Default::default()
            },
        )
        .unwrap();
    assert!(video.isfinite().all().int64_value(&[]) == 1);
    // And the updates follow the f32 run's closely.
    let mut num = 0.0;
    let mut den = 0.0;
    for ((name, p), (_, q)) in bf16_run.opt.params().iter().zip(f32_run.opt.params()) {
        let d = (p - q).to_kind(Kind::Double).square().sum(Kind::Double);
        num += d.double_value(&[]);
        den += q
            .to_kind(Kind::Double)
            .square()
            .sum(Kind::Double)
            .double_value(&[]);
        assert!(num.is_finite(), "{name}");
    }
    assert!(
        (num / den).sqrt() < 0.05,
        "bf16 parameters differ from f32 by {:.3} (relative)",
        (num / den).sqrt()
    );
}

/// A stand-in backend: the rank and world size of a data-parallel run, and
/// an all-reduce that assumes every rank holds the same buffer.
#[derive(Debug)]
struct AloneCollective {
    rank: usize,
    world: usize,
}

impl bridgev2w_train::distributed::Collective for AloneCollective {
    fn rank(&self) -> usize {
        self.rank
    }
    fn world(&self) -> usize {
        self.world
    }
    fn name(&self) -> &'static str {
        "alone"
    }
    fn all_reduce_sum(&mut self, buf: &mut tch::Tensor) -> bridgev2w_train::Result<()> {
        let _ = buf.g_mul_scalar_(self.world as f64);
        Ok(())
    }
    fn all_gather_f64(&mut self, row: &[f64]) -> bridgev2w_train::Result<Vec<Vec<f64>>> {
        Ok(vec![row.to_vec(); self.world])
    }
    fn barrier(&mut self) -> bridgev2w_train::Result<()> {
        Ok(())
    }
}

#[test]
fn data_parallel_shards_see_the_global_batch_draws() {
    let _g = lock();
    let tmp = tempfile::tempdir().unwrap();
    let mut c = config(tmp.path());
    c.train.batch_size = 4;
    c.data.clips_per_video = 4;
    c.train.condition_dropout = 0.0;
    let whole = Trainer::new(c.clone()).unwrap();
    let shards: Vec<Trainer> = (0..2)
        .map(|rank| {
            Trainer::with_collective(c.clone(), Box::new(AloneCollective { rank, world: 2 }))
                .unwrap()
        })
        .collect();
    for step in [0, 1, 5] {
        let b = whole.batch(step).unwrap();
        let l = whole.losses(&b, step).unwrap();
        let mut diff = 0.0;
        let mut dynm = 0.0;
        for t in &shards {
            let sb = t.batch(step).unwrap();
            assert_eq!(sb.video.size()[0], 2);
            // The shard's clips are the whole batch's items rank, rank + 2.
            let rows = tch::Tensor::from_slice(&[
                t.rank_and_world().0 as i64,
                t.rank_and_world().0 as i64 + 2,
            ]);
            let expect = b.video.index_select(0, &rows);
            assert_eq!(
                (sb.video - expect).abs().max().double_value(&[]),
                0.0,
                "step {step}: shard clips"
            );
            let sl = t.losses(&t.batch(step).unwrap(), step).unwrap();
            diff += sl.diffusion / 2.0;
            dynm += sl.dynamics / 2.0;
        }
        assert!(
            (diff - l.diffusion).abs() < 1e-5 * l.diffusion,
            "step {step}: diffusion {} (whole) vs {diff} (mean of shards)",
            l.diffusion
        );
        assert!(
            (dynm - l.dynamics).abs() < 1e-5 * l.dynamics.max(1e-6),
            "step {step}: dynamics {} (whole) vs {dynm} (mean of shards)",
            l.dynamics
        );
    }
}
