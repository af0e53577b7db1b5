//! Whole trajectories of the built-in Franka at 720x480: labels with depth
//! maps (`render_trajectory`, what `masks --depth` and the demo's overlay
//! need) against labels alone (`render_trajectory_labels`, what `masks`
//! writes otherwise), measured in the same run.

use bridgev2w_embodiment::camera::Camera;
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_embodiment::masks::{render_trajectory, render_trajectory_labels};
use criterion::{black_box, criterion_group, criterion_main, Criterion, Throughput};

const CAMERA: &str = r#"{"fx": 600, "fy": 600, "cx": 359.5, "cy": 239.5, "width": 720, "height": 480,
  "world_from_camera": [[-0.3939, 0.3019, -0.8682, 1.7],
                        [0.9191, 0.1294, -0.3721, 0.6],
                        [0.0, -0.9445, -0.3284, 1.0],
                        [0, 0, 0, 1]]}"#;

fn bench(c: &mut Criterion) {
    let (Ok(e), Ok(camera)) = (
        Embodiment::builtin("franka"),
        Camera::from_json_str(CAMERA, "bench camera"),
    ) else {
        return;
    };
    // 49 frames (a CogVideoX clip): the first joint swings across the view.
    let joints: Vec<Vec<f64>> = (0..49)
        .map(|t| {
            let mut q = e.home.clone();
            q[0] += 0.6 * (t as f64 / 48.0 - 0.5);
            q
        })
        .collect();
    let mut group = c.benchmark_group("trajectory_franka_720x480");
    group.throughput(Throughput::Elements(joints.len() as u64));
    group.sample_size(20);
    group.bench_function("labels_and_depth", |b| {
        b.iter(|| black_box(render_trajectory(&e.robot, &camera, &joints, &|| {})))
    });
    group.bench_function("labels_only", |b| {
        b.iter(|| black_box(render_trajectory_labels(&e.robot, &camera, &joints, &|| {})))
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
