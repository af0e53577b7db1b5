//! Profiling harness: renders the `bench masks` trajectory on one thread.
//! Usage: `panda_masks URDF [FRAMES] [REPEAT]`.

use bridgev2w_embodiment::camera::{Camera, Intrinsics};
use bridgev2w_embodiment::masks::render_items;
use bridgev2w_embodiment::raster::Rasterizer;
use bridgev2w_embodiment::robot::{LoadOptions, Robot};
use nalgebra::{Point3, Vector3};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let urdf = std::path::PathBuf::from(&args[1]);
    let frames: usize = args.get(2).map_or(50, |s| s.parse().expect("frames"));
    let repeat: usize = args.get(3).map_or(1, |s| s.parse().expect("repeat"));
    let robot = Robot::from_urdf_file(&urdf, &LoadOptions::default()).expect("urdf");
    let camera = Camera::look_at(
        Intrinsics::centered(560.0, 720, 480),
        Point3::new(1.5, 0.9, 0.9),
        Point3::new(0.2, 0.0, 0.4),
        Vector3::z(),
    )
    .expect("camera");
    let limits = robot.dof_limits();
    let joints: Vec<Vec<f64>> = (0..frames)
        .map(|f| {
            let s = f as f64 / frames as f64;
            limits
                .iter()
                .enumerate()
                .map(|(i, &(lo, hi))| {
                    let (lo, hi) = (lo.max(-2.5), hi.min(2.5));
                    0.5 * (lo + hi)
                        + 0.35 * (hi - lo) * (std::f64::consts::TAU * s + i as f64).sin()
                })
                .collect()
        })
        .collect();
    let rasterizer = Rasterizer::new(&camera);
    let mut checksum = 0usize;
    let t0 = std::time::Instant::now();
    for _ in 0..repeat {
        for q in &joints {
            let poses = robot.link_poses(q);
            let labels = rasterizer.render_labels(&render_items(&robot, &poses, true));
            checksum += labels.iter().filter(|&&l| l != 0).count();
        }
    }
    let s = t0.elapsed().as_secs_f64();
    println!(
        "{:.3} ms/frame, checksum {checksum}",
        s * 1e3 / (frames * repeat) as f64
    );
}
