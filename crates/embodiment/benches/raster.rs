//! Rasterizer throughput at 720x480.
//!
//! Always: 8 capsules/spheres of ~2k triangles each. Optionally, when the
//! environment variable `BRIDGEV2W_RASTER_SCENE` names a JSON file
//! `[{"mesh": "path.obj", "position": [x, y, z], "quaternion_xyzw": [..],
//! "scale": [..]}, ...]` (e.g. a Franka Panda's visual meshes posed by a
//! simulator), that scene too, seen from the same viewpoint as the reference
//! measurement (eye (1.125, 0.825, 0.9), target (0, 0, 0.35), 50° vertical
//! field of view).

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
                closed_triangles: 0,
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

/// Minimum wall time of `f` over `n` runs, milliseconds (robust to other
/// load on a shared machine).
fn min_time_ms(n: usize, mut f: impl FnMut()) -> f64 {
    (0..n)
        .map(|_| {
            let t = std::time::Instant::now();
            f();
            t.elapsed().as_secs_f64() * 1e3
        })
        .fold(f64::INFINITY, f64::min)
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
        "scene: {triangles} triangles, coverage {} px of {}, min {:.3} ms/frame",
        out.coverage(),
        720 * 480,
        min_time_ms(200, || raster.render_into(&items, &mut out))
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

/// A minimal OBJ reader for the benchmark: `v` and `f` records, polygons
/// fan-triangulated, negative (relative) indices supported.
fn read_obj(path: &str, scale: [f32; 3]) -> TriMesh {
    let text = std::fs::read_to_string(path).expect("readable OBJ");
    let mut mesh = TriMesh::default();
    for line in text.lines() {
        let mut fields = line.split_whitespace();
        match fields.next() {
            Some("v") => {
                let c: Vec<f32> = fields.take(3).map(|f| f.parse().expect("number")).collect();
                mesh.vertices.push(Point3::new(
                    c[0] * scale[0],
                    c[1] * scale[1],
                    c[2] * scale[2],
                ));
            }
            Some("f") => {
                let n = mesh.vertices.len() as i64;
                let idx: Vec<u32> = fields
                    .map(|f| {
                        let i: i64 = f.split('/').next().expect("index").parse().expect("int");
                        (if i < 0 { n + i } else { i - 1 }) as u32
                    })
                    .collect();
                for k in 1..idx.len().saturating_sub(1) {
                    mesh.triangles.push([idx[0], idx[k], idx[k + 1]]);
                }
            }
            _ => {}
        }
    }
    mesh
}

fn bench_scene_file(c: &mut Criterion) {
    let Ok(path) = std::env::var("BRIDGEV2W_RASTER_SCENE") else {
        return;
    };
    let text = std::fs::read_to_string(&path).expect("readable scene");
    let entries: Vec<serde_json::Value> = serde_json::from_str(&text).expect("scene JSON");
    let f32s = |v: &serde_json::Value| -> Vec<f64> {
        v.as_array()
            .expect("array")
            .iter()
            .map(|x| x.as_f64().expect("number"))
            .collect()
    };
    let mut placed = Vec::new();
    for e in &entries {
        let s = f32s(&e["scale"]);
        let mesh = read_obj(
            e["mesh"].as_str().expect("mesh path"),
            [s[0] as f32, s[1] as f32, s[2] as f32],
        );
        let p = f32s(&e["position"]);
        let q = f32s(&e["quaternion_xyzw"]);
        let pose = Isometry3::from_parts(
            Translation3::new(p[0], p[1], p[2]),
            UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[3], q[0], q[1], q[2])),
        );
        placed.push((mesh, pose));
    }
    let triangles: usize = placed.iter().map(|(m, _)| m.triangles.len()).sum();
    let fy = 240.0 / 25f64.to_radians().tan();
    let intrinsics = Intrinsics {
        fx: fy,
        fy,
        cx: 359.5,
        cy: 239.5,
        width: 720,
        height: 480,
        distortion: None,
    };
    let camera = Camera::look_at(
        intrinsics,
        Point3::new(1.125, 0.825, 0.9),
        Point3::new(0.0, 0.0, 0.35),
        Vector3::z(),
    )
    .expect("valid camera");
    let raster = Rasterizer::new(&camera);
    let items: Vec<RenderItem> = placed
        .iter()
        .enumerate()
        .map(|(i, (mesh, pose))| RenderItem {
            mesh,
            world_from_mesh: *pose,
            label: i as u16 + 1,
            closed_triangles: 0,
        })
        .collect();
    let mut out = RenderOutput::new(720, 480);
    raster.render_into(&items, &mut out);
    eprintln!(
        "scene file: {} meshes, {triangles} triangles, coverage {} px, min {:.3} ms/frame",
        items.len(),
        out.coverage(),
        min_time_ms(200, || raster.render_into(&items, &mut out))
    );
    let frames: Vec<Vec<RenderItem>> = (0..16).map(|_| items.clone()).collect();
    eprintln!(
        "scene file: render_frames of 16 frames on {} rayon threads: min {:.3} ms/frame",
        rayon::current_num_threads(),
        min_time_ms(20, || {
            std::hint::black_box(raster.render_frames(&frames));
        }) / 16.0
    );
    let mut group = c.benchmark_group("raster_720x480_scene_file");
    group.throughput(Throughput::Elements(1));
    group.bench_function("render_into_1_frame", |b| {
        b.iter(|| raster.render_into(&items, &mut out))
    });
    group.finish();
}

criterion_group!(benches, bench, bench_scene_file);
criterion_main!(benches);
