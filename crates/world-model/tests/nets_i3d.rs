//! I3D (the FVD feature network) against an independent torch implementation
//! written in the fixture script, with the same random weights.

#![allow(clippy::unwrap_used)]

use crate::common;

use bridgev2w_world_model::nets::i3d::{I3d, NUM_CLASSES};
use bridgev2w_world_model::parity::{run_fixture, DEFAULT_TOLERANCE};
use bridgev2w_world_model::weights::resolve_weight_files;
use bridgev2w_world_model::ComputeDevice;
use tch::{Kind, Tensor};

fn fixture() -> std::path::PathBuf {
    common::fixture("i3d", &["i3d", "--frames", "16", "--batch", "1"])
}

#[test]
fn matches_the_torch_reference_and_counts_its_parameters() {
    let dir = fixture();
    let report = run_fixture(&dir).unwrap();
    assert_eq!(report.outputs.len(), 1);
    let o = &report.outputs[0];
    assert_eq!(o.shape, vec![1, NUM_CLASSES]);
    eprintln!(
        "I3D logits: max abs {:e}, max rel {:e}",
        o.max_abs, o.max_rel
    );
    assert!(
        o.max_rel <= DEFAULT_TOLERANCE,
        "logits: rel {:e} abs {:e}",
        o.max_rel,
        o.max_abs
    );
    // The reference logits differ between classes (not a degenerate constant).
    let io = bridgev2w_world_model::parity::FixtureIo::read(&dir.join("io.safetensors")).unwrap();
    let want = io.get("logits").unwrap();
    assert!(want.std(true).double_value(&[]) > 1e-3);
    let meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("meta.json")).unwrap()).unwrap();
    let net = I3d::load(
        &resolve_weight_files(&dir.join("model"), "i3d").unwrap(),
        ComputeDevice::Cpu,
    )
    .unwrap();
    let trainable: i64 = net
        .var_store()
        .variables()
        .iter()
        .filter(|(k, _)| !k.contains("running_"))
        .map(|(_, v)| v.numel() as i64)
        .sum();
    assert_eq!(trainable, meta["parameters"].as_i64().unwrap());
}

#[test]
fn bad_inputs_are_clear_errors() {
    let net = I3d::new(ComputeDevice::Cpu).unwrap();
    for shape in [
        [1i64, 3, 8, 224, 224],
        [1, 3, 16, 112, 112],
        [1, 1, 16, 224, 224],
    ] {
        let err = net
            .forward(&Tensor::zeros(shape, (Kind::Float, tch::Device::Cpu)))
            .unwrap_err()
            .to_string();
        assert!(err.contains("I3D") && err.contains("224"), "{err}");
    }
}
