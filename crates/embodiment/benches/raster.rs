//! Rasterizer throughput: 8 capsules/spheres of ~2k triangles at 720x480.

use bridgev2w_embodiment::camera::{Camera, Distortion, Intrinsics};
use bridgev2w_embodiment::mesh::TriMesh;
use bridgev2w_embodiment::raster::{Rasterizer, RenderItem, RenderOutput};
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};

fn camera() -> Camera {
    let intrinsics = Intrinsics {
        fx: 520.0,
        fy: 520.0,
        cx: 359.5,
        cy: 239.5,
        width: 720,
        height: 480,
        distortion: None,
    };
    Camera::look_at(
        intrinsics,
        Point3::new(0.75, 0.55, 0.6),
        Point3::new(0.0, 0.0, 0.35),
        Vector3::z(),
    )
    .expect("valid camera")
}

/// An arm-like chain of links: capsules and spheres (~2k triangles each).
fn scene(meshes: &[TriMesh], t: f64) -> Vec<RenderItem<'_>> {
    meshes
        .iter()
        .enumerate()
        .map(|(i, mesh)| {
            let s = i as f64;
            RenderItem {
                mesh,
                world_from_mesh: Isometry3::from_parts(
                    Translation3::new(0.08 * (s + t).sin(), 0.05 * s - 0.2, 0.1 * s),
                    UnitQuaternion::from_euler_angles(0.4 * s + t, 0.2 * s, 0.0),
                ),
                label: i as u16 + 1,
            }
        })
        .collect()
}

fn meshes() -> Vec<TriMesh> {
    (0..8)
        .map(|i| {
            if i % 2 == 0 {
                TriMesh::capsule(0.06, 0.2, 44)
            } else {
                TriMesh::sphere(0.07, 44)
            }
        })
        .collect()
}

fn bench(c: &mut Criterion) {
    let camera = camera();
    let raster = Rasterizer::new(&camera);
    let meshes = meshes();
    let triangles: usize = meshes.iter().map(|m| m.triangles.len()).sum();
    let items = scene(&meshes, 0.3);
    let mut out = RenderOutput::new(720, 480);
    raster.render_into(&items, &mut out);
    eprintln!(
        "scene: {triangles} triangles, coverage {} px of {}",
        out.coverage(),
        720 * 480
    );

    let mut group = c.benchmark_group("raster_720x480");
    group.throughput(Throughput::Elements(1));
    group.bench_function("render_into_1_frame", |b| {
        b.iter(|| raster.render_into(&items, &mut out))
    });
    let mut distorted = camera.clone();
    distorted.intrinsics.distortion = Some(Distortion {
        k1: -0.1,
        k2: 0.02,
        ..Default::default()
    });
    let distorted = Rasterizer::new(&distorted);
    group.bench_function("render_into_1_frame_distorted", |b| {
        b.iter(|| distorted.render_into(&items, &mut out))
    });
    let frames: Vec<Vec<RenderItem>> = (0..16)
        .map(|f| scene(&meshes, f64::from(f) * 0.05))
        .collect();
    group.throughput(Throughput::Elements(frames.len() as u64));
    group.bench_function("render_frames_16_parallel", |b| {
        b.iter(|| raster.render_frames(&frames))
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
