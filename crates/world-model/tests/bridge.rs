//! The BridgeV2W model: the ControlNet identity with zero projections, the branch
//! initialised from the backbone, weights files, gradients (and their
//! checkpointing) and the image conditioning. Prediction through the
//! `WorldModel` contract: `bridge_predict.rs`.

#![allow(clippy::unwrap_used)]

mod bridge_common;

use bridge_common::*;
use bridgev2w_world_model::bridge::{BridgeV2W, BridgeV2WConfig, ImageConditioning};
use bridgev2w_world_model::controlnet::ControlNetConfig;
use bridgev2w_world_model::scheduler::SchedulerConfig;
use bridgev2w_world_model::transformer::TransformerConfig;
use bridgev2w_world_model::vae::VaeConfig;
use bridgev2w_world_model::{ComputeDevice, Precision};
use tch::{Device, Kind, Tensor};

#[test]
fn zero_projections_and_fresh_lora_leave_the_backbone_exactly() {
    let _rng = rng_lock();
    let m = tiny(BridgeV2WConfig::tiny(), 1);
    let (x, c, t) = inputs(2);
    let with_branch = m.velocity_with(&x, &t, Some(&c)).unwrap();
    let without = m.velocity_with(&x, &t, None).unwrap();
    assert_eq!(with_branch.size(), [1, 3, 4, 8, 12]);
    assert_eq!(max_abs(&with_branch, &without), 0.0);
    // And equal to a plain backbone without adapters (same seed, same init order).
    let text = Tensor::zeros([1, 8, 24], (Kind::Float, Device::Cpu));
    let plain = bridgev2w_world_model::transformer::LoadedTransformer::random(
        &TransformerConfig::tiny(),
        ComputeDevice::Cpu,
        Precision::F32,
    )
    .unwrap();
    tch::no_grad(|| {
        let src = m.transformer.vs.variables();
        for (name, mut v) in plain.vs.variables() {
            v.copy_(&src[&name]);
        }
    });
    let rotary = plain.model.rotary_for(&x).unwrap();
    let base = plain
        .model
        .forward(&x, &text, &t, rotary.as_ref(), None)
        .unwrap();
    assert_eq!(max_abs(&with_branch, &base), 0.0);
}

#[test]
fn branch_starts_as_a_copy_of_the_backbone_and_changes_the_output_when_trained() {
    let _rng = rng_lock();
    let m = tiny(BridgeV2WConfig::tiny(), 3);
    let base = m.transformer.vs.variables();
    let branch = m.adapters.variables();
    let mut copied = 0;
    for (name, v) in &branch {
        let Some(rest) = name.strip_prefix("controlnet.") else {
            continue;
        };
        if rest.starts_with("out_projectors") {
            assert_eq!(v.abs().sum(Kind::Double).double_value(&[]), 0.0, "{name}");
            continue;
        }
        assert_eq!(max_abs(v, &base[rest]), 0.0, "{name}");
        copied += 1;
    }
    // patch_embed (proj w+b, text_proj w+b, pos_embedding) + one block's tensors.
    assert!(copied > 10, "{copied}");
    assert!(!branch
        .keys()
        .any(|k| k.starts_with("controlnet.transformer_blocks.1.")));
    perturb_projections(&m);
    let (x, c, t) = inputs(4);
    let a = m.velocity_with(&x, &t, Some(&c)).unwrap();
    let b = m.velocity_with(&x, &t, None).unwrap();
    assert!(max_abs(&a, &b) > 1e-4);
    // Another control input gives another prediction.
    let c2 = Tensor::randn_like(&c);
    let a2 = m.velocity_with(&x, &t, Some(&c2)).unwrap();
    assert!(max_abs(&a, &a2) > 1e-5);
}

#[test]
fn per_block_weights_scale_the_residuals() {
    let _rng = rng_lock();
    let mut cfg = BridgeV2WConfig::tiny();
    cfg.controlnet = ControlNetConfig {
        num_layers: 2,
        conditioning_scale: vec![0.0, 0.0],
        zero_init: true,
    };
    let m = tiny(cfg.clone(), 5);
    perturb_projections(&m);
    let (x, c, t) = inputs(6);
    let off = m.velocity_with(&x, &t, Some(&c)).unwrap();
    let base = m.velocity_with(&x, &t, None).unwrap();
    assert_eq!(max_abs(&off, &base), 0.0, "weights 0 switch the branch off");
    cfg.controlnet.conditioning_scale = vec![1.0, 0.0];
    let bad = BridgeV2W::random(
        BridgeV2WConfig {
            controlnet: ControlNetConfig {
                conditioning_scale: vec![1.0],
                ..cfg.controlnet.clone()
            },
            ..cfg.clone()
        },
        &VaeConfig::tiny(),
        &TransformerConfig::tiny(),
        SchedulerConfig::cogvideox_5b_i2v(),
        ComputeDevice::Cpu,
        0,
    )
    .unwrap_err()
    .to_string();
    assert!(
        bad.contains("conditioning_scale") && bad.contains("1 weights for 2 blocks"),
        "{bad}"
    );
    let too_many = BridgeV2W::random(
        BridgeV2WConfig {
            controlnet: ControlNetConfig::with_layers(3),
            ..cfg
        },
        &VaeConfig::tiny(),
        &TransformerConfig::tiny(),
        SchedulerConfig::cogvideox_5b_i2v(),
        ComputeDevice::Cpu,
        0,
    )
    .unwrap_err()
    .to_string();
    assert!(too_many.contains("expected 1..=2"), "{too_many}");
    // 5 frames = 2 latent frames: the causal VAE would decode 8.
    for (frames, ok) in [(5, false), (13, false), (9, true), (17, true), (6, false)] {
        let r = BridgeV2WConfig {
            frames,
            ..cfg.clone()
        }
        .validate(&VaeConfig::tiny(), &TransformerConfig::tiny());
        assert_eq!(r.is_ok(), ok, "{frames} frames: {r:?}");
        if frames == 5 {
            let e = r.unwrap_err().to_string();
            assert!(
                e.contains("decodes to 8 frames") && e.contains("8k + 1"),
                "{e}"
            );
        }
    }
}

#[test]
fn non_zero_initialised_branch_is_the_ablation() {
    let _rng = rng_lock();
    let mut cfg = BridgeV2WConfig::tiny();
    cfg.controlnet.zero_init = false;
    let m = tiny(cfg, 7);
    let (x, c, t) = inputs(8);
    let a = m.velocity_with(&x, &t, Some(&c)).unwrap();
    let b = m.velocity_with(&x, &t, None).unwrap();
    assert!(max_abs(&a, &b) > 1e-4);
}

#[test]
fn gradients_reach_the_branch_and_lora_only() {
    let _rng = rng_lock();
    let m = tiny(BridgeV2WConfig::tiny(), 9);
    let (x, c, t) = inputs(10);
    let v = m.velocity_with(&x, &t, Some(&c)).unwrap();
    v.square().mean(Kind::Float).backward();
    let vars = m.adapters.variables();
    let grad_norm = |k: &str| vars[k].grad().abs().sum(Kind::Double).double_value(&[]);
    // Zero projections get gradients (their inputs are non-zero) ...
    assert!(grad_norm("controlnet.out_projectors.0.weight") > 0.0);
    // ... and LoRA B does (A is random), while the frozen backbone has none.
    assert!(grad_norm("transformer.transformer_blocks.0.attn1.to_q.lora_B.weight") > 0.0);
    for (name, v) in m.transformer.vs.variables() {
        assert!(!v.requires_grad(), "{name} should be frozen");
    }
}

#[test]
fn weights_file_round_trip_with_config_and_strict_loading() {
    let _rng = rng_lock();
    let mut cfg = BridgeV2WConfig::tiny();
    cfg.controlnet.conditioning_scale = vec![0.5];
    let m = tiny(cfg.clone(), 11);
    perturb_projections(&m);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bridgev2w.safetensors");
    m.save_weights(&path).unwrap();
    assert_eq!(BridgeV2W::weights_config(&path).unwrap(), Some(cfg.clone()));
    let other = tiny(cfg.clone(), 12);
    other.load_weights(&path).unwrap();
    for (name, v) in m.adapters.variables() {
        assert_eq!(
            max_abs(&v, &other.adapters.variables()[&name]),
            0.0,
            "{name}"
        );
    }
    // A file from a model with another branch depth is rejected, naming a key.
    let mut deeper = cfg;
    deeper.controlnet = ControlNetConfig::with_layers(2);
    let err = tiny(deeper, 13)
        .load_weights(&path)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("missing weight `controlnet.") && err.contains(".1."),
        "{err}"
    );
    // Not a safetensors file.
    std::fs::write(dir.path().join("bad.safetensors"), b"\x05\0\0\0\0\0\0\0{").unwrap();
    let err = BridgeV2W::weights_config(&dir.path().join("bad.safetensors"))
        .unwrap_err()
        .to_string();
    assert!(err.contains("bad.safetensors"), "{err}");
    // A truncated file: the tensor and the byte range in words, no library code.
    let bytes = std::fs::read(&path).unwrap();
    let cut = dir.path().join("cut.safetensors");
    std::fs::write(&cut, &bytes[..bytes.len() - 16]).unwrap();
    let err = other.load_weights(&cut).unwrap_err().to_string();
    assert!(
        err.contains("cut.safetensors")
            && err.contains("lie outside")
            && !err.contains("InvalidOffset"),
        "{err}"
    );
    // NaN weights are refused when loaded, naming the file and the tensor.
    let (name, v) = m.adapters.variables().into_iter().next().unwrap();
    let _ = tch::no_grad(|| v.shallow_clone().fill_(f64::NAN));
    let nan = dir.path().join("nan.safetensors");
    m.save_weights(&nan).unwrap();
    let err = other.load_weights(&nan).unwrap_err().to_string();
    assert!(
        err.contains("nan.safetensors")
            && err.contains(&format!("`{name}`"))
            && err.contains("NaN"),
        "{err}"
    );
}

#[test]
fn per_block_gradient_checkpointing_gives_the_same_gradients() {
    let _rng = rng_lock();
    let m = tiny(BridgeV2WConfig::tiny(), 21);
    // Non-zero projections and LoRA B, so every path carries gradient.
    tch::no_grad(|| {
        for (name, mut v) in m.adapters.variables() {
            if name.contains("out_projectors") || name.contains("lora_B") {
                v.copy_(&(Tensor::randn_like(&v) * 0.05));
            }
        }
    });
    let (x, c, t) = inputs(22);
    let d = TransformerConfig::tiny().inner_dim();
    let extra = Tensor::randn([1, 1, d], (Kind::Float, Device::Cpu)) * 0.1;
    let weight = Tensor::randn([1, 3, 4, 8, 12], (Kind::Float, Device::Cpu));
    let loss = |v: &Tensor| (v * &weight).square().mean(Kind::Float);
    let vars = m.adapters.variables();
    let copy = |g: Tensor| g.defined().then(|| g.copy());
    let grads = |e: &Tensor| -> Vec<(String, Option<Tensor>)> {
        let mut g: Vec<(String, Option<Tensor>)> = vars
            .iter()
            .map(|(k, v)| (k.clone(), copy(v.grad())))
            .collect();
        g.push(("extra".into(), copy(e.grad())));
        g
    };
    let zero = || {
        tch::no_grad(|| {
            for v in vars.values() {
                let mut g = v.grad();
                if g.defined() {
                    let _ = g.zero_();
                }
            }
        })
    };
    // Plain backward.
    zero();
    let e1 = extra.detach().set_requires_grad(true);
    let v1 = m
        .velocity_with_extra(&x, &t, Some(&c), std::slice::from_ref(&e1))
        .unwrap();
    loss(&v1).backward();
    let plain = grads(&e1);
    // Checkpointed.
    zero();
    let e2 = extra.detach().set_requires_grad(true);
    let (v2, record) = m
        .velocity_checkpointed(&x, &t, Some(&c), std::slice::from_ref(&e2))
        .unwrap();
    assert!(max_abs(&v1, &v2) < 1e-6, "outputs differ");
    assert!(v2.requires_grad() && v2.is_leaf());
    loss(&v2).backward();
    record.backward(&m.transformer.model).unwrap();
    let checkpointed = grads(&e2);
    let mut nonzero = 0;
    for ((name, a), (_, b)) in plain.iter().zip(&checkpointed) {
        let (a, b) = match (a, b) {
            (Some(a), Some(b)) => (a, b),
            (None, None) => continue,
            _ => panic!("{name}: gradient defined in one run only"),
        };
        let scale = a.abs().max().double_value(&[]);
        nonzero += usize::from(scale > 0.0);
        let diff = max_abs(a, b);
        assert!(
            diff <= 1e-5 * (1.0 + scale),
            "{name}: {diff} (scale {scale})"
        );
    }
    // Branch, LoRA A and B of every block, and the extra residual.
    assert!(nonzero >= 4, "{nonzero} non-zero gradients");
    assert!(checkpointed.iter().any(|(n, g)| n.contains("lora_A")
        && g.as_ref()
            .is_some_and(|g| g.abs().max().double_value(&[]) > 0.0)));
    assert!(checkpointed
        .iter()
        .any(|(n, g)| n == "extra" && g.is_some()));
    // More extra residuals than backbone blocks: the same clear error on both paths.
    let layers = TransformerConfig::tiny().num_layers as usize;
    let too_many: Vec<Tensor> = (0..=layers).map(|_| extra.shallow_clone()).collect();
    let e = m
        .velocity_with_extra(&x, &t, Some(&c), &too_many)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains(&format!(
            "{} residuals for {layers} backbone blocks",
            layers + 1
        )),
        "{e}"
    );
    let e = m
        .velocity_checkpointed(&x, &t, Some(&c), &too_many)
        .unwrap_err()
        .to_string();
    assert!(e.contains("backbone blocks"), "{e}");
    // A RoPE backbone without its rotary table: the same error as the plain forward.
    let text = Tensor::zeros([1, 3, 24], (Kind::Float, Device::Cpu));
    let tf = &m.transformer.model;
    let e = tf
        .forward_checkpointed(&x, &text, &t, None, None, vec![])
        .unwrap_err()
        .to_string();
    assert!(e.contains("rotary embeddings"), "{e}");
    let plain = tf
        .forward(&x, &text, &t, None, None)
        .unwrap_err()
        .to_string();
    assert_eq!(e, plain);
}

#[test]
fn image_conditioning_pads_or_repeats_and_travels_with_the_backbone() {
    let _rng = rng_lock();
    let every = BridgeV2WConfig {
        image_conditioning: ImageConditioning::EveryFrame,
        ..BridgeV2WConfig::tiny()
    };
    let first = tiny(BridgeV2WConfig::tiny(), 21);
    let m = tiny(every.clone(), 21);
    tch::manual_seed(22);
    let img = Tensor::rand([2, 3, 64, 96], (Kind::Float, Device::Cpu)) * 2.0 - 1.0;
    let a = first.image_latents(&img, None).unwrap(); // [2, 3, 8, 8, 12]
    let b = m.image_latents(&img, None).unwrap();
    assert_eq!(a.size(), b.size());
    let t = a.size()[1];
    assert!(a.narrow(1, 0, 1).abs().max().double_value(&[]) > 0.0);
    assert_eq!(a.narrow(1, 1, t - 1).abs().max().double_value(&[]), 0.0);
    for i in 0..t {
        assert_eq!(
            max_abs(&b.narrow(1, i, 1), &a.narrow(1, 0, 1)),
            0.0,
            "frame {i}"
        );
    }
    // The folder records the deviation; loading it alone adopts it, and a
    // weights file that disagrees is refused by name.
    let dir = tempfile::tempdir().unwrap();
    let folder = dir.path().join("prior");
    m.save_backbone(&folder).unwrap();
    let index = std::fs::read_to_string(folder.join("model_index.json")).unwrap();
    assert!(
        index.contains("\"_bridgev2w_image_conditioning\": \"every_frame\""),
        "{index}"
    );
    let load = |w: Option<&std::path::Path>| {
        BridgeV2W::load(
            &folder,
            w,
            None,
            BridgeV2WConfig::tiny(),
            ComputeDevice::Cpu,
            Precision::F32,
        )
    };
    let loaded = load(None).unwrap();
    assert_eq!(
        loaded.config().image_conditioning,
        ImageConditioning::EveryFrame
    );
    let weights = dir.path().join("first.safetensors");
    first.save_weights(&weights).unwrap();
    let e = load(Some(&weights)).unwrap_err().to_string();
    assert!(
        e.contains("image_conditioning") && e.contains("every_frame") && e.contains("first_frame"),
        "{e}"
    );
    // A first-frame backbone records nothing (diffusers' own folders).
    first.save_backbone(&dir.path().join("cog")).unwrap();
    let index = std::fs::read_to_string(dir.path().join("cog/model_index.json")).unwrap();
    assert!(!index.contains("image_conditioning"), "{index}");
    assert_eq!(
        "every_frame".parse::<ImageConditioning>().unwrap(),
        ImageConditioning::EveryFrame
    );
    let e = "repeat"
        .parse::<ImageConditioning>()
        .unwrap_err()
        .to_string();
    assert!(e.contains("first_frame, every_frame"), "{e}");
}
