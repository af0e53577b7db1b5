//! `lora_export`: a tiny BridgeV2W's LoRA (non-zero `lora_B`, alpha != rank)
//! exported in diffusers' layout, loaded by diffusers' `load_lora_weights` into
//! the same transformer (`scripts/parity/lora_diffusers.py`): its output equals
//! ours with the adapters, and differs from the output without them.

#![allow(clippy::unwrap_used)]

use crate::common;

use bridgev2w_world_model::bridge::{BridgeV2W, BridgeV2WConfig};
use bridgev2w_world_model::lora::LoraConfig;
use bridgev2w_world_model::lora_export::{export_lora, export_lora_file, DIFFUSERS_LORA_FILE};
use bridgev2w_world_model::scheduler::SchedulerConfig;
use bridgev2w_world_model::transformer::{LoadedTransformer, TransformerConfig};
use bridgev2w_world_model::vae::VaeConfig;
use bridgev2w_world_model::weights::{read_safetensors, read_safetensors_metadata};
use bridgev2w_world_model::{ComputeDevice, Precision};
use std::path::Path;
use std::process::Command;
use tch::{Device, Kind, Tensor};

const RANK: i64 = 4;
const ALPHA: f64 = 6.0;

fn tiny_model_with_trained_lora() -> BridgeV2W {
    let cfg = BridgeV2WConfig {
        lora: Some(LoraConfig {
            rank: RANK,
            alpha: ALPHA,
        }),
        ..BridgeV2WConfig::tiny()
    };
    let model = BridgeV2W::random(
        cfg,
        &VaeConfig::tiny(),
        &TransformerConfig::tiny(),
        SchedulerConfig::cogvideox_5b_i2v(),
        ComputeDevice::Cpu,
        3,
    )
    .unwrap();
    // A fresh adapter has B = 0 (no effect): give every B random values.
    tch::no_grad(|| {
        for (k, mut v) in model.adapters.variables() {
            if k.ends_with("lora_B.weight") {
                v.copy_(&(Tensor::randn_like(&v) * 0.2));
            }
        }
    });
    model
}

fn max_abs(a: &Tensor, b: &Tensor) -> f64 {
    assert_eq!(a.size(), b.size());
    (a - b).abs().max().double_value(&[])
}

/// Whether the venv's python has diffusers (the test is skipped without it).
fn has_diffusers(python: &Path) -> bool {
    Command::new(python)
        .args(["-c", "import diffusers"])
        .status()
        .is_ok_and(|s| s.success())
}

#[test]
fn diffusers_load_lora_weights_reproduces_our_lora_forward() {
    let python = common::venv_python();
    if !has_diffusers(&python) {
        eprintln!(
            "SKIPPED: {} cannot import diffusers; run scripts/setup-venv.sh",
            python.display()
        );
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let (backbone, weights) = (
        tmp.path().join("backbone"),
        tmp.path().join("bw.safetensors"),
    );
    let model = tiny_model_with_trained_lora();
    model.save_backbone(&backbone).unwrap();
    model.save_weights(&weights).unwrap();

    // From the weights file (the CLI's path) and from the model in memory: the same tensors.
    let out = tmp.path().join("lora");
    let e = export_lora_file(&weights, &backbone, &out, false).unwrap();
    let layers = 4 * TransformerConfig::tiny().num_layers as usize;
    assert_eq!((e.layers, e.rank, e.alpha), (layers, RANK, ALPHA));
    assert_eq!(e.path, out.join(DIFFUSERS_LORA_FILE));
    let from_memory = tmp.path().join("lora-mem");
    export_lora(&model, &from_memory, false).unwrap();
    let sorted = |p: &Path| {
        let mut v = read_safetensors(p).unwrap();
        v.sort_by(|a, b| a.0.cmp(&b.0));
        v
    };
    let file = sorted(&e.path);
    let mem = sorted(&from_memory.join(DIFFUSERS_LORA_FILE));
    assert_eq!(file.len(), 2 * layers);
    for ((k1, t1), (k2, t2)) in file.iter().zip(&mem) {
        assert_eq!(k1, k2);
        assert!(t1.equal(t2), "{k1}");
    }
    assert_eq!(
        read_safetensors_metadata(&e.path).unwrap().get("format"),
        Some(&"pt".to_owned())
    );
    // lora_B carries alpha / rank; lora_A is as trained.
    let vars = model.adapters.variables();
    let key = "transformer.transformer_blocks.1.attn1.to_out.0.lora_B.weight";
    let exported = &file.iter().find(|(k, _)| k == key).unwrap().1;
    assert!(exported.allclose(&(&vars[key] * (ALPHA / RANK as f64)), 1e-6, 1e-7, false));
    assert!(file.iter().all(|(k, _)| k.starts_with("transformer.")));

    // An existing file is refused unless overwrite.
    let err = export_lora_file(&weights, &backbone, &out, false)
        .unwrap_err()
        .to_string();
    assert!(err.contains("--overwrite"), "{err}");
    export_lora_file(&weights, &backbone, &out, true).unwrap();

    // Ours: the backbone with and without the adapters, on fixed inputs.
    let tf = TransformerConfig::tiny();
    tch::manual_seed(11);
    let opts = (Kind::Float, Device::Cpu);
    let x = Tensor::randn(
        [2, 3, tf.in_channels, tf.sample_height, tf.sample_width],
        opts,
    );
    let text = Tensor::randn([2, tf.max_text_seq_length, tf.text_embed_dim], opts);
    let t = Tensor::from_slice(&[17i64, 640]);
    let ours_lora = tch::no_grad(|| {
        let m = &model.transformer.model;
        let rot = m.rotary_for(&x).unwrap();
        m.forward(&x, &text, &t, rot.as_ref(), None).unwrap()
    });
    let plain = LoadedTransformer::load(
        &backbone.join("transformer"),
        ComputeDevice::Cpu,
        Precision::F32,
    )
    .unwrap();
    let rot = plain.model.rotary_for(&x).unwrap().unwrap();
    let ours_base = tch::no_grad(|| {
        plain
            .model
            .forward(&x, &text, &t, Some(&rot), None)
            .unwrap()
    });

    // diffusers: the same backbone folder, before and after load_lora_weights.
    let inputs = tmp.path().join("inputs.safetensors");
    Tensor::write_safetensors(
        &[
            ("hidden_states", &x),
            ("encoder_hidden_states", &text),
            ("timestep", &t),
            ("rope_cos", &rot.cos),
            ("rope_sin", &rot.sin),
        ],
        &inputs,
    )
    .unwrap();
    let result = tmp.path().join("diffusers.safetensors");
    let run = Command::new(&python)
        .arg(common::repo_root().join("scripts/parity/lora_diffusers.py"))
        .arg("--backbone")
        .arg(&backbone)
        .arg("--lora")
        .arg(&out)
        .arg("--inputs")
        .arg(&inputs)
        .arg("--out")
        .arg(&result)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(
        run.status.success(),
        "lora_diffusers.py failed (diffusers' LoRA loading also needs peft, pinned in scripts/requirements-lock.txt: run scripts/setup-venv.sh):\n{stderr}"
    );
    let info: serde_json::Value = serde_json::from_slice(&run.stdout).unwrap();
    assert_eq!(info["lora_layers"].as_u64(), Some(layers as u64), "{info}");
    assert_eq!(info["r"].as_i64(), Some(RANK), "{info}");
    assert_eq!(info["lora_alpha"].as_f64(), Some(RANK as f64), "{info}");
    let got: std::collections::HashMap<String, Tensor> =
        read_safetensors(&result).unwrap().into_iter().collect();

    let base_diff = max_abs(&got["sample_base"], &ours_base);
    let lora_diff = max_abs(&got["sample_lora"], &ours_lora);
    let effect = max_abs(&ours_lora, &ours_base);
    eprintln!(
        "max |diffusers - ours|: without LoRA {base_diff:.3e}, with LoRA {lora_diff:.3e}; LoRA effect {effect:.3e}"
    );
    assert!(base_diff < 1e-4, "backbone: {base_diff:e}");
    assert!(lora_diff < 1e-4, "with LoRA: {lora_diff:e}");
    assert!(
        effect > 1e-2,
        "the LoRA barely changes the output: {effect:e}"
    );
}

/// An output file that is the weights file, or lies inside the backbone
/// folder, is refused before anything is read or written (issue 69).
#[test]
fn an_output_overlapping_an_input_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let (backbone, out) = (tmp.path().join("backbone"), tmp.path().join("lora"));
    std::fs::create_dir_all(&backbone).unwrap();
    std::fs::create_dir_all(&out).unwrap();
    let weights = out.join(DIFFUSERS_LORA_FILE);
    std::fs::write(&weights, "the user's weights").unwrap();
    for (dir, how) in [(&out, "is the input"), (&backbone, "is inside the input")] {
        let err = export_lora_file(&weights, &backbone, dir, true)
            .unwrap_err()
            .to_string();
        assert!(err.contains("--out") && err.contains(how), "{err}");
    }
    assert_eq!(
        std::fs::read_to_string(&weights).unwrap(),
        "the user's weights"
    );
    assert_eq!(std::fs::read_dir(&backbone).unwrap().count(), 0);
}

#[test]
fn a_backbone_of_another_depth_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let model = tiny_model_with_trained_lora();
    let weights = tmp.path().join("bw.safetensors");
    model.save_weights(&weights).unwrap();
    let other = BridgeV2W::random(
        BridgeV2WConfig::tiny(),
        &VaeConfig::tiny(),
        &TransformerConfig {
            num_layers: 3,
            ..TransformerConfig::tiny()
        },
        SchedulerConfig::cogvideox_5b_i2v(),
        ComputeDevice::Cpu,
        0,
    )
    .unwrap();
    other.save_backbone(&tmp.path().join("deeper")).unwrap();
    let out = tmp.path().join("lora");
    let err = export_lora_file(&weights, &tmp.path().join("deeper"), &out, false)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("transformer_blocks.2.attn1") && err.contains("3 blocks"),
        "{err}"
    );
    assert!(!out.join(DIFFUSERS_LORA_FILE).exists());
}
