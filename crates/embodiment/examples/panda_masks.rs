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
    // FNV-1a over every label of every frame: output identity across changes.
    let mut hash = 0xcbf2_9ce4_8422_2325u64;
    let (mut render_s, mut cpu_s) = (0.0, 0.0);
    for _ in 0..repeat {
        for q in &joints {
            let poses = robot.link_poses(q);
            let (t, c) = (std::time::Instant::now(), cpu_ns());
            let labels = rasterizer.render_labels(&render_items(&robot, &poses, true));
            render_s += t.elapsed().as_secs_f64();
            cpu_s += (cpu_ns() - c) as f64 * 1e-9;
            checksum += labels.iter().filter(|&&l| l != 0).count();
            for &l in &labels {
                hash = (hash ^ u64::from(l)).wrapping_mul(0x0100_0000_01b3);
            }
        }
    }
    let n = (frames * repeat) as f64;
    println!(
        "{:.3} ms/frame on CPU, {:.3} ms/frame wall (render_labels), checksum {checksum}, hash {hash:016x}",
        cpu_s * 1e3 / n,
        render_s * 1e3 / n
    );
}

/// CPU time of this thread, nanoseconds (Linux; 0 elsewhere): robust to
/// other processes on a shared machine, unlike wall time.
fn cpu_ns() -> u64 {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()
        .and_then(|s| s.split_whitespace().next()?.parse().ok())
        .unwrap_or(0)
}
