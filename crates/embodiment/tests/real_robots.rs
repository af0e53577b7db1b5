//! The built-in real robots against real recorded episodes
//! (`../shared/realdata/`, see its README; skipped with a message where the
//! folder is absent): forward kinematics of the recorded joints reproduces
//! the recorded flange poses and camera poses.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use bridgev2w_embodiment::embodiment::{Embodiment, BUILTIN_ROBOTS};
use bridgev2w_embodiment::kinematics::pose_error;
use bridgev2w_io::npy::read_npy;
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion};
use std::path::{Path, PathBuf};

fn realdata() -> Option<PathBuf> {
    bridgev2w_io::realdata::dir(env!("CARGO_MANIFEST_DIR"), "")
}

fn pose_xyz_rpy(v: &[f64]) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(v[0], v[1], v[2]),
        UnitQuaternion::from_euler_angles(v[3], v[4], v[5]),
    )
}

fn pose_rows(m: &[f64]) -> Isometry3<f64> {
    let r = Matrix3::from_fn(|i, j| m[4 * i + j]);
    Isometry3::from_parts(
        Translation3::new(m[3], m[7], m[11]),
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&r)),
    )
}

fn json_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            json_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "json")
            && p.parent()
                .unwrap()
                .parent()
                .unwrap()
                .ends_with("annotation")
        {
            out.push(p);
        }
    }
}

fn rows(v: &serde_json::Value) -> Vec<Vec<f64>> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|r| {
            r.as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap())
                .collect()
        })
        .collect()
}

#[test]
fn every_builtin_robot_loads_with_its_meshes() {
    for b in BUILTIN_ROBOTS {
        let e = Embodiment::builtin(b.name).unwrap();
        let meshed = e.robot.links.iter().filter(|l| l.mesh.is_some()).count();
        assert!(meshed >= 8, "{}: {meshed} links with geometry", b.name);
        assert_eq!(e.end_effectors.len(), b.arms.len());
        for a in b.arms {
            assert!(
                e.robot.link_index(a.flange_link).is_some(),
                "{}: flange {}",
                b.name,
                a.flange_link
            );
        }
        let folder = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("robots")
            .join(b.folder);
        assert!(folder.join("README.md").is_file(), "{}: README", b.name);
    }
}

/// DROID: FK of the recorded Franka joints on `franka-robotiq` gives the
/// recorded `cartesian_position` (the flange `panda_link8`) in every frame
/// of every episode, within 1 mm and 0.1 degree.
#[test]
fn droid_joints_reproduce_the_recorded_flange_poses() {
    let Some(root) = realdata() else { return };
    let e = Embodiment::builtin("franka-robotiq").unwrap();
    let r = &e.robot;
    let flange = r.link_index("panda_link8").unwrap();
    let mut files = Vec::new();
    json_files(&root.join("droid"), &mut files);
    assert!(files.len() >= 40, "{} episode files", files.len());
    let (mut frames, mut worst_m, mut worst_rad) = (0usize, 0.0f64, 0.0f64);
    for f in &files {
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(f).unwrap()).unwrap();
        let pairs = if let Some(j) = v.get("observation.state.joint_position") {
            (rows(j), rows(&v["observation.state.cartesian_position"]))
        } else {
            (rows(&v["joints"]), rows(&v["states"]))
        };
        assert_eq!(pairs.0.len(), pairs.1.len(), "{}", f.display());
        for (joints, pose) in pairs.0.iter().zip(&pairs.1) {
            let mut q = e.home.clone();
            q[..7].copy_from_slice(&joints[..7]);
            let (dp, dr) = pose_error(&r.link_pose(flange, &q), &pose_xyz_rpy(pose));
            worst_m = worst_m.max(dp);
            worst_rad = worst_rad.max(dr);
            frames += 1;
        }
    }
    eprintln!(
        "DROID: {} episodes, {frames} frames: worst {:.2e} mm, {:.2e} deg",
        files.len(),
        worst_m * 1e3,
        worst_rad.to_degrees()
    );
    assert!(frames > 5000);
    assert!(worst_m < 1e-3 && worst_rad.to_degrees() < 0.1);
}

/// AgiBot World (the ge-sim-v2 sample with joints and calibration): FK of
/// the recorded joints, waist and head on `agibot-g1` gives the recorded
/// flange poses (`arm_*_link7`) and the head camera's recorded pose.
#[test]
fn agibot_joints_reproduce_the_recorded_flange_and_head_camera_poses() {
    let Some(root) = realdata() else { return };
    let dir = root.join("agibot-world/ge-sim-v2-demo_000");
    let e = Embodiment::builtin("agibot-g1").unwrap();
    let r = &e.robot;
    let joints = read_npy(&dir.join("state_joints_0.npy")).unwrap();
    let eef = read_npy(&dir.join("state_eef_poses_0.npy")).unwrap();
    let ext = read_npy(&dir.join("extrinsic_alignstate_0.npy")).unwrap();
    let t_count = joints.shape[0];
    assert_eq!(joints.shape, [t_count, 20]);
    // state_joints: left arm 7, right arm 7, grippers 2, head 2, waist
    // (pitch, lift).
    let mut names: Vec<String> = (1..=7).map(|k| format!("idx2{k}_arm_l_joint{k}")).collect();
    names.extend((1..=7).map(|k| format!("idx6{k}_arm_r_joint{k}")));
    let columns: Vec<(usize, usize)> = names
        .iter()
        .enumerate()
        .map(|(c, n)| (c, r.dof_index(n).unwrap()))
        .chain([
            (16, r.dof_index("idx11_head_joint1").unwrap()),
            (17, r.dof_index("idx12_head_joint2").unwrap()),
            (18, r.dof_index("idx02_body_joint2").unwrap()),
            (19, r.dof_index("idx01_body_joint1").unwrap()),
        ])
        .collect();
    let flanges = [
        r.link_index("arm_l_link7").unwrap(),
        r.link_index("arm_r_link7").unwrap(),
    ];
    let head_camera = r.link_index("head_camera_optical").unwrap();
    let (mut worst_m, mut worst_rad, mut cam_m, mut cam_rad) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    for t in 0..t_count {
        let row = &joints.data[20 * t..20 * t + 20];
        let mut q = e.home.clone();
        for &(c, d) in &columns {
            q[d] = row[c];
        }
        let poses = r.link_poses(&q);
        for (arm, &l) in flanges.iter().enumerate() {
            let rec = &eef.data[14 * t + 7 * arm..14 * t + 7 * arm + 6];
            let (dp, dr) = pose_error(&poses[l], &pose_xyz_rpy(rec));
            worst_m = worst_m.max(dp);
            worst_rad = worst_rad.max(dr);
        }
        let m = &ext.data[16 * t..16 * t + 16]; // camera 0 = head
        let (dp, dr) = pose_error(&poses[head_camera], &pose_rows(m));
        cam_m = cam_m.max(dp);
        cam_rad = cam_rad.max(dr);
    }
    eprintln!(
        "AgiBot G1: {t_count} frames: flanges worst {:.4} mm, {:.4} deg; head camera worst {:.3} mm, {:.3} deg",
        worst_m * 1e3,
        worst_rad.to_degrees(),
        cam_m * 1e3,
        cam_rad.to_degrees()
    );
    assert!(worst_m < 1e-3 && worst_rad.to_degrees() < 0.1);
    assert!(cam_m < 2e-3 && cam_rad.to_degrees() < 0.2);
}

/// Flange poses re-expressed as TCP poses equal the TCP's own forward
/// kinematics (and back), for DROID's robot at its recorded joints.
#[test]
fn flange_and_tcp_actions_convert_into_each_other() {
    let e = Embodiment::builtin("franka-robotiq").unwrap();
    let r = &e.robot;
    let (flange, tcp) = (
        r.link_index("panda_link8").unwrap(),
        r.link_index("robotiq_tcp").unwrap(),
    );
    let mut q = e.home.clone();
    q[0] = 0.3;
    q[3] = -2.0;
    let row = |link: usize| {
        let mut v =
            bridgev2w_embodiment::kinematics::xyz_rpy_from_pose(&r.link_pose(link, &q)).to_vec();
        v.push(0.7);
        v
    };
    let names = |n: &str| vec![n.to_string()];
    let out = e
        .convert_action_links(&[row(flange)], &names("panda_link8"), &names("robotiq_tcp"))
        .unwrap();
    let (dp, dr) = pose_error(&pose_xyz_rpy(&out[0]), &pose_xyz_rpy(&row(tcp)));
    assert!(dp < 1e-9 && dr < 1e-9, "{dp} {dr}");
    assert_eq!(out[0][6], 0.7, "gripper copied");
    let back = e
        .convert_action_links(&out, &names("robotiq_tcp"), &names("panda_link8"))
        .unwrap();
    let (dp, dr) = pose_error(&pose_xyz_rpy(&back[0]), &pose_xyz_rpy(&row(flange)));
    assert!(dp < 1e-9 && dr < 1e-9);
    // Links that a joint separates are refused by name.
    let err = e
        .convert_action_links(&[row(flange)], &names("panda_link3"), &names("robotiq_tcp"))
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("panda_link3") && err.contains("rigidly"),
        "{err}"
    );
}
