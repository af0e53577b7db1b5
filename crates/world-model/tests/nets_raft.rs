//! RAFT (torchvision raft_small / raft_large) against torchvision, plus
//! behaviour the flow loss relies on.

#![allow(clippy::unwrap_used)]

use crate::common;

use bridgev2w_world_model::nets::raft::{Raft, RaftConfig};
use bridgev2w_world_model::parity::{run_fixture, DEFAULT_TOLERANCE};
use bridgev2w_world_model::weights::resolve_weight_files;
use bridgev2w_world_model::ComputeDevice;
use tch::{Kind, Tensor};

fn check(name: &str, args: &[&str]) {
    let dir = common::fixture(name, args);
    let report = run_fixture(&dir).unwrap();
    assert_eq!(report.outputs.len(), 2, "{name}");
    for o in &report.outputs {
        assert!(
            o.max_rel <= DEFAULT_TOLERANCE,
            "{name}: {} rel {:e} abs {:e}",
            o.name,
            o.max_rel,
            o.max_abs
        );
    }
}

#[test]
fn raft_small_matches_torchvision() {
    check(
        "raft-small",
        &[
            "raft",
            "--variant",
            "raft_small",
            "--shape",
            "2,3,128,136",
            "--iterations",
            "3",
        ],
    );
}

#[test]
fn raft_large_matches_torchvision() {
    check(
        "raft-large",
        &[
            "raft",
            "--variant",
            "raft_large",
            "--shape",
            "1,3,128,128",
            "--iterations",
            "2",
        ],
    );
}

#[test]
fn gradients_reach_the_images_and_bad_sizes_are_errors() {
    let dir = common::fixture(
        "raft-small",
        &[
            "raft",
            "--variant",
            "raft_small",
            "--shape",
            "2,3,128,136",
            "--iterations",
            "3",
        ],
    );
    let files = resolve_weight_files(&dir.join("model"), "raft_small").unwrap();
    let net = Raft::load(RaftConfig::small(), &files, ComputeDevice::Cpu).unwrap();
    tch::manual_seed(0);
    let a = (Tensor::rand([1, 3, 128, 128], (Kind::Float, tch::Device::Cpu)) * 2.0 - 1.0)
        .set_requires_grad(true);
    let b = a.roll([1, 2], [2, 3]).detach();
    let flow = net.forward(&a, &b, 2).unwrap();
    assert_eq!(flow.size(), [1, 2, 128, 128]);
    flow.abs().mean(Kind::Float).backward();
    let g = a.grad();
    assert!(
        g.abs().sum(Kind::Float).double_value(&[]) > 0.0,
        "no gradient reached image1"
    );
    // Frozen: the weights get no gradients.
    assert!(net
        .var_store()
        .variables()
        .values()
        .all(|v| !v.requires_grad()));
    let e = net
        .forward(&a.detach().narrow(2, 0, 120), &b.narrow(2, 0, 120), 2)
        .unwrap_err()
        .to_string();
    assert!(e.contains("divisible by 8"), "{e}");
    let e = net.forward(&a.detach(), &b, 0).unwrap_err().to_string();
    assert!(e.contains("0 refinement iterations"), "{e}");
}
