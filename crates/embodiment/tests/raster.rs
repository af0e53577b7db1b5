//! Rasterizer tests: silhouettes and depth against closed forms,
//! occlusion, clipping, distortion, the top-left fill rule and determinism.

use bridgev2w_embodiment::camera::{Camera, Distortion};
use bridgev2w_embodiment::mesh::TriMesh;
use bridgev2w_embodiment::raster::{Rasterizer, RenderItem, RenderOutput};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use proptest::prelude::*;

use crate::cameras;

use cameras::{identity_camera, intrinsics, lens};

// ---------------------------------------------------------------- raster

fn at(x: f64, y: f64, z: f64) -> Isometry3<f64> {
    Isometry3::translation(x, y, z)
}

fn iou(a: &[bool], b: &[bool]) -> f64 {
    let inter = a.iter().zip(b).filter(|(x, y)| **x && **y).count();
    let union = a.iter().zip(b).filter(|(x, y)| **x || **y).count();
    inter as f64 / union.max(1) as f64
}

/// Ray from the origin along `d` (unit) hits a sphere.
fn ray_hits_sphere(d: &Vector3<f64>, centre: &Vector3<f64>, radius: f64) -> bool {
    let t = d.dot(centre);
    t > 0.0 && (centre - d * t).norm_squared() <= radius * radius
}

#[test]
fn sphere_silhouette_matches_analytic() {
    for distortion in [None, Some(lens())] {
        let mut k = intrinsics(320, 240);
        k.distortion = distortion;
        let cam = Camera::new(k, Isometry3::identity()).expect("valid");
        let centre = Vector3::new(0.05, -0.03, 1.0);
        let radius = 0.15;
        let mesh = TriMesh::sphere(radius as f32, 256);
        let out = Rasterizer::new(&cam).render(&[RenderItem {
            mesh: &mesh,
            world_from_mesh: at(centre.x, centre.y, centre.z),
            label: 3,
            closed_triangles: 0,
        }]);
        let rendered: Vec<bool> = out.labels.iter().map(|&l| l == 3).collect();
        let mut analytic = Vec::new();
        for v in 0..k.height {
            for u in 0..k.width {
                let d = cam.pixel_ray(f64::from(u), f64::from(v));
                analytic.push(ray_hits_sphere(&d, &centre, radius));
            }
        }
        let score = iou(&rendered, &analytic);
        assert!(score >= 0.99, "IoU {score} (distortion {distortion:?})");
        assert!(out.coverage() > 3000);
        assert!(out.labels.iter().all(|&l| l == 0 || l == 3));
    }
}

/// Ray from the origin along `d` hits an axis-aligned box (slab test).
fn ray_hits_box(d: &Vector3<f64>, lo: &Vector3<f64>, hi: &Vector3<f64>) -> Option<f64> {
    let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
    for i in 0..3 {
        let (a, b) = (lo[i] / d[i], hi[i] / d[i]);
        t0 = t0.max(a.min(b));
        t1 = t1.min(a.max(b));
    }
    (t0 <= t1).then_some(t0)
}

#[test]
fn rotated_box_silhouette_and_depth_match_analytic() {
    // Camera looking at an axis-aligned box from an oblique pose; the test
    // works in the camera frame by moving the box into it.
    let k = intrinsics(320, 240);
    let cam = Camera::look_at(
        k,
        Point3::new(0.9, -0.7, 0.6),
        Point3::new(0.0, 0.0, 0.0),
        Vector3::z(),
    )
    .expect("valid");
    let size = [0.3, 0.2, 0.25];
    let mesh = TriMesh::cuboid(size.map(|s| s as f32));
    let out = Rasterizer::new(&cam).render(&[RenderItem {
        mesh: &mesh,
        world_from_mesh: Isometry3::identity(),
        label: 1,
        closed_triangles: 0,
    }]);
    let eye = cam.world_from_camera.translation.vector;
    let lo = Vector3::new(-size[0] / 2.0, -size[1] / 2.0, -size[2] / 2.0) - eye;
    let hi = Vector3::new(size[0] / 2.0, size[1] / 2.0, size[2] / 2.0) - eye;
    let mut analytic = Vec::new();
    let mut max_depth_err = 0.0f64;
    let camera_z = cam.world_from_camera.rotation * Vector3::z();
    for v in 0..k.height {
        for u in 0..k.width {
            let d = cam.pixel_ray(f64::from(u), f64::from(v));
            let hit = ray_hits_box(&d, &lo, &hi);
            analytic.push(hit.is_some());
            let i = (v * k.width + u) as usize;
            if let (Some(t), true) = (hit, out.labels[i] == 1) {
                let z = t * d.dot(&camera_z);
                max_depth_err = max_depth_err.max((f64::from(out.depth_m[i]) - z).abs());
            }
        }
    }
    let rendered: Vec<bool> = out.labels.iter().map(|&l| l == 1).collect();
    let score = iou(&rendered, &analytic);
    assert!(score >= 0.99, "IoU {score}");
    // Edge pixels may hit the analytic box on a different face; interior
    // depths are exact.
    assert!(max_depth_err < 0.05, "max depth error {max_depth_err}");
}

#[test]
fn plane_depth_and_occlusion() {
    let cam = identity_camera(160, 120);
    let raster = Rasterizer::new(&cam);
    // A wall facing the camera at z = 2 (box face at 2.0) and a nearer box.
    let wall = TriMesh::cuboid([3.0, 3.0, 0.2]);
    let near_box = TriMesh::cuboid([0.2, 0.2, 0.2]);
    let items = [
        RenderItem {
            mesh: &wall,
            world_from_mesh: at(0.0, 0.0, 2.1),
            label: 1,
            closed_triangles: 0,
        },
        RenderItem {
            mesh: &near_box,
            world_from_mesh: at(0.0, 0.0, 1.1),
            label: 2,
            closed_triangles: 0,
        },
    ];
    for order in [[0, 1], [1, 0]] {
        let items = [items[order[0]], items[order[1]]];
        let out = raster.render(&items);
        assert_eq!(out.coverage(), 160 * 120);
        let centre = (60 * 160 + 80) as usize;
        assert_eq!(out.labels[centre], 2);
        assert!(
            (out.depth_m[centre] - 1.0).abs() < 1e-3,
            "{}",
            out.depth_m[centre]
        );
        let corner = (5 * 160 + 5) as usize;
        assert_eq!(out.labels[corner], 1);
        assert!(
            (out.depth_m[corner] - 2.0).abs() < 1e-3,
            "{}",
            out.depth_m[corner]
        );
        let max_wall_err = out
            .labels
            .iter()
            .zip(&out.depth_m)
            .filter(|(l, _)| **l == 1)
            .map(|(_, d)| (d - 2.0).abs())
            .fold(0.0f32, f32::max);
        assert!(max_wall_err < 1e-3, "{max_wall_err}");
        // The near box: 0.2 m wide at 1 m with fx = 500 -> about 100 px wide.
        let n = out.labels.iter().filter(|&&l| l == 2).count();
        assert!((9000..=11000).contains(&n), "{n}");
    }
}

#[test]
fn tilted_plane_depth_is_perspective_correct() {
    let cam = identity_camera(200, 150);
    // A big quad on the plane z = 1 + 0.5 x.
    let mesh = TriMesh {
        vertices: vec![
            Point3::new(-1.0, -1.0, 0.5),
            Point3::new(1.0, -1.0, 1.5),
            Point3::new(1.0, 1.0, 1.5),
            Point3::new(-1.0, 1.0, 0.5),
        ],
        triangles: vec![[0, 1, 2], [0, 2, 3]],
    };
    let out = Rasterizer::new(&cam).render(&[RenderItem {
        mesh: &mesh,
        world_from_mesh: at(0.0, 0.0, 1.0),
        label: 1,
        closed_triangles: 0,
    }]);
    let k = cam.intrinsics;
    let mut worst = 0.0f64;
    for v in 0..k.height {
        for u in 0..k.width {
            let i = (v * k.width + u) as usize;
            if out.labels[i] == 0 {
                continue;
            }
            // z = 2 + 0.5 x with x = z (u - cx) / fx -> z = 2 / (1 - 0.5 (u - cx) / fx)
            let z = 2.0 / (1.0 - 0.5 * (f64::from(u) - k.cx) / k.fx);
            worst = worst.max((f64::from(out.depth_m[i]) - z).abs());
        }
    }
    assert!(out.coverage() == 200 * 150);
    assert!(worst < 1e-3, "worst depth error {worst}");
}

#[test]
fn shared_edges_cover_each_pixel_exactly_once() {
    let cam = identity_camera(97, 71);
    let raster = Rasterizer::new(&cam);
    // A fan of triangles around a centre (many shared edges at odd slopes),
    // plus a quad split along its diagonal.
    let mut fan = TriMesh::default();
    fan.vertices.push(Point3::new(0.013, -0.021, 1.0));
    let n = 13;
    for i in 0..n {
        let a = 2.0 * std::f32::consts::PI * i as f32 / n as f32 + 0.1;
        fan.vertices.push(Point3::new(
            0.3 * a.cos(),
            0.25 * a.sin(),
            1.0 + 0.1 * a.sin(),
        ));
    }
    for i in 0..n {
        fan.triangles.push([0, 1 + i, 1 + (i + 1) % n]);
    }
    let quad = TriMesh {
        vertices: vec![
            Point3::new(-0.0712, -0.0533, 1.0),
            Point3::new(0.0811, -0.0471, 1.0),
            Point3::new(0.0733, 0.0627, 1.0),
            Point3::new(-0.0641, 0.0544, 1.0),
        ],
        // Mixed winding (two-sided).
        triangles: vec![[0, 1, 2], [0, 3, 2]],
    };
    for mesh in [&fan, &quad] {
        let whole = raster.render(&[RenderItem {
            mesh,
            world_from_mesh: Isometry3::identity(),
            label: 1,
            closed_triangles: 0,
        }]);
        let mut per_pixel = vec![0u32; whole.labels.len()];
        let mut sum = 0;
        for tri in &mesh.triangles {
            let single = TriMesh {
                vertices: mesh.vertices.clone(),
                triangles: vec![*tri],
            };
            let out = raster.render(&[RenderItem {
                mesh: &single,
                world_from_mesh: Isometry3::identity(),
                label: 1,
                closed_triangles: 0,
            }]);
            sum += out.coverage();
            for (c, &l) in per_pixel.iter_mut().zip(&out.labels) {
                *c += u32::from(l != 0);
            }
        }
        assert!(whole.coverage() > 100);
        assert_eq!(sum, whole.coverage(), "double coverage or holes");
        assert!(per_pixel.iter().all(|&c| c <= 1));
        // No holes: covered pixels of the union equal the whole render.
        for (c, &l) in per_pixel.iter().zip(&whole.labels) {
            assert_eq!(*c == 1, l != 0);
        }
    }
    // A fully interior region: the fan's pixels form a hole-free blob
    // (every covered pixel's 4 neighbours inside the fan's inner disc are covered).
    let whole = raster.render(&[RenderItem {
        mesh: &fan,
        world_from_mesh: Isometry3::identity(),
        label: 1,
        closed_triangles: 0,
    }]);
    for v in 25..46u32 {
        for u in 35..62u32 {
            assert_eq!(whole.labels[(v * 97 + u) as usize], 1, "hole at ({u}, {v})");
        }
    }
}

#[test]
fn near_plane_clipping() {
    let cam = identity_camera(100, 100);
    let raster = Rasterizer::new(&cam);
    // A triangle from behind the camera (z = -1) to in front (z = 1).
    let mesh = TriMesh {
        vertices: vec![
            Point3::new(-0.5, 0.02, -1.0),
            Point3::new(0.5, 0.02, -1.0),
            Point3::new(0.0, 0.02, 1.0),
        ],
        triangles: vec![[0, 1, 2]],
    };
    let out = raster.render(&[RenderItem {
        mesh: &mesh,
        world_from_mesh: Isometry3::identity(),
        label: 1,
        closed_triangles: 0,
    }]);
    // The plane y = 0.02 is seen below the horizon only: rows v > cy.
    assert!(out.coverage() > 500, "{}", out.coverage());
    let k = cam.intrinsics;
    for v in 0..100u32 {
        for u in 0..100u32 {
            let i = (v * 100 + u) as usize;
            if out.labels[i] != 0 {
                assert!(f64::from(v) > k.cy, "pixel ({u}, {v}) above the horizon");
                let d = out.depth_m[i];
                assert!((0.0099..=1.0 + 1e-3).contains(&d), "depth {d}");
                // Depth of the plane y = 0.02 seen at row v: z = 0.02 fy / (v - cy).
                let z = 0.02 * k.fy / (f64::from(v) - k.cy);
                assert!((f64::from(d) - z).abs() < 1e-3 * z.max(1.0), "{d} vs {z}");
            }
        }
    }
    // Entirely behind the camera: nothing.
    let behind = TriMesh {
        vertices: mesh
            .vertices
            .iter()
            .map(|p| Point3::new(p.x, p.y, -2.0 - p.z))
            .collect(),
        triangles: mesh.triangles.clone(),
    };
    let out = raster.render(&[RenderItem {
        mesh: &behind,
        world_from_mesh: Isometry3::identity(),
        label: 1,
        closed_triangles: 0,
    }]);
    assert_eq!(out.coverage(), 0);
    // A camera inside a box sees the box all around: every pixel covered.
    let room = TriMesh::cuboid([4.0, 4.0, 4.0]);
    let out = raster.render(&[RenderItem {
        mesh: &room,
        world_from_mesh: Isometry3::identity(),
        label: 5,
        closed_triangles: 0,
    }]);
    assert_eq!(out.coverage(), 100 * 100);
    assert!(out.depth_m.iter().all(|&d| (d - 2.0).abs() < 1e-3));
}

#[test]
fn distorted_render_matches_distorted_projection() {
    let mut k = intrinsics(320, 240);
    k.distortion = Some(Distortion {
        k1: -0.25,
        k2: 0.08,
        p1: 0.002,
        p2: -0.001,
        k3: 0.0,
    });
    let cam = Camera::new(k, Isometry3::identity()).expect("valid");
    let raster = Rasterizer::new(&cam);
    let mesh = TriMesh::sphere(0.03, 64);
    for centre in [
        Point3::new(0.0, 0.0, 1.0),
        Point3::new(0.25, 0.18, 1.0),
        Point3::new(-0.28, -0.2, 1.0),
    ] {
        let out = raster.render(&[RenderItem {
            mesh: &mesh,
            world_from_mesh: at(centre.x, centre.y, centre.z),
            label: 7,
            closed_triangles: 0,
        }]);
        let (mut su, mut sv, mut n) = (0.0, 0.0, 0.0);
        for (i, &l) in out.labels.iter().enumerate() {
            if l == 7 {
                su += (i % 320) as f64;
                sv += (i / 320) as f64;
                n += 1.0;
            }
        }
        assert!(n > 50.0, "{n}");
        let p = cam.project(&centre).expect("in front");
        let pinhole = identity_camera(320, 240)
            .project(&centre)
            .expect("in front");
        assert!(
            (su / n - p.x).abs() < 1.0 && (sv / n - p.y).abs() < 1.0,
            "centroid ({}, {}) vs projection {p}",
            su / n,
            sv / n
        );
        if centre.x != 0.0 {
            // The distortion is large enough that ignoring it would fail.
            assert!((pinhole - p).norm() > 3.0);
        }
    }
}

#[test]
fn render_frames_is_deterministic_across_thread_counts() {
    let cam = Camera::look_at(
        intrinsics(160, 120),
        Point3::new(1.0, 0.6, 0.8),
        Point3::origin(),
        Vector3::z(),
    )
    .expect("valid");
    let raster = Rasterizer::new(&cam);
    let sphere = TriMesh::sphere(0.1, 32);
    let capsule = TriMesh::capsule(0.05, 0.3, 24);
    let frames: Vec<Vec<RenderItem>> = (0..12)
        .map(|f| {
            let t = f64::from(f) * 0.1;
            vec![
                RenderItem {
                    mesh: &sphere,
                    world_from_mesh: at(0.1 * t.cos(), 0.1 * t.sin(), 0.0),
                    label: 1,
                    closed_triangles: 0,
                },
                RenderItem {
                    mesh: &capsule,
                    world_from_mesh: Isometry3::from_parts(
                        Translation3::new(0.0, 0.05, 0.05),
                        UnitQuaternion::from_euler_angles(t, 0.3, 0.0),
                    ),
                    label: 2,
                    closed_triangles: 0,
                },
            ]
        })
        .collect();
    let run = |threads: usize| -> Vec<RenderOutput> {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("pool")
            .install(|| raster.render_frames(&frames))
    };
    let one = run(1);
    let two = run(2);
    assert_eq!(one.len(), 12);
    assert!(one.iter().all(|o| o.coverage() > 100));
    for (a, b) in one.iter().zip(&two) {
        assert_eq!(a.labels, b.labels);
        assert_eq!(
            a.depth_m.iter().map(|d| d.to_bits()).collect::<Vec<_>>(),
            b.depth_m.iter().map(|d| d.to_bits()).collect::<Vec<_>>()
        );
    }
    // Sequential render agrees too.
    assert_eq!(raster.render(&frames[3]), one[3]);
}

#[test]
fn empty_scene_and_buffer_reuse() {
    let cam = identity_camera(40, 30);
    let raster = Rasterizer::new(&cam);
    let out = raster.render(&[]);
    assert_eq!((out.width, out.height), (40, 30));
    assert_eq!(out.coverage(), 0);
    assert!(out.mask().iter().all(|&m| m == 0));
    assert!(out.depth_m.iter().all(|d| d.is_infinite()));

    let mesh = TriMesh::sphere(0.1, 16);
    let item = RenderItem {
        mesh: &mesh,
        world_from_mesh: at(0.0, 0.0, 1.0),
        label: 4,
        closed_triangles: 0,
    };
    let mut reused = RenderOutput::new(3, 2);
    raster.render_into(&[item], &mut reused);
    assert_eq!(reused, raster.render(&[item]));
    assert_eq!(
        reused.mask().iter().filter(|&&m| m == 1).count(),
        reused.coverage()
    );
    assert!(reused.coverage() > 0);
    raster.render_into(&[], &mut reused);
    assert_eq!(reused.coverage(), 0);
    reused.clear();
    assert!(reused.depth_m.iter().all(|d| d.is_infinite()));

    // Bad indices and label 0 are ignored without panicking.
    let broken = TriMesh {
        vertices: vec![Point3::origin()],
        triangles: vec![[0, 1, 2]],
    };
    let out = raster.render(&[
        RenderItem {
            mesh: &broken,
            world_from_mesh: at(0.0, 0.0, 1.0),
            label: 1,
            closed_triangles: 0,
        },
        RenderItem {
            mesh: &mesh,
            world_from_mesh: at(0.0, 0.0, 1.0),
            label: 0,
            closed_triangles: 0,
        },
    ]);
    assert_eq!(out.coverage(), 0);
}

/// Camera-frame point at depth `z` that projects exactly to pixel `(u, v)`.
fn unproject(cam: &Camera, u: f64, v: f64, z: f64) -> Point3<f32> {
    let k = &cam.intrinsics;
    Point3::new(
        ((u - k.cx) / k.fx * z) as f32,
        ((v - k.cy) / k.fy * z) as f32,
        z as f32,
    )
}

#[test]
fn top_left_rule_on_pixel_centres() {
    let cam = identity_camera(97, 71);
    let raster = Rasterizer::new(&cam);
    let render = |mesh: &TriMesh| {
        raster.render(&[RenderItem {
            mesh,
            world_from_mesh: Isometry3::identity(),
            label: 1,
            closed_triangles: 0,
        }])
    };
    // An axis-aligned rectangle with corners on pixel centres, split along
    // its diagonal: top and left edges are drawn, bottom and right are not,
    // so exactly 20 x 10 pixels are covered.
    let rect = TriMesh {
        vertices: vec![
            unproject(&cam, 10.0, 10.0, 1.0),
            unproject(&cam, 30.0, 10.0, 1.0),
            unproject(&cam, 30.0, 20.0, 1.0),
            unproject(&cam, 10.0, 20.0, 1.0),
        ],
        triangles: vec![[0, 1, 2], [2, 3, 0]],
    };
    let out = render(&rect);
    assert_eq!(out.coverage(), 200);
    assert_eq!(out.labels[(10 * 97 + 10) as usize], 1);
    assert_eq!(out.labels[(19 * 97 + 29) as usize], 1);
    assert_eq!(out.labels[(20 * 97 + 15) as usize], 0);
    assert_eq!(out.labels[(15 * 97 + 30) as usize], 0);
    // A quad whose diagonal passes through pixel centres (slope 5/4).
    let quad = TriMesh {
        vertices: vec![
            unproject(&cam, 20.0, 10.0, 1.0),
            unproject(&cam, 70.0, 15.0, 1.3),
            unproject(&cam, 60.0, 60.0, 0.9),
            unproject(&cam, 25.0, 50.0, 1.1),
        ],
        triangles: vec![[0, 1, 2], [0, 2, 3]],
    };
    let whole = render(&quad);
    let mut total = 0;
    let mut counts = vec![0u32; whole.labels.len()];
    for tri in &quad.triangles {
        let single = TriMesh {
            vertices: quad.vertices.clone(),
            triangles: vec![*tri],
        };
        let out = render(&single);
        total += out.coverage();
        for (c, &l) in counts.iter_mut().zip(&out.labels) {
            *c += u32::from(l != 0);
        }
    }
    assert_eq!(total, whole.coverage());
    assert!(counts.iter().all(|&c| c <= 1));
    // Diagonal pixel centres (20 + 4k, 10 + 5k) strictly inside the quad are
    // covered by exactly one triangle.
    for k in 1..8u32 {
        let (u, v) = (20 + 4 * k, 10 + 5 * k);
        assert_eq!(counts[(v * 97 + u) as usize], 1, "({u}, {v})");
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]
    /// Two triangles sharing an edge, on opposite sides of it: every pixel is
    /// drawn at most once and the union has no holes along the edge.
    #[test]
    fn shared_edge_random(coords in proptest::collection::vec(-0.35f32..0.35, 8),
                          depths in proptest::collection::vec(0.5f32..2.0, 4)) {
        let cam = identity_camera(64, 48);
        let raster = Rasterizer::new(&cam);
        let v: Vec<Point3<f32>> = (0..4)
            .map(|i| Point3::new(coords[2 * i] * depths[i], coords[2 * i + 1] * depths[i], depths[i]))
            .collect();
        let p: Vec<_> = v
            .iter()
            .map(|q| cam.project(&q.cast::<f64>()).expect("in front"))
            .collect();
        let side = |c: usize| {
            (p[1].x - p[0].x) * (p[c].y - p[0].y) - (p[1].y - p[0].y) * (p[c].x - p[0].x)
        };
        prop_assume!(side(2) * side(3) < 0.0);
        let mesh = |triangles: Vec<[u32; 3]>| TriMesh { vertices: v.clone(), triangles };
        let render = |m: &TriMesh| {
            raster.render(&[RenderItem { mesh: m, world_from_mesh: Isometry3::identity(), label: 1 , closed_triangles: 0 }])
        };
        let first = render(&mesh(vec![[0, 1, 2]]));
        let second = render(&mesh(vec![[1, 0, 3]]));
        let both = render(&mesh(vec![[0, 1, 2], [1, 0, 3]]));
        for ((a, b), c) in first.labels.iter().zip(&second.labels).zip(&both.labels) {
            prop_assert!(!(*a != 0 && *b != 0), "pixel drawn twice");
            prop_assert_eq!(*a != 0 || *b != 0, *c != 0);
        }
        // No holes: a pixel centre clearly inside either triangle (by more
        // than the 1/256 px vertex snapping) is covered.
        let inside = |t: [usize; 3], x: f64, y: f64| {
            let e = |i: usize, j: usize| {
                let (a, b) = (p[t[i]], p[t[j]]);
                let len = ((b.x - a.x).powi(2) + (b.y - a.y).powi(2)).sqrt();
                ((b.x - a.x) * (y - a.y) - (b.y - a.y) * (x - a.x)) / len
            };
            let (e0, e1, e2) = (e(0, 1), e(1, 2), e(2, 0));
            let margin = 0.02;
            (e0 > margin && e1 > margin && e2 > margin) || (e0 < -margin && e1 < -margin && e2 < -margin)
        };
        for (i, &c) in both.labels.iter().enumerate() {
            let (x, y) = ((i % 64) as f64, (i / 64) as f64);
            if inside([0, 1, 2], x, y) || inside([1, 0, 3], x, y) {
                prop_assert!(c != 0, "hole at ({}, {})", x, y);
            }
        }
    }
}
