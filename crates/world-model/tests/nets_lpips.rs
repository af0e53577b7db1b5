//! LPIPS (AlexNet, v0.1) against the `lpips` package, plus its metric properties.

#![allow(clippy::unwrap_used)]

use crate::common;

use bridgev2w_io::frame::RgbFrame;
use bridgev2w_world_model::nets::lpips::Lpips;
use bridgev2w_world_model::parity::{run_fixture, DEFAULT_TOLERANCE};
use bridgev2w_world_model::video::Video;
use bridgev2w_world_model::weights::resolve_weight_files;
use bridgev2w_world_model::ComputeDevice;

fn fixture() -> std::path::PathBuf {
    common::fixture("lpips-alex", &["lpips", "--shape", "3,3,64,96"])
}

#[test]
fn matches_the_lpips_package() {
    let report = run_fixture(&fixture()).unwrap();
    assert_eq!(report.outputs.len(), 1);
    let o = &report.outputs[0];
    assert!(
        o.max_rel <= DEFAULT_TOLERANCE,
        "distance: rel {:e} abs {:e}",
        o.max_rel,
        o.max_abs
    );
}

fn image(seed: u64, h: usize, w: usize) -> RgbFrame {
    let mut s = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
    let data = (0..h * w * 3)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 40) as f32 / (1u64 << 24) as f32
        })
        .collect();
    RgbFrame {
        height: h,
        width: w,
        rgb: data,
    }
}

#[test]
fn identity_symmetry_and_positivity() {
    let files = resolve_weight_files(&fixture().join("model"), "lpips_alex").unwrap();
    let net = Lpips::load(&files, ComputeDevice::Cpu).unwrap();
    let (a, b) = (image(1, 48, 64), image(2, 48, 64));
    assert_eq!(net.distance(&a, &a).unwrap(), 0.0);
    let (ab, ba) = (net.distance(&a, &b).unwrap(), net.distance(&b, &a).unwrap());
    assert!(ab > 0.0 && (ab - ba).abs() < 1e-6 * ab, "{ab} {ba}");
    // A video's mean equals the mean of its frames' distances.
    let video = |imgs: &[&RgbFrame]| Video {
        frames: imgs.len(),
        height: 48,
        width: 64,
        data: imgs.iter().flat_map(|i| i.rgb.iter().copied()).collect(),
    };
    let c = image(3, 48, 64);
    let v = net
        .video_distance(&video(&[&a, &c]), &video(&[&b, &c]), 1)
        .unwrap();
    assert!((v - ab / 2.0).abs() < 1e-6, "{v} vs {}", ab / 2.0);
}

#[test]
fn bad_inputs_and_weights_are_errors() {
    let files = resolve_weight_files(&fixture().join("model"), "lpips_alex").unwrap();
    let net = Lpips::load(&files, ComputeDevice::Cpu).unwrap();
    let e = net
        .distance(&image(1, 16, 16), &image(2, 16, 16))
        .unwrap_err()
        .to_string();
    assert!(e.contains("at least 32x32"), "{e}");
    let e = net
        .distance(&image(1, 48, 64), &image(2, 64, 48))
        .unwrap_err()
        .to_string();
    assert!(e.contains("of one shape"), "{e}");
    // A file without the heads: the missing key is named.
    let dir = tempfile::tempdir().unwrap();
    let trunk_only = dir.path().join("alexnet.safetensors");
    let named: Vec<(String, tch::Tensor)> =
        bridgev2w_world_model::weights::read_safetensors(&files[0])
            .unwrap()
            .into_iter()
            .filter(|(k, _)| k.starts_with("features."))
            .collect();
    bridgev2w_world_model::weights::save_safetensors(&named, &trunk_only).unwrap();
    let e = Lpips::load(&[trunk_only], ComputeDevice::Cpu)
        .unwrap_err()
        .to_string();
    assert!(e.contains("lin0.model.1.weight"), "{e}");
}
