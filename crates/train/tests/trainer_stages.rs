//! Trainer tests on a tiny synthetic dataset (`random:tiny` backbone):
//! mask sources, RAFT's flow loss, the VAE / prior / decoder stages, the
//! evaluation, gradient checkpointing, bf16 autocast, data-parallel shards
//! and link-coded masks. libtorch's generator is process-global, so the
//! tests that train run one at a time (`lock`).

#![allow(clippy::unwrap_used)]

mod common;

use bridgev2w_train::config::{Stage, TrainConfig, VaeParts};
use bridgev2w_train::trainer::Trainer;
use bridgev2w_world_model::bridge::ImageConditioning;
use bridgev2w_world_model::pipeline::SampleOptions;
use common::{assert_trains_only, config, controlnet_grad_sum, dataset, lock};
use std::path::Path;
use tch::Kind;

/// The clip pipeline's mask sources agree with the masks the synthetic world
/// wrote: `calc` rendered from the joint states and calibration (and cached),
/// and `seg` read back from PNG folders; mixing draws from both.
#[test]
fn calc_and_seg_mask_sources_and_mixing() {
    use bridgev2w_train::data::{ClipDataset, MaskKind, SourceSpec};
    let src = dataset();
    let reference = ClipDataset::open(src, "train", None, 9, 64, 96).unwrap();
    assert!(reference.has_masks());
    // A copy without masks/: calc masks are rendered for the robot and cached.
    let tmp = tempfile::tempdir().unwrap();
    let copy = tmp.path().join("nomasks");
    copy_dir(src, &copy);
    std::fs::remove_dir_all(copy.join("masks")).unwrap();
    let cache = tmp.path().join("cache");
    let spec = |masks: MaskKind, weight: f64| SourceSpec {
        root: copy.clone(),
        split: "train".into(),
        video_key: None,
        masks,
        weight,
    };
    let calc = MaskKind::Calc {
        robot: Some("franka".into()),
        cache: cache.clone(),
    };
    let rendered = ClipDataset::open_sources(&[spec(calc.clone(), 1.0)], 9, 64, 96, 3).unwrap();
    for (a, b) in rendered.episodes.iter().zip(&reference.episodes) {
        let (ma, mb) = (a.masks.as_ref().unwrap(), b.masks.as_ref().unwrap());
        let differ = ma.iter().zip(mb).filter(|(x, y)| x != y).count();
        assert_eq!(
            differ, 0,
            "episode {}: rendered calc masks differ from the synthetic ground truth",
            a.index
        );
    }
    let cached: Vec<_> = std::fs::read_dir(cache.join("observation.images.main"))
        .unwrap()
        .flatten()
        .collect();
    assert_eq!(cached.len(), 2, "one cache file per episode");
    assert!(cached[0]
        .file_name()
        .to_string_lossy()
        .ends_with("_96x64.npy"));
    // Rendering needs the calibration: its absence is an error naming the file and episode.
    let nocal = tmp.path().join("nocal");
    copy_dir(&copy, &nocal);
    std::fs::remove_dir_all(nocal.join("meta/calibration")).unwrap();
    let err = ClipDataset::open_sources(
        &[SourceSpec {
            root: nocal.clone(),
            ..spec(
                MaskKind::Calc {
                    robot: Some("franka".into()),
                    cache: tmp.path().join("c3"),
                },
                1.0,
            )
        }],
        9,
        64,
        96,
        1,
    )
    .unwrap_err();
    assert!(
        err.to_string()
            .contains("missing camera calibration of episode"),
        "{err}"
    );
    // Without a robot and without masks/, calc gives no masks (the ablation's case).
    let none = ClipDataset::open_sources(
        &[spec(
            MaskKind::Calc {
                robot: None,
                cache: tmp.path().join("c2"),
            },
            1.0,
        )],
        9,
        64,
        96,
        1,
    )
    .unwrap();
    assert!(!none.has_masks());

    // seg: PNG folders (here: the ground truth at half resolution, upsampled nearest).
    let seg = tmp.path().join("seg");
    for e in &reference.episodes {
        let dir = seg.join(format!("episode_{:06}", e.index));
        std::fs::create_dir_all(&dir).unwrap();
        let m = e.masks.as_ref().unwrap();
        for f in 0..e.frames {
            let half: Vec<u8> = (0..32 * 48)
                .map(|k| 255 * u8::from(m[f * 64 * 96 + (k / 48) * 2 * 96 + (k % 48) * 2] != 0))
                .collect();
            std::fs::write(
                dir.join(format!("{f:06}.png")),
                bridgev2w_io::png::encode_gray8(48, 32, &half),
            )
            .unwrap();
        }
    }
    let open_seg = || {
        ClipDataset::open_sources(
            &[spec(MaskKind::Seg { dir: seg.clone() }, 1.0)],
            9,
            64,
            96,
            1,
        )
    };
    let segd = open_seg().unwrap();
    for (a, b) in segd.episodes.iter().zip(&reference.episodes) {
        let (ma, mb) = (a.masks.as_ref().unwrap(), b.masks.as_ref().unwrap());
        // seg masks are 0/1; the reference holds the synthetic link labels.
        let agree = ma
            .iter()
            .zip(mb)
            .filter(|(x, y)| (**x != 0) == (**y != 0))
            .count() as f64
            / ma.len() as f64;
        assert!(
            agree > 0.97,
            "seg masks agree with the ground truth on {agree}"
        );
    }
    // A missing frame is an error naming the folder.
    std::fs::remove_file(seg.join(format!(
        "episode_{:06}/000003.png",
        reference.episodes[0].index
    )))
    .unwrap();
    let err = open_seg().unwrap_err();
    assert!(
        err.to_string().contains("11 PNG masks for 12 video frames"),
        "{err}"
    );

    // Mixing: weights 3:1 between two sources; every epoch covers each video clips_per_video times
    // within its share.
    let mixed =
        ClipDataset::open_sources(&[spec(calc.clone(), 3.0), spec(calc, 1.0)], 9, 64, 96, 20)
            .unwrap();
    assert_eq!(mixed.episodes.len(), 4);
    assert_eq!(mixed.steps_per_epoch(4), 20);
    let slots = mixed.epoch_slots(5, 0, 4000);
    let first = slots
        .iter()
        .filter(|&&i| mixed.episodes[i].source == 0)
        .count() as f64
        / 4000.0;
    assert!((first - 0.75).abs() < 0.03, "share of source 0: {first}");
    assert_eq!(slots, mixed.epoch_slots(5, 0, 4000), "deterministic");
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            copy_dir(&p, &to.join(e.file_name()));
        } else {
            std::fs::copy(&p, to.join(e.file_name())).unwrap();
        }
    }
}

/// The flow loss with a frozen RAFT (random `raft_small` weights written as a
/// torchvision-keyed safetensors file): finite, positive, and its gradient
/// reaches the adapters through the VAE decoder; RAFT itself stays frozen.
#[test]
fn raft_flow_loss_trains_through_the_decoder() {
    use bridgev2w_world_model::nets::raft::{Raft, RaftConfig};
    use bridgev2w_world_model::weights::save_safetensors;
    use bridgev2w_world_model::ComputeDevice;
    let _g = lock();
    let tmp = tempfile::tempdir().unwrap();
    tch::manual_seed(11);
    let raft = Raft::new(
        RaftConfig::by_name("raft_small").unwrap(),
        ComputeDevice::Cpu,
    )
    .unwrap();
    let named: Vec<(String, tch::Tensor)> = raft.var_store().variables().into_iter().collect();
    let weights = tmp.path().join("raft_small.safetensors");
    save_safetensors(&named, &weights).unwrap();
    let mut c = config(tmp.path());
    c.train.e_switch = 0;
    c.train.condition_dropout = 0.0;
    c.train.raft_weights = Some(weights);
    c.train.raft_model = bridgev2w_world_model::nets::raft::RaftVariant::RaftSmall;
    c.train.raft_iterations = 2;
    let grads = |c: TrainConfig| -> (f64, f64) {
        let t = Trainer::new(c).unwrap();
        let l = t.losses(&t.batch(0).unwrap(), 0).unwrap();
        assert!(!l.dropped);
        l.total.backward();
        (l.flow, controlnet_grad_sum(&t))
    };
    let (flow, with_flow) = grads(c.clone());
    assert!(flow.is_finite() && flow > 0.0, "RAFT flow loss {flow}");
    c.ablation.flow_loss = false;
    let (off, without_flow) = grads(c);
    assert_eq!(off, 0.0);
    assert!(with_flow > 0.0 && without_flow > 0.0);
    assert!(
        (with_flow - without_flow).abs() > 1e-9 * without_flow,
        "the RAFT flow term adds gradient to the branch: {with_flow} vs {without_flow}"
    );
}

/// The video-prior stages: `vae` trains the autoencoder (reconstruction
/// falls, the latent scale is re-estimated) and writes a diffusers backbone;
/// `prior` trains that backbone's transformer action-free (no branch, no
/// adapters) and writes it again; the paper's fine-tuning then starts from it.
#[test]
fn vae_then_prior_stages_write_a_backbone_the_next_stage_loads() {
    let _g = lock();
    let tmp = tempfile::tempdir().unwrap();
    let mut c = config(&tmp.path().join("vae"));
    c.train.stage = Stage::Vae;
    c.train.max_steps = 24;
    c.train.lr = 2e-3;
    c.train.warmup_steps = 0;
    c.train.checkpoint_every = 0;
    let mut t = Trainer::new(c).unwrap();
    assert_trains_only(&t, "vae.");
    let m = t.run(&mut |_| {}).unwrap();
    let first: f64 = m[..4].iter().map(|x| x.recon).sum::<f64>() / 4.0;
    let last: f64 = m[20..].iter().map(|x| x.recon).sum::<f64>() / 4.0;
    assert!(m
        .iter()
        .all(|x| x.recon > 0.0 && x.kl >= 0.0 && x.diffusion == 0.0));
    assert!(last < 0.8 * first, "reconstruction L1 {first} -> {last}");
    let backbone = tmp.path().join("vae/final/backbone");
    let vcfg: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(backbone.join("vae/config.json")).unwrap())
            .unwrap();
    let scale = vcfg["scaling_factor"].as_f64().unwrap();
    assert!(
        scale.is_finite() && scale > 0.0 && (scale - 0.7).abs() > 1e-6,
        "re-estimated scale {scale}"
    );

    // A clip stage from it, inflated: every causal convolution's weight sits
    // on the current frame's tap; only a vae stage accepts the switch.
    let mut c = config(&tmp.path().join("vae-clips"));
    c.model.backbone = backbone.display().to_string();
    (c.data.frames, c.data.height, c.data.width) = (9, 64, 96);
    (c.train.stage, c.train.inflate_image_vae) = (Stage::Vae, true);
    let t = Trainer::new(c.clone()).unwrap();
    let mut inflated = 0;
    for (name, w) in t.model.vae_vs.variables() {
        if w.dim() == 5 && w.size()[2] > 1 {
            let kt = w.size()[2];
            let earlier = w.narrow(2, 0, kt - 1).abs().max().double_value(&[]);
            assert_eq!(earlier, 0.0, "{name}");
            assert!(w.narrow(2, kt - 1, 1).abs().max().double_value(&[]) > 0.0);
            inflated += 1;
        }
    }
    assert!(inflated > 4, "{inflated} inflated convolutions");
    c.train.stage = Stage::Prior;
    let e = Trainer::new(c).unwrap_err().to_string();
    assert!(e.contains("train.inflate_image_vae"), "{e}");

    // A decoder-only stage from it: only the decoder trains, the encoder
    // (and so the latents every later stage was trained on) stays as loaded.
    let mut c = config(&tmp.path().join("vae-decoder"));
    c.model.backbone = backbone.display().to_string();
    (c.data.frames, c.data.height, c.data.width) = (9, 64, 96);
    (c.train.stage, c.train.vae_parts) = (Stage::Vae, VaeParts::Decoder);
    (
        c.train.max_steps,
        c.train.lr,
        c.train.warmup_steps,
        c.train.checkpoint_every,
    ) = (3, 2e-3, 0, 0);
    let mut t = Trainer::new(c).unwrap();
    assert_trains_only(&t, "vae.decoder.");
    let before: Vec<(String, tch::Tensor)> = t
        .model
        .vae_vs
        .variables()
        .into_iter()
        .map(|(n, v)| (n, v.detach().copy()))
        .collect();
    t.run(&mut |_| {}).unwrap();
    let after = t.model.vae_vs.variables();
    let mut changed = 0;
    for (n, v) in &before {
        if n.starts_with("encoder.") {
            assert!(v.equal(&after[n]), "{n} moved");
        } else if !v.equal(&after[n]) {
            changed += 1;
        }
    }
    assert!(changed > 4, "{changed} decoder tensors trained");
    // ... and with it the latent scale the later stages were trained with.
    let scale_of = |dir: &Path| {
        let text = std::fs::read_to_string(dir.join("vae/config.json")).unwrap();
        serde_json::from_str::<serde_json::Value>(&text).unwrap()["scaling_factor"]
            .as_f64()
            .unwrap()
    };
    let decoder_backbone = tmp.path().join("vae-decoder/final/backbone");
    assert_eq!(scale_of(&decoder_backbone), scale_of(&backbone));

    let mut c = config(&tmp.path().join("prior"));
    c.model.backbone = backbone.display().to_string();
    (c.data.frames, c.data.height, c.data.width) = (9, 64, 96);
    c.train.stage = Stage::Prior;
    c.train.max_steps = 2;
    c.train.checkpoint_every = 0;
    c.model.image_conditioning = ImageConditioning::EveryFrame;
    let mut t = Trainer::new(c).unwrap();
    assert_trains_only(&t, "backbone.");
    let m = t.run(&mut |_| {}).unwrap();
    assert!(m
        .iter()
        .all(|x| x.dropped && x.flow == 0.0 && x.diffusion > 0.0));
    let prior = tmp.path().join("prior/final/backbone");
    assert!(prior.join("transformer/config.json").is_file());

    // model.transformer: a fresh transformer of that preset in place of the
    // folder's (a prior of another width over the same autoencoder). Over
    // the trained prior: fresh weights, the folder's VAE; the wide preset's
    // learned positions do not fit this VAE's latents: refused up front.
    let mut c = config(&tmp.path().join("prior-fresh"));
    c.model.backbone = prior.display().to_string();
    (c.data.frames, c.data.height, c.data.width) = (9, 64, 96);
    (c.train.stage, c.train.max_steps, c.train.checkpoint_every) = (Stage::Prior, 1, 0);
    c.model.image_conditioning = ImageConditioning::EveryFrame;
    let loaded = Trainer::new(c.clone()).unwrap();
    c.model.transformer = Some("tiny".into());
    let fresh = Trainer::new(c.clone()).unwrap();
    let weight = |t: &Trainer, name: &str| t.model.transformer.vs.variables()[name].shallow_clone();
    let name = "patch_embed.proj.weight";
    assert!(weight(&loaded, name).size() == weight(&fresh, name).size());
    assert!(!weight(&loaded, name).allclose(&weight(&fresh, name), 1e-6, 1e-6, false));
    for (n, v) in loaded.model.vae_vs.variables() {
        assert!(v.equal(&fresh.model.vae_vs.variables()[&n]), "{n}");
    }
    c.model.transformer = Some("small2x-wide".into());
    let e = Trainer::new(c).unwrap_err().to_string();
    assert!(
        e.contains("learned positional embedding") && e.contains("32x48"),
        "{e}"
    );

    // Fine-tuning from the prior loads it (the paper's pipeline).
    let mut c = config(&tmp.path().join("ft"));
    c.model.backbone = prior.display().to_string();
    (c.data.frames, c.data.height, c.data.width) = (9, 64, 96);
    c.train.max_steps = 1;
    // ... with the prior's image conditioning, which its folder records.
    let e = Trainer::new(c.clone()).unwrap_err().to_string();
    assert!(
        e.contains("model.image_conditioning") && e.contains("every_frame"),
        "{e}"
    );
    c.model.image_conditioning = ImageConditioning::EveryFrame;
    let mut t = Trainer::new(c).unwrap();
    assert_trains_only(&t, "adapters.");
    t.run(&mut |_| {}).unwrap();
}

/// `evaluate_split` scores a run's predictions next to the copy-the-first-frame
/// baseline, for the mask-conditioned model and the action-MLP ablation;
/// predictions are deterministic for a seed.
#[test]
fn evaluation_scores_mask_and_action_models_against_the_baseline() {
    use bridgev2w_train::evaluate::{color_segmenter, evaluate_split, EvalOptions};
    use bridgev2w_train::segmenter::{CnnSegmenter, SegmenterOptions};
    let _g = lock();
    let tmp = tempfile::tempdir().unwrap();
    let opts = EvalOptions {
        steps: 2,
        guidance: 1.0,
        seed: 3,
        max_videos: 1,
        ..EvalOptions::default()
    };
    for mask_action in [true, false] {
        let mut c = config(tmp.path());
        c.ablation.mask_action = mask_action;
        let t = Trainer::new(c).unwrap();
        let seg = color_segmenter(&t.data).unwrap().unwrap();
        let s = evaluate_split(&t, "unseen_camera", &opts, Some(&seg), &|| {}).unwrap();
        assert_eq!((s.split.as_str(), s.videos), ("unseen_camera", 1));
        // The segmenter reads the robot off real frames well; the copied
        // first frame's robot overlaps the moving robot less.
        let (iou, base, ceiling) = (
            s.mask_iou.unwrap(),
            s.baseline_mask_iou.unwrap(),
            s.segmenter_mask_iou.unwrap(),
        );
        eprintln!("Mask-IoU {iou} baseline {base} ceiling {ceiling}");
        assert!((0.0..=1.0).contains(&iou), "{s:?}");
        assert!(ceiling > 0.4 && ceiling > base, "{s:?}");
        let no_seg = evaluate_split(&t, "unseen_camera", &opts, None, &|| {}).unwrap();
        assert_eq!(no_seg.mask_iou, None);
        assert_eq!((no_seg.psnr, no_seg.ssim), (s.psnr, s.ssim));
        if mask_action {
            // The learned segmenter plugs in the same way (its advantage over
            // colour is tested in the segmenter's unit test).
            let quick = SegmenterOptions {
                steps: 100,
                batch: 4,
                ..SegmenterOptions::default()
            };
            let cnn = CnnSegmenter::fit(&t.data, &quick).unwrap().unwrap();
            let c = evaluate_split(&t, "unseen_camera", &opts, Some(&cnn), &|| {}).unwrap();
            let cnn_ceiling = c.segmenter_mask_iou.unwrap();
            eprintln!(
                "CNN segmenter ceiling {cnn_ceiling} (BCE {})",
                cnn.final_loss
            );
            assert!(cnn_ceiling > 0.0 && cnn_ceiling <= 1.0, "{c:?}");
        }
        for v in [s.psnr, s.baseline_psnr, s.autoencoder_psnr] {
            assert!(v.is_finite() && v > 0.0 && v < 100.0, "{s:?}");
        }
        assert!(
            s.autoencoder_ssim > -1.0 && s.autoencoder_ssim <= 1.0,
            "{s:?}"
        );
        assert!(
            s.ssim > -1.0 && s.ssim <= 1.0 && s.baseline_ssim > 0.0,
            "{s:?}"
        );
        let b = t.batch(0).unwrap();
        let sample = |seed| SampleOptions {
            steps: 2,
            guidance_scale: 1.0,
            seed,
            ..SampleOptions::default()
        };
        let (p1, p2) = (
            t.predict(&b, &sample(9)).unwrap(),
            t.predict(&b, &sample(9)).unwrap(),
        );
        assert_eq!(p1.size(), b.video.size());
        assert!(p1.equal(&p2), "same seed, same prediction");
        let p3 = t.predict(&b, &sample(10)).unwrap();
        assert!(!p1.equal(&p3), "another seed, another sample");
    }
    let err = evaluate_split(
        &Trainer::new(config(tmp.path())).unwrap(),
        "nope",
        &opts,
        None,
        &|| {},
    )
    .unwrap_err();
    assert!(
        err.to_string().contains("no episodes in split \"nope\""),
        "{err}"
    );
}

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

#[test]
fn link_coded_masks_train_from_the_datasets_labels_and_need_them() {
    use bridgev2w_world_model::bridge::MaskCoding;
    let _g = lock();
    let tmp = tempfile::tempdir().unwrap();
    let mut c = config(&tmp.path().join("run"));
    c.model.mask_coding = MaskCoding::Links;
    let t = Trainer::new(c.clone()).unwrap();
    assert_eq!(t.model.config().mask_coding, MaskCoding::Links);
    let batch = t.batch(0).unwrap();
    // Channel 0 is the silhouette (+-1); channel 1 codes the link, so robot
    // pixels take values strictly between -1 and 1 as well.
    let silhouette = batch.masks.select(1, 0);
    assert_eq!(silhouette.abs().min().double_value(&[]), 1.0);
    let ramp = batch.masks.select(1, 1);
    let inside = ramp.gt(-0.99).logical_and(&ramp.lt(0.99));
    assert!(inside.any().int64_value(&[]) == 1, "no link-coded pixel");
    // A dataset without labels/ is refused by name.
    let copy = tmp.path().join("nolabels");
    copy_dir(dataset(), &copy);
    std::fs::remove_dir_all(copy.join("labels")).unwrap();
    c.data.dataset = copy;
    c.train.out = tmp.path().join("run2");
    let e = Trainer::new(c)
        .err()
        .map(|e| e.to_string())
        .unwrap_or_default();
    assert!(
        e.contains("labels/episode_") && e.contains("mask_coding"),
        "{e}"
    );
}

/// `model.vae_tile`: the clips' encoding and the flow loss's decode run in
/// tiles of that size (the backward, plain and checkpointed, replaying one
/// tile at a time), with gradients into the branch; tiles that would not
/// join, a size that is not `HxW` and the vae stage are refused by name.
#[test]
fn vae_tile_tiles_the_encoding_and_the_flow_loss_decode() {
    let _g = lock();
    let tmp = tempfile::tempdir().unwrap();
    let mut c = config(tmp.path());
    c.train.e_switch = 0;
    c.train.condition_dropout = 0.0;
    let losses = |c: TrainConfig| -> (f64, f64, f64, Option<(i64, i64)>) {
        let t = Trainer::new(c).unwrap();
        let tiling = t.model.vae.tiling();
        let tiled = t
            .model
            .vae
            .uses_tiling()
            .then_some((tiling.tile_sample_min_height, tiling.tile_sample_min_width));
        let l = t.losses(&t.batch(0).unwrap(), 0).unwrap();
        l.total.backward();
        if let Some(record) = l.checkpointed {
            record.backward(&t.model.transformer.model).unwrap();
        }
        (l.diffusion, l.flow, controlnet_grad_sum(&t), tiled)
    };
    // 64x96 frames: whole frames by default (below 256x256).
    let (diffusion, flow, grad, tiled) = losses(c.clone());
    assert_eq!(tiled, None);
    // Latent tiles of 6x5 (48x40 px) over the 8x12 latents: 2 x 3 tiles.
    c.model.vae_tile = Some("48x40".parse().unwrap());
    for checkpointing in [false, true] {
        c.train.gradient_checkpointing = checkpointing;
        let (tiled_diffusion, tiled_flow, tiled_grad, tiled) = losses(c.clone());
        assert_eq!(tiled, Some((48, 40)));
        assert!(
            tiled_flow.is_finite() && tiled_flow > 0.0 && tiled_grad > 0.0,
            "checkpointing {checkpointing}: flow {tiled_flow}, branch gradient {tiled_grad}"
        );
        // The tiles are blended: another encoding and decoding than whole frames.
        assert!(
            (tiled_diffusion - diffusion).abs() > 1e-9 && (tiled_flow - flow).abs() > 1e-9,
            "tiled {tiled_diffusion} / {tiled_flow} vs whole frames {diffusion} / {flow}"
        );
        assert!(grad > 0.0);
    }
    // Tiles that would not join: refused when the model is built.
    c.model.vae_tile = Some("64x96".parse().unwrap());
    let e = Trainer::new(c.clone()).unwrap_err().to_string();
    assert!(
        e.contains("model.vae_tile") && e.contains("64x96") && e.contains("would not join"),
        "{e}"
    );
    // In a config file: parsed as HxW; anything else, and the vae stage, refused.
    let toml = |tile: &str, stage: &str| {
        format!(
            "[model]\nvae_tile = \"{tile}\"\n[data]\ndataset = \"d\"\n[train]\nstage = \"{stage}\"\n"
        )
    };
    let parsed = TrainConfig::from_toml(&toml("144x200", "bridgev2w")).unwrap();
    assert_eq!(
        parsed.model.vae_tile.map(|t| t.to_string()).as_deref(),
        Some("144x200")
    );
    let back = TrainConfig::from_toml(&parsed.to_toml().unwrap()).unwrap();
    assert_eq!(back.model.vae_tile, parsed.model.vae_tile);
    for bad in ["144", "144x", "0x200", "ax200"] {
        let e = TrainConfig::from_toml(&toml(bad, "bridgev2w"))
            .unwrap_err()
            .to_string();
        assert!(e.contains(bad) && e.contains("HEIGHTxWIDTH"), "{bad}: {e}");
    }
    let e = TrainConfig::from_toml(&toml("144x200", "vae"))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("model.vae_tile") && e.contains("vae stage"),
        "{e}"
    );
}
