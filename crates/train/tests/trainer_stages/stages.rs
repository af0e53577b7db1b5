//! The stages and losses beyond the paper's fine-tuning: RAFT's flow loss,
//! the VAE and prior stages, the evaluation, and VAE tiles.

use crate::common::{assert_trains_only, config, controlnet_grad_sum, lock};
use bridgev2w_train::config::{Stage, TrainConfig, VaeParts};
use bridgev2w_train::trainer::Trainer;
use bridgev2w_world_model::bridge::ImageConditioning;
use bridgev2w_world_model::pipeline::SampleOptions;
use std::path::Path;

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
