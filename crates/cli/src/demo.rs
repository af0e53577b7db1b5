//! `bridgev2w demo`: the built-in Franka doing a pick-and-place, seen from a
//! built-in camera; writes masks, labels, PNGs and an animated GIF overlay.

use crate::masks_cmd::{render_with_progress, report_empty, write_ik_report};
use crate::overlay::{floor_background, overlay, write_gif};
use anyhow::{Context, Result};
use bridgev2w_embodiment::actions::{actions_to_joints, Trajectory};
use bridgev2w_embodiment::camera::{Camera, Intrinsics};
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_embodiment::kinematics::{xyz_rpy_from_pose, IkOptions};
use bridgev2w_embodiment::masks::{write_outputs, WriteOptions};
use bridgev2w_embodiment::npy::write_atomic;
use nalgebra::{Point3, UnitQuaternion, Vector3};
use rayon::prelude::*;
use std::path::PathBuf;
use std::time::Instant;

/// Arguments of `demo`.
#[derive(Debug, clap::Args)]
pub struct DemoArgs {
    /// Output directory.
    #[arg(long, default_value = "demo-out")]
    pub out: PathBuf,
    /// Frames in the trajectory (CogVideoX clips are 49 frames).
    #[arg(long, default_value_t = 49)]
    pub frames: usize,
}

/// The built-in demo camera: 720x480, looking at the Franka's workspace
/// from the front-right, about 1.3 m away.
pub fn demo_camera() -> Result<Camera> {
    let intrinsics = Intrinsics::centered(560.0, 720, 480);
    Ok(Camera::look_at(
        intrinsics,
        Point3::new(1.3, 0.8, 0.85),
        Point3::new(0.38, 0.0, 0.36),
        Vector3::z(),
    )?)
}

/// A pick-and-place in end-effector space: from home, approach, descend,
/// grasp, lift, carry, lower, release. `[x,y,z,roll,pitch,yaw,gripper]` rows.
pub fn demo_actions(e: &Embodiment, frames: usize) -> Result<Trajectory> {
    let ee = e
        .end_effectors
        .first()
        .context("robot has no end effector")?;
    let home = e.robot.link_pose(ee.link, &e.home);
    // (x, y, z, yaw offset, gripper)
    let keys: [(f64, f64, f64, f64, f64); 8] = [
        (
            home.translation.x,
            home.translation.y,
            home.translation.z,
            0.0,
            0.0,
        ),
        (0.50, 0.15, 0.25, 0.3, 0.0),
        (0.50, 0.15, 0.13, 0.3, 0.0),
        (0.50, 0.15, 0.13, 0.3, 1.0),
        (0.50, 0.15, 0.30, 0.3, 1.0),
        (0.40, -0.20, 0.30, -0.2, 1.0),
        (0.40, -0.20, 0.15, -0.2, 1.0),
        (0.40, -0.20, 0.15, -0.2, 0.0),
    ];
    let frames = frames.max(2);
    let rows = (0..frames)
        .map(|f| {
            let s = f as f64 / (frames - 1) as f64 * (keys.len() - 1) as f64;
            let k = (s.floor() as usize).min(keys.len() - 2);
            let t = s - k as f64;
            // Smoothstep within each segment: the arm eases in and out.
            let t = t * t * (3.0 - 2.0 * t);
            let (a, b) = (keys[k], keys[k + 1]);
            let lerp = |x: f64, y: f64| x + (y - x) * t;
            let yaw = lerp(a.3, b.3);
            let mut pose = home;
            pose.translation.vector = Vector3::new(lerp(a.0, b.0), lerp(a.1, b.1), lerp(a.2, b.2));
            pose.rotation =
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw) * home.rotation;
            let mut row = xyz_rpy_from_pose(&pose).to_vec();
            row.push(lerp(a.4, b.4));
            row
        })
        .collect();
    Ok(Trajectory::new("built-in demo trajectory", rows)?)
}

pub fn run(args: &DemoArgs) -> Result<()> {
    let start = Instant::now();
    let e = Embodiment::builtin("franka")?;
    let camera = demo_camera()?;
    let actions = demo_actions(&e, args.frames)?;
    let (joints, residuals) = actions_to_joints(
        &e.robot,
        &e.end_effectors,
        &actions,
        &e.home,
        &IkOptions::default(),
        false,
    )?;
    let frames = render_with_progress(&e, &camera, &joints);
    let out = &args.out;
    let written = write_outputs(
        out,
        &e.robot,
        &frames,
        WriteOptions {
            pngs: true,
            depth: false,
        },
    )?;
    write_ik_report(out, &residuals)?;
    write_atomic(&out.join("camera.json"), camera.to_json().as_bytes())?;
    write_atomic(
        &out.join("actions.json"),
        serde_json::to_string(&actions.rows)?.as_bytes(),
    )?;
    let background = floor_background(&camera);
    let rgb: Vec<Vec<u8>> = frames.par_iter().map(|f| overlay(f, &background)).collect();
    let gif = out.join("overlay.gif");
    write_gif(
        &gif,
        camera.intrinsics.width,
        camera.intrinsics.height,
        &rgb,
        10,
    )?;
    let still = out.join("overlay.png");
    let mid = &rgb[rgb.len() / 2];
    let png = bridgev2w_embodiment::png::encode_rgb8(
        camera.intrinsics.width,
        camera.intrinsics.height,
        mid,
    );
    write_atomic(&still, &png)?;
    report_empty(&written.empty_frames, frames.len());
    let max_res_mm = residuals
        .iter()
        .map(|r| r.position_error_m)
        .fold(0.0, f64::max)
        * 1e3;
    println!(
        "demo: {} frames of the Franka pick-and-place at 720x480 (IK max residual {max_res_mm:.4} mm) in {:.2} s",
        frames.len(),
        start.elapsed().as_secs_f64()
    );
    println!(
        "  {}/masks.npy, labels.npy, labels.json, frames/*.png",
        out.display()
    );
    println!(
        "  {}, {}  (colour overlay: animation, middle frame)",
        gif.display(),
        still.display()
    );
    println!(
        "  {}/actions.json + camera.json: re-render with",
        out.display()
    );
    println!(
        "  bridgev2w masks --robot franka --camera {0}/camera.json --actions {0}/actions.json --out OUT",
        out.display()
    );
    Ok(())
}
