//! AgiBot World's genie-envisioner samples (`../shared/realdata/`, see its
//! README; skipped with a message where the folder is absent): no joints are
//! recorded, only the flange poses, the grippers and per-frame calibrations
//! of the head and both hand cameras. The body (lift, waist pitch, head yaw
//! and pitch) is recovered from the head camera's recorded pose, the arms
//! by IK to the recorded flanges ([`joints_from_flange_poses`]); the masks
//! rendered through the three recorded cameras must then cover each arm's
//! recorded flange position, projected through the same calibration.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use bridgev2w_embodiment::camera::{read_poses_npy, Camera, CameraPose, CameraTrack, Intrinsics};
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_embodiment::masks::{link_labels, render_track_labels};
use bridgev2w_embodiment::posture::{joints_from_flange_poses, FlangeRecording, PostureOptions};
use bridgev2w_io::npy::read_npy;
use nalgebra::{Isometry3, Point3};
use std::path::{Path, PathBuf};

/// Frames with real images (`{cam}_color/{0..3}.png`).
const FRAMES: usize = 4;
const WIDTH: u32 = 640;
const HEIGHT: u32 = 480;
const CAMERAS: [&str; 3] = ["head", "hand_left", "hand_right"];
/// A projected flange within this distance of its arm's pixels counts.
const TOLERANCE_PX: f64 = 3.0;

fn samples_dir() -> Option<PathBuf> {
    bridgev2w_io::realdata::dir(
        env!("CARGO_MANIFEST_DIR"),
        "agibot-world/genie-envisioner-samples",
    )
}

fn intrinsics(path: &Path) -> Intrinsics {
    let k = read_npy(path).unwrap();
    assert_eq!(k.shape, [3, 3], "{}", path.display());
    Intrinsics {
        fx: k.data[0],
        fy: k.data[4],
        cx: k.data[2],
        cy: k.data[5],
        width: WIDTH,
        height: HEIGHT,
        distortion: None,
    }
}

fn track(dir: &Path, cam: &str) -> CameraTrack {
    let poses = read_poses_npy(&dir.join(format!("extrinsic_{cam}.npy"))).unwrap();
    CameraTrack {
        intrinsics: intrinsics(&dir.join(format!("intrinsic_{cam}.npy"))),
        pose: CameraPose::PerFrame(poses[..FRAMES].to_vec()),
    }
}

/// The first `FRAMES` rows of `actions.npy` (16 values each).
fn action_rows(dir: &Path) -> Vec<Vec<f64>> {
    let a = read_npy(&dir.join("actions.npy")).unwrap();
    assert_eq!(a.shape[1], 16);
    a.data
        .chunks(16)
        .take(FRAMES)
        .map(<[f64]>::to_vec)
        .collect()
}

/// Distance from `(u, v)` to the nearest pixel whose label is in `labels`.
fn distance_to(map: &[u16], labels: &[u16], (u, v): (f64, f64)) -> Option<f64> {
    let w = WIDTH as usize;
    map.iter()
        .enumerate()
        .filter(|(_, l)| labels.contains(l))
        .map(|(i, _)| ((i % w) as f64 - u).hypot((i / w) as f64 - v))
        .min_by(f64::total_cmp)
}

#[test]
fn genie_envisioner_masks_cover_the_recorded_flanges() {
    let Some(root) = samples_dir() else { return };
    let mut e = Embodiment::builtin("agibot-g1").unwrap();
    e.set_ee_links(&["arm_l_link7".into(), "arm_r_link7".into()])
        .unwrap();
    let robot = &e.robot;
    // Each arm's labels: its own arm and gripper links.
    let arm_labels: Vec<Vec<u16>> = ["_l_", "_r_"]
        .iter()
        .map(|side| {
            link_labels(robot)
                .into_iter()
                .filter(|(_, n)| {
                    n.starts_with(&format!("arm{side}")) || n.starts_with(&format!("gripper{side}"))
                })
                .map(|(l, _)| l)
                .collect()
        })
        .collect();
    assert!(arm_labels.iter().all(|l| l.len() >= 8), "{arm_labels:?}");

    let (mut checked, mut failures) = (0usize, Vec::new());
    for s in 0..3 {
        let dir = root.join(format!("sample_{s}"));
        let rows = action_rows(&dir);
        let tracks: Vec<CameraTrack> = CAMERAS.iter().map(|c| track(&dir, c)).collect();
        let CameraPose::PerFrame(head) = &tracks[0].pose else {
            unreachable!()
        };
        let name = format!("sample_{s}");
        let rec = FlangeRecording::from_agibot_rows(&name, &rows, 2, head.clone()).unwrap();
        let mut opts = PostureOptions::new("head_camera_optical");
        opts.allow_residual = true; // asserted below, with the figures printed first
        let posture = joints_from_flange_poses(&e, &rec, &e.home, &opts).unwrap();

        for (f, b) in posture.body.iter().enumerate() {
            let (mm, deg) = (
                b.position_residual_m * 1e3,
                b.rotation_residual_rad.to_degrees(),
            );
            let q = |n: &str| b.q[robot.dof_index(n).unwrap()];
            eprintln!(
                "{name} frame {f}: body lift {:.4} m, pitch {:.4}, head yaw {:.4}, head pitch {:.4} rad; head camera residual {mm:.2} mm, {deg:.3} deg",
                q("idx01_body_joint1"),
                q("idx02_body_joint2"),
                q("idx11_head_joint1"),
                q("idx12_head_joint2"),
            );
            // Sample 2 was recorded on another robot (or calibration): no
            // lift, pitch and head angles put the G1 model's head camera
            // (mount estimated on ge-sim-v2) on its recorded pose; the least
            // squares leave 33 mm / 0.45 deg (26 mm / 2.7 deg with rotation
            // weighted less), so only samples 0 and 1 are held to 5 mm /
            // 1 deg; sample 2 is held loosely, to catch a broken solve.
            let (tol_mm, tol_deg) = if s == 2 { (40.0, 4.0) } else { (5.0, 1.0) };
            assert!(
                mm <= tol_mm && deg <= tol_deg,
                "{name} frame {f}: head camera residual {mm:.2} mm, {deg:.3} deg > {tol_mm} mm, {tol_deg} deg"
            );
        }
        for r in &posture.arms {
            let (mm, deg) = (r.position_error_m * 1e3, r.rotation_error_rad.to_degrees());
            eprintln!(
                "{name} frame {}: {} flange IK residual {mm:.4} mm, {deg:.4} deg",
                r.frame, r.arm
            );
            assert!(
                mm <= 1.0 && deg <= 0.5,
                "{name} frame {}: {} flange not reached: {mm:.3} mm, {deg:.3} deg",
                r.frame,
                r.arm
            );
        }

        for (c, cam) in CAMERAS.iter().enumerate() {
            let labels = render_track_labels(robot, &tracks[c], &posture.joints, &|| {});
            for (f, map) in labels.iter().enumerate() {
                let camera = Camera {
                    intrinsics: tracks[c].intrinsics,
                    world_from_camera: pose_at(&tracks[c], f),
                };
                for (arm, flanges) in ["left", "right"].iter().zip(0..2) {
                    let p: Point3<f64> =
                        rec.world_from_flange[f][flanges].translation.vector.into();
                    let Some(px) = camera.project(&p) else {
                        eprintln!("{name} {cam} frame {f}: {arm} flange behind the camera");
                        continue;
                    };
                    let inside = (0.0..f64::from(WIDTH) - 0.5).contains(&px.x)
                        && (0.0..f64::from(HEIGHT) - 0.5).contains(&px.y);
                    if !inside {
                        eprintln!(
                            "{name} {cam} frame {f}: {arm} flange projects outside the image ({:.1}, {:.1})",
                            px.x, px.y
                        );
                        continue;
                    }
                    let d = distance_to(map, &arm_labels[flanges], (px.x, px.y));
                    let covered = d.is_some_and(|d| d <= TOLERANCE_PX);
                    eprintln!(
                        "{name} {cam} frame {f}: {arm} flange at ({:.1}, {:.1}): {} px from the {arm} arm's pixels, covered {covered}",
                        px.x,
                        px.y,
                        d.map_or("no pixels".to_string(), |d| format!("{d:.1}"))
                    );
                    checked += 1;
                    if !covered {
                        failures.push(format!("{name} {cam} frame {f} {arm}: {d:?} px"));
                    }
                }
            }
        }
    }
    eprintln!(
        "{checked} projected flanges checked, {} not covered",
        failures.len()
    );
    // In view (the rest project outside the image or behind the camera, as
    // the real frames show): samples 0 and 1, the right flange in the head
    // and the left-hand view of every frame; sample 2 has no flange in view.
    assert!(checked >= 2 * 2 * FRAMES, "{checked} checked");
    assert!(failures.is_empty(), "not covered: {failures:?}");
}

fn pose_at(track: &CameraTrack, f: usize) -> Isometry3<f64> {
    match &track.pose {
        CameraPose::PerFrame(p) => p[f],
        CameraPose::Fixed(p) => *p,
        CameraPose::Mounted { .. } => unreachable!("the samples' cameras are per-frame"),
    }
}
