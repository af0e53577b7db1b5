use super::lanes::LANE_MASKS;
use super::pixels::{depth_key, Keys, LabelDepth, Pixels, BACKGROUND_KEY};
use super::*;
use wide::f32x4;

#[test]
fn rasterizer_is_send_sync() {
    fn assert_send_sync<T: Send + Sync>() {}
    assert_send_sync::<Rasterizer>();
}

use nalgebra::{Point3, Translation3, UnitQuaternion};

/// Deterministic xorshift generator in [0, 1).
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f32 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// A dense random mesh around `centre`: clusters of tiny triangles (many
/// sub-pixel) sharing vertices, plus a few large ones.
fn dense_mesh(rng: &mut Rng, centre: [f32; 3], spread: f32, size: f32, n: usize) -> TriMesh {
    let mut vertices = Vec::new();
    let mut triangles = Vec::new();
    for _ in 0..n {
        let c = [
            centre[0] + spread * (rng.next() - 0.5),
            centre[1] + spread * (rng.next() - 0.5),
            centre[2] + spread * (rng.next() - 0.5),
        ];
        let s = if rng.next() < 0.05 { size * 30.0 } else { size };
        let base = vertices.len() as u32;
        for _ in 0..4 {
            vertices.push(Point3::new(
                c[0] + s * (rng.next() - 0.5),
                c[1] + s * (rng.next() - 0.5),
                c[2] + s * (rng.next() - 0.5),
            ));
        }
        triangles.push([base, base + 1, base + 2]);
        triangles.push([base + 2, base + 1, base + 3]);
        triangles.push([base, base + 3, base + 1]);
    }
    TriMesh {
        vertices,
        triangles,
    }
}

/// Triangles of 0 to 7 pixels anywhere in (and around) a small image,
/// so that every class occurs, also touching the image borders and the
/// last pixels of the buffer: same output as the reference.
#[test]
fn size_classes_match_reference_at_borders() {
    use crate::camera::Intrinsics;
    let (w, h) = (37u32, 23u32);
    let intrinsics = Intrinsics {
        fx: 100.0,
        fy: 100.0,
        cx: 18.0,
        cy: 11.0,
        width: w,
        height: h,
        distortion: None,
    };
    let camera = Camera::look_at(
        intrinsics,
        nalgebra::Point3::new(0.0, 0.0, 0.0),
        nalgebra::Point3::new(0.0, 0.0, 1.0),
        nalgebra::Vector3::y(),
    )
    .expect("camera");
    let rasterizer = Rasterizer::new(&camera);
    let mut rng = Rng(0x2545_f491_4f6c_dd1d);
    let mut drawn = 0;
    for case in 0..60 {
        let mut vertices = Vec::new();
        let mut triangles = Vec::new();
        let max_size = [1.5, 3.0, 7.0][case % 3];
        for t in 0..400u32 {
            // Pixel-space centre, biased towards the bottom-right corner
            // in a third of the cases; 1 px = 0.01 m at z = 1.
            let corner = case % 3 == 1 && t % 2 == 0;
            let (u, v) = if corner {
                (w as f32 - 4.0 * rng.next(), h as f32 - 4.0 * rng.next())
            } else {
                (
                    (w as f32 + 4.0) * rng.next() - 2.0,
                    (h as f32 + 4.0) * rng.next() - 2.0,
                )
            };
            let z = 1.0 + rng.next();
            for _ in 0..3 {
                let du = max_size * (rng.next() - 0.5);
                let dv = max_size * (rng.next() - 0.5);
                // Snap some vertices to pixel centres and edges.
                let snap = |p: f32| {
                    if rng.0 % 4 == 0 {
                        (p * 2.0).round() / 2.0
                    } else {
                        p
                    }
                };
                let (pu, pv) = (snap(u + du), snap(v + dv));
                vertices.push(nalgebra::Point3::new(
                    (pu - 18.0) * 0.01 * z,
                    (pv - 11.0) * 0.01 * z,
                    z,
                ));
            }
            triangles.push([3 * t, 3 * t + 1, 3 * t + 2]);
        }
        let mesh = TriMesh {
            vertices,
            triangles,
        };
        let items = [RenderItem {
            mesh: &mesh,
            world_from_mesh: Isometry3::identity(),
            label: 1 + (case % 3) as u16,
            closed_triangles: if case % 2 == 1 { usize::MAX } else { 0 },
        }];
        let fast = rasterizer.render(&items);
        let mut reference = RenderOutput::new(w, h);
        rasterizer.draw_items_reference(&items, &rasterizer.pinhole, &mut reference);
        assert_eq!(fast.labels, reference.labels, "case {case}");
        for (a, b) in fast.depth_m.iter().zip(&reference.depth_m) {
            assert_eq!(a.to_bits(), b.to_bits(), "case {case}");
        }
        assert_eq!(rasterizer.render_labels(&items), reference.labels);
        drawn += fast.coverage();
    }
    assert!(drawn > 5000, "{drawn}");
}

/// Packed keys order as the depth test (nearer wins, then the lower
/// label) for depths of any sign and infinities, and the packed pixel
/// buffer's depth tests (single, four in a row, four anywhere, spans)
/// give the labels of separate depth and label buffers.
#[test]
fn packed_keys_match_separate_buffers() {
    let mut rng = Rng(0x1234_5678_9abc_def1);
    let depths = [
        f32::NEG_INFINITY,
        -3.5,
        -1e-30,
        1e-30,
        0.01,
        0.5,
        0.5000001,
        1.0,
        7.25,
        1e30,
        f32::INFINITY,
    ];
    for &a in &depths {
        for &b in &depths {
            for (la, lb) in [(1u16, 2u16), (2, 1), (3, 3)] {
                let float_wins = a < b || (a == b && la < lb);
                assert_eq!(depth_key(a, la) < depth_key(b, lb), float_wins, "{a} {b}");
            }
        }
    }
    assert_eq!(depth_key(f32::INFINITY, 0), BACKGROUND_KEY);
    let n = 64;
    let mut labels = vec![0u16; n];
    let mut depth_m = vec![f32::INFINITY; n];
    let mut keys = vec![BACKGROUND_KEY; n];
    let z_of = |rng: &mut Rng| {
        // Few distinct depths, so that ties occur.
        let z = 0.5 + (rng.next() * 8.0).floor() * 0.25;
        if rng.next() < 0.05 {
            -z
        } else {
            z
        }
    };
    for step in 0..4000 {
        let label = 1 + (rng.next() * 5.0) as u16;
        let mut separate = LabelDepth {
            labels: &mut labels,
            depth_m: &mut depth_m,
        };
        let mut packed = Keys { keys: &mut keys };
        // Indices reach past the end: ignored by both.
        let idx = (rng.next() * (n + 6) as f32) as usize;
        let z = f32x4::from([
            z_of(&mut rng),
            z_of(&mut rng),
            z_of(&mut rng),
            z_of(&mut rng),
        ]);
        let bits = (rng.next() * 16.0) as i32;
        match step % 4 {
            0 => {
                let covered = bits & 1 != 0;
                let z = z.to_array()[0];
                separate.depth_test(idx, z, label, covered);
                packed.depth_test(idx, z, label, covered);
            }
            1 => {
                let covered = LANE_MASKS[bits as usize];
                separate.depth_test_x4(idx, z, label, covered);
                packed.depth_test_x4(idx, z, label, covered);
            }
            2 => {
                let idx: [usize; 4] =
                    std::array::from_fn(|_| (rng.next() * (n + 2) as f32) as usize);
                separate.depth_test_lanes(idx, z, label, bits);
                packed.depth_test_lanes(idx, z, label, bits);
            }
            _ => {
                let end = idx + (rng.next() * 5.0) as usize;
                let zs = z.to_array();
                let z_at = |i: &mut usize| {
                    *i += 1;
                    ((bits >> (*i % 4)) & 1 != 0).then_some(zs[*i % 4])
                };
                let (mut i, mut j) = (0, 0);
                let a = separate.depth_test_span(idx, end, label, || z_at(&mut i));
                let b = packed.depth_test_span(idx, end, label, || z_at(&mut j));
                assert_eq!(a, b);
            }
        }
        for i in 0..n {
            assert_eq!(keys[i], depth_key(depth_m[i], labels[i]), "step {step}");
        }
    }
    assert!(labels.iter().filter(|&&l| l != 0).count() > n / 2);
}

#[test]
fn fast_path_matches_reference() {
    use crate::camera::Intrinsics;
    let intrinsics = Intrinsics {
        fx: 300.0,
        fy: 310.0,
        cx: 79.5,
        cy: 59.5,
        width: 160,
        height: 120,
        distortion: None,
    };
    let camera = Camera::look_at(
        intrinsics,
        nalgebra::Point3::new(0.0, 0.0, 0.0),
        nalgebra::Point3::new(0.0, 0.0, 1.0),
        nalgebra::Vector3::y(),
    )
    .expect("camera");
    let rasterizer = Rasterizer::new(&camera);
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
    for case in 0..40 {
        let meshes: Vec<TriMesh> = (0..3)
            .map(|i| {
                let z = 0.3 + rng.next() * 1.5;
                let spread = 0.2 + rng.next() * 0.6;
                // Some meshes reach behind the near plane and outside
                // the image.
                let spread = if case % 5 == 0 && i == 0 { 2.0 } else { spread };
                let size = 0.0005 + rng.next() * 0.004;
                dense_mesh(&mut rng, [0.0, 0.0, z], spread, size, 3000)
            })
            .collect();
        let items: Vec<RenderItem> = meshes
            .iter()
            .enumerate()
            .map(|(i, mesh)| RenderItem {
                mesh,
                world_from_mesh: Isometry3::from_parts(
                    Translation3::new(0.0, 0.0, 0.0),
                    UnitQuaternion::from_euler_angles(0.01 * case as f64, 0.0, 0.0),
                ),
                label: 1 + (i as u16 % 2),
                closed_triangles: if case % 2 == 1 { usize::MAX } else { 0 },
            })
            .collect();
        let fast = rasterizer.render(&items);
        let mut reference = RenderOutput::new(160, 120);
        rasterizer.draw_items_reference(&items, &rasterizer.pinhole, &mut reference);
        assert!(
            fast.coverage() > 200,
            "case {case}: coverage {}",
            fast.coverage()
        );
        assert_eq!(fast.labels, reference.labels, "case {case}");
        for (a, b) in fast.depth_m.iter().zip(&reference.depth_m) {
            assert_eq!(a.to_bits(), b.to_bits(), "case {case}");
        }
    }
}

/// Label maps rendered one after another on one thread (reusing its
/// frame buffers, which are reset only where something was drawn) equal
/// fresh full renders: meshes crossing the near plane and the image
/// border, in a corner, none at all, and drawn over a non-zero map.
#[test]
fn label_frames_reused_across_frames_match_full_renders() {
    use crate::camera::Intrinsics;
    let camera = Camera::look_at(
        Intrinsics::centered(120.0, 96, 64),
        nalgebra::Point3::new(0.0, 0.0, 0.0),
        nalgebra::Point3::new(0.0, 0.0, 1.0),
        nalgebra::Vector3::y(),
    )
    .expect("camera");
    let rasterizer = Rasterizer::new(&camera);
    let sphere = TriMesh::sphere(0.3, 24);
    let cube = TriMesh::cuboid([0.2, 0.2, 0.2]);
    let at = |mesh, x: f64, y: f64, z: f64, label| RenderItem {
        mesh,
        world_from_mesh: Isometry3::translation(x, y, z),
        label,
        closed_triangles: 0,
    };
    let scenes: Vec<Vec<RenderItem>> = vec![
        vec![at(&sphere, 0.0, 0.0, 1.5, 1), at(&cube, 0.1, 0.0, 1.2, 2)],
        // Crosses the near plane: clipped.
        vec![at(&sphere, 0.1, 0.05, 0.1, 3)],
        vec![at(&cube, 0.55, 0.35, 1.3, 1)],
        vec![],
        // Partly outside the image.
        vec![at(&sphere, -0.7, 0.0, 1.0, 2), at(&cube, 0.0, 0.4, 1.0, 5)],
        vec![at(&cube, -0.3, -0.2, 2.0, 4)],
    ];
    for round in 0..2 {
        for (i, items) in scenes.iter().enumerate() {
            let expected = rasterizer.render(items).labels;
            assert_eq!(rasterizer.render_labels(items), expected, "scene {i}");
            let mut over = vec![9u16; expected.len()];
            rasterizer.render_labels_into(items, &mut over);
            for (o, &e) in over.iter().zip(&expected) {
                assert_eq!(*o, if e != 0 { e } else { 9 }, "scene {i} round {round}");
            }
        }
    }
    assert!(rasterizer.render(&scenes[1]).coverage() > 1000);
}

#[test]
fn culling_closed_components_changes_nothing() {
    use crate::camera::Intrinsics;
    // An open box (one face missing: its inside shows), an inward-wound
    // closed box and a sphere, as one mesh with closed components first.
    let mut open = TriMesh::cuboid([0.3, 0.3, 0.3]);
    open.triangles.truncate(open.triangles.len() - 2);
    let inward = TriMesh::cuboid([0.2, 0.25, 0.15])
        .transformed(&Isometry3::translation(0.4, 0.0, 0.0))
        .flipped();
    let sphere = TriMesh::sphere(0.15, 24).transformed(&Isometry3::translation(-0.4, 0.1, 0.0));
    let mut mesh = TriMesh::default();
    mesh.append(&open);
    mesh.append(&inward);
    mesh.append(&sphere);
    let (mesh, n_closed) = mesh.closed_components_first();
    assert_eq!(n_closed, inward.triangles.len() + sphere.triangles.len());
    let mut rng = Rng(0x2545_f491_4f6c_dd1d);
    for case in 0..24 {
        let angle = f64::from(rng.next()) * std::f64::consts::TAU;
        let height = -0.8 + 1.6 * f64::from(rng.next());
        let eye = nalgebra::Point3::new(1.6 * angle.cos(), 1.6 * angle.sin(), height);
        let camera = Camera::look_at(
            Intrinsics::centered(150.0, 160, 120),
            eye,
            nalgebra::Point3::origin(),
            nalgebra::Vector3::z(),
        )
        .expect("camera");
        let rasterizer = Rasterizer::new(&camera);
        let item = |closed_triangles| RenderItem {
            mesh: &mesh,
            world_from_mesh: Isometry3::identity(),
            label: 3,
            closed_triangles,
        };
        let culled = rasterizer.render(&[item(n_closed)]);
        let full = rasterizer.render(&[item(0)]);
        assert!(full.coverage() > 1000, "case {case}: {}", full.coverage());
        assert_eq!(culled.labels, full.labels, "case {case}");
        for (a, b) in culled.depth_m.iter().zip(&full.depth_m) {
            assert!(
                a == b || (a - b).abs() <= 1e-5 * b.abs(),
                "case {case}: {a} vs {b}"
            );
        }
    }
}
