//! The overlay library ([`overlay`]) on real AgiBot World frames
//! (`../shared/realdata/agibot-world/`, see its README; skipped with a
//! message where the folder is absent): the masks of `agibot-g1` rendered
//! through the recorded calibrations must cover each arm's recorded flange
//! position projected through the same calibration (`scores.json`'s truth
//! points).
//!
//! - ge-sim-v2 demo_000: recorded joints, one photo per camera at t = 0.
//! - genie-envisioner samples: no joints; the body from the head camera and
//!   the arms from the recorded flanges
//!   ([`bridgev2w_embodiment::posture::joints_from_flange_poses`]), 4 frames
//!   per camera.
//!
//! With `BRIDGEV2W_WRITE_DOC_IMAGES=DIR` the overlays of the data guide are
//! written there (at most 320 px wide): `ge_sim_v2_head.png`,
//! `ge_sim_v2_hand_left.png`, `genie_envisioner_sample_0_head.png`,
//! `genie_envisioner_sample_0_hand_left.png`.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use bridgev2w_data::overlay::{overlay, FrameSource, OverlayOptions, OverlayReport, TruthPoint};
use bridgev2w_embodiment::camera::{read_poses_npy, Camera, CameraPose, CameraTrack, Intrinsics};
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_embodiment::posture::{joints_from_flange_poses, FlangeRecording, PostureOptions};
use bridgev2w_embodiment::robot::Robot;
use bridgev2w_io::npy::read_npy;
use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion};
use std::path::{Path, PathBuf};

const TOLERANCE_PX: f64 = 3.0;
const DOC_WIDTH: u32 = 320;

fn agibot_dir() -> Option<PathBuf> {
    bridgev2w_io::realdata::dir(env!("CARGO_MANIFEST_DIR"), "agibot-world")
}

fn intrinsics(k: &[f64], width: u32, height: u32) -> Intrinsics {
    Intrinsics {
        fx: k[0],
        fy: k[4],
        cx: k[2],
        cy: k[5],
        width,
        height,
        distortion: None,
    }
}

fn pose_rows(m: &[f64]) -> Isometry3<f64> {
    let r = Matrix3::from_fn(|i, j| m[4 * i + j]);
    Isometry3::from_parts(
        Translation3::new(m[3], m[7], m[11]),
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&r)),
    )
}

/// Truth points: each flange position (`flanges[frame][arm]`) projected
/// through the track's camera of that frame, where it is in front of the
/// camera and inside the image.
fn flange_points(track: &CameraTrack, flanges: &[Vec<Point3<f64>>]) -> Vec<TruthPoint> {
    let k = &track.intrinsics;
    let mut out = Vec::new();
    for (frame, arms) in flanges.iter().enumerate() {
        let world_from_camera = match &track.pose {
            CameraPose::PerFrame(p) => p[frame],
            CameraPose::Fixed(p) => *p,
            CameraPose::Mounted { .. } => unreachable!("recorded cameras"),
        };
        let camera = Camera {
            intrinsics: *k,
            world_from_camera,
        };
        for (arm, p) in ["left", "right"].iter().zip(arms) {
            let Some(px) = camera.project(p) else {
                continue;
            };
            if (0.0..f64::from(k.width) - 0.5).contains(&px.x)
                && (0.0..f64::from(k.height) - 0.5).contains(&px.y)
            {
                out.push(TruthPoint {
                    frame,
                    u: px.x,
                    v: px.y,
                    name: format!("{arm} flange"),
                });
            }
        }
    }
    out
}

/// Runs [`overlay`] with the flange truth points and checks they are all
/// covered; prints the figures; returns the report and the output folder.
fn run_overlay(
    label: &str,
    robot: &Robot,
    track: &CameraTrack,
    joints: &[Vec<f64>],
    images: Vec<PathBuf>,
    flanges: &[Vec<Point3<f64>>],
    out: &Path,
) -> OverlayReport {
    let points = flange_points(track, flanges);
    std::fs::create_dir_all(out).unwrap();
    let truth = out.join("truth_points.json");
    std::fs::write(&truth, serde_json::to_string(&points).unwrap()).unwrap();
    let options = OverlayOptions {
        frames: FrameSource::Images(images),
        truth_points: Some(truth),
        point_tolerance_px: TOLERANCE_PX,
        ..OverlayOptions::default()
    };
    let report = overlay(robot, track, joints, &options, out, &|| {}).unwrap();
    for p in &report.per_point {
        eprintln!(
            "{label} frame {}: {} at ({:.1}, {:.1}): {} px from the mask, covered {}",
            p.point.frame,
            p.point.name,
            p.point.u,
            p.point.v,
            p.distance_px
                .map_or("no mask".into(), |d| format!("{d:.1}")),
            p.inside
        );
    }
    eprintln!(
        "{label}: {} frames, {}/{} flange points covered, robot pixels per frame {:?}",
        report.frames,
        report.points_inside,
        report.points,
        report
            .per_frame
            .iter()
            .map(|f| f.robot_pixels)
            .collect::<Vec<_>>()
    );
    assert_eq!(report.frames, joints.len());
    assert!(
        report.per_frame.iter().all(|f| f.robot_pixels > 0),
        "{label}: an empty mask"
    );
    assert_eq!(
        report.points_inside, report.points,
        "{label}: flange points not covered"
    );
    report
}

/// Copies `out/overlay/000000.png` to `DIR/name` (at most [`DOC_WIDTH`]
/// wide) when `BRIDGEV2W_WRITE_DOC_IMAGES=DIR` is set.
fn write_doc_image(out: &Path, name: &str) {
    let Some(dir) = std::env::var_os("BRIDGEV2W_WRITE_DOC_IMAGES") else {
        return;
    };
    let dir = PathBuf::from(dir);
    std::fs::create_dir_all(&dir).unwrap();
    let bytes = std::fs::read(out.join("overlay/000000.png")).unwrap();
    let (w, h, rgb) = bridgev2w_io::png::decode_rgb8(&bytes).unwrap();
    let img = image::RgbImage::from_raw(w, h, rgb).unwrap();
    let img = if w > DOC_WIDTH {
        let h_small = (f64::from(h) * f64::from(DOC_WIDTH) / f64::from(w)).round() as u32;
        image::imageops::resize(
            &img,
            DOC_WIDTH,
            h_small,
            image::imageops::FilterType::Triangle,
        )
    } else {
        img
    };
    let png = bridgev2w_io::png::encode_rgb8_small(img.width(), img.height(), img.as_raw());
    std::fs::write(dir.join(name), png).unwrap();
    eprintln!("wrote {}", dir.join(name).display());
}

/// ge-sim-v2 demo_000 at t = 0: the recorded joints (arms, grippers, head,
/// waist) through the recorded head and hand calibrations.
#[test]
fn ge_sim_v2_overlays_cover_the_recorded_flanges() {
    let Some(root) = agibot_dir() else { return };
    let dir = root.join("ge-sim-v2-demo_000");
    let e = Embodiment::builtin("agibot-g1").unwrap();
    let r = &e.robot;
    let joints = read_npy(&dir.join("state_joints_0.npy")).unwrap();
    let eef = read_npy(&dir.join("state_eef_poses_0.npy")).unwrap();
    let ext = read_npy(&dir.join("extrinsic_alignstate_0.npy")).unwrap();
    let k = read_npy(&dir.join("intrinsic.npy")).unwrap();
    let t_count = joints.shape[0];
    assert_eq!(joints.shape, [t_count, 20]);
    assert_eq!(ext.shape, [3, t_count, 4, 4]);
    assert_eq!(k.shape, [3, 3, 3]);

    // state_joints: left arm 7, right arm 7, grippers 2 (raw, / 120), head
    // 2, waist (pitch, lift).
    let row = &joints.data[..20];
    let mut q = e.home.clone();
    for k in 1..=7 {
        q[r.dof_index(&format!("idx2{k}_arm_l_joint{k}")).unwrap()] = row[k - 1];
        q[r.dof_index(&format!("idx6{k}_arm_r_joint{k}")).unwrap()] = row[6 + k];
    }
    for (c, name) in [
        (16, "idx11_head_joint1"),
        (17, "idx12_head_joint2"),
        (18, "idx02_body_joint2"),
        (19, "idx01_body_joint1"),
    ] {
        q[r.dof_index(name).unwrap()] = row[c];
    }
    let limits = r.dof_limits();
    for (arm, ee) in e.end_effectors.iter().enumerate() {
        let d = ee.gripper_dof.unwrap();
        q[d] = ee.gripper_joint_value((row[14 + arm] / 120.0).clamp(0.0, 1.0), limits[d]);
    }
    let flanges = vec![(0..2)
        .map(|arm| {
            let v = &eef.data[7 * arm..7 * arm + 3];
            Point3::new(v[0], v[1], v[2])
        })
        .collect::<Vec<_>>()];

    let tmp = tempfile::tempdir().unwrap();
    let mut covered = 0;
    for (c, (cam, photo)) in [
        ("head", "cur_head"),
        ("hand_left", "cur_left"),
        ("hand_right", "cur_right"),
    ]
    .iter()
    .enumerate()
    {
        let m = &ext.data[16 * c * t_count..16 * c * t_count + 16];
        let track = CameraTrack {
            intrinsics: intrinsics(&k.data[9 * c..9 * c + 9], 512, 384),
            pose: CameraPose::PerFrame(vec![pose_rows(m)]),
        };
        let out = tmp.path().join(cam);
        let report = run_overlay(
            &format!("ge-sim-v2 {cam}"),
            r,
            &track,
            std::slice::from_ref(&q),
            vec![dir.join(format!("{photo}.png"))],
            &flanges,
            &out,
        );
        covered += report.points_inside;
        if *cam != "hand_right" {
            write_doc_image(&out, &format!("ge_sim_v2_{cam}.png"));
        }
    }
    // The other arm's flange in each hand view (both flanges are just
    // outside the head view at t = 0: the grippers show at its edges).
    assert!(covered >= 2, "{covered} flange points covered");
}

/// The genie-envisioner samples, frames 0..3: joints recovered from the
/// recorded flanges and head camera, overlaid on every camera's frames.
#[test]
fn genie_envisioner_overlays_cover_the_recorded_flanges() {
    let Some(root) = agibot_dir() else { return };
    let mut e = Embodiment::builtin("agibot-g1").unwrap();
    e.set_ee_links(&["arm_l_link7".into(), "arm_r_link7".into()])
        .unwrap();
    const FRAMES: usize = 4;
    let tmp = tempfile::tempdir().unwrap();
    let mut covered = 0;
    for s in 0..3 {
        let dir = root.join(format!("genie-envisioner-samples/sample_{s}"));
        let a = read_npy(&dir.join("actions.npy")).unwrap();
        assert_eq!(a.shape[1], 16);
        let rows: Vec<Vec<f64>> = a
            .data
            .chunks(16)
            .take(FRAMES)
            .map(<[f64]>::to_vec)
            .collect();
        let track = |cam: &str| {
            let k = read_npy(&dir.join(format!("intrinsic_{cam}.npy"))).unwrap();
            let poses = read_poses_npy(&dir.join(format!("extrinsic_{cam}.npy"))).unwrap();
            CameraTrack {
                intrinsics: intrinsics(&k.data, 640, 480),
                pose: CameraPose::PerFrame(poses[..FRAMES].to_vec()),
            }
        };
        let head = track("head");
        let CameraPose::PerFrame(head_poses) = &head.pose else {
            unreachable!()
        };
        let name = format!("sample_{s}");
        let rec = FlangeRecording::from_agibot_rows(&name, &rows, 2, head_poses.clone()).unwrap();
        let posture = joints_from_flange_poses(
            &e,
            &rec,
            &e.home,
            &PostureOptions::new("head_camera_optical"),
        )
        .unwrap();
        let flanges: Vec<Vec<Point3<f64>>> = rec
            .world_from_flange
            .iter()
            .map(|arms| arms.iter().map(|p| p.translation.vector.into()).collect())
            .collect();
        for cam in ["head", "hand_left", "hand_right"] {
            let images = (0..FRAMES)
                .map(|f| dir.join(format!("{cam}_color/{f}.png")))
                .collect();
            let out = tmp.path().join(format!("{name}_{cam}"));
            let report = run_overlay(
                &format!("genie-envisioner {name} {cam}"),
                &e.robot,
                &track(cam),
                &posture.joints,
                images,
                &flanges,
                &out,
            );
            covered += report.points_inside;
            if s == 0 && cam != "hand_right" {
                write_doc_image(&out, &format!("genie_envisioner_sample_0_{cam}.png"));
            }
        }
    }
    // Samples 0 and 1: the right flange in the head and left-hand views of
    // every frame (the others are outside the images).
    assert!(covered >= 2 * 2 * FRAMES, "{covered} flange points covered");
}
