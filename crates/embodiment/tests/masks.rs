//! The full pipeline: URDF + joints + camera -> masks aligned with projections.

use bridgev2w_embodiment::camera::{Camera, Intrinsics};
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_embodiment::masks::{link_labels, render_trajectory, write_outputs, WriteOptions};
use bridgev2w_embodiment::robot::{LoadOptions, Robot};
use bridgev2w_io::npy::read_npy;
use nalgebra::{Point3, Vector3};

fn camera() -> Camera {
    let intr = Intrinsics::centered(500.0, 640, 480);
    Camera::look_at(
        intr,
        Point3::new(1.5, 0.0, 0.5),
        Point3::new(0.0, 0.0, 0.5),
        Vector3::z(),
    )
    .expect("camera")
}

/// A sphere carried by a prismatic joint: its mask centroid must sit on the
/// projection of the sphere centre computed by FK.
#[test]
fn mask_centroid_follows_forward_kinematics() {
    let urdf = r#"<robot name="slider">
      <link name="base"/>
      <link name="ball"><visual><origin xyz="0 0 0.5"/><geometry><sphere radius="0.05"/></geometry></visual></link>
      <joint name="slide" type="prismatic"><parent link="base"/><child link="ball"/><axis xyz="0 1 0"/>
        <limit lower="-0.4" upper="0.4" effort="1" velocity="1"/></joint>
    </robot>"#;
    let robot =
        Robot::from_urdf_str(urdf, "slider.urdf", None, &LoadOptions::default()).expect("urdf");
    let cam = camera();
    let joints: Vec<Vec<f64>> = (0..9).map(|i| vec![-0.4 + 0.1 * i as f64]).collect();
    let frames = render_trajectory(&robot, &cam, &joints, &|| {});
    for (q, f) in joints.iter().zip(&frames) {
        let (mut sx, mut sy, mut n) = (0.0, 0.0, 0.0);
        for (i, &l) in f.labels.iter().enumerate() {
            if l != 0 {
                assert_eq!(l, 2, "the ball is link 1 -> label 2");
                sx += (i % 640) as f64;
                sy += (i / 640) as f64;
                n += 1.0;
            }
        }
        assert!(n > 100.0);
        let c = cam.project(&Point3::new(0.0, q[0], 0.5)).expect("in front");
        // A sphere's silhouette centroid is within a fraction of a pixel of
        // the projected centre at this distance and field of view.
        assert!(
            (sx / n - c.x).abs() < 0.5 && (sy / n - c.y).abs() < 0.5,
            "q={q:?}: centroid ({}, {}) vs {c}",
            sx / n,
            sy / n
        );
    }
}

#[test]
fn builtin_robots_render_and_outputs_are_written() {
    let dir = tempfile::tempdir().expect("tmp");
    for name in ["franka", "dual-arm"] {
        let e = Embodiment::builtin(name).expect("builtin");
        let intr = Intrinsics::centered(300.0, 320, 240);
        let cam = Camera::look_at(
            intr,
            Point3::new(2.2, 0.6, 1.2),
            Point3::new(0.2, 0.0, 0.6),
            Vector3::z(),
        )
        .expect("cam");
        let joints = vec![e.home.clone(); 3];
        let frames = render_trajectory(&e.robot, &cam, &joints, &|| {});
        assert!(frames.iter().all(|f| f.coverage() > 500), "{name} visible");
        // Every label drawn names a link with geometry.
        let labels: Vec<u16> = link_labels(&e.robot).into_iter().map(|(l, _)| l).collect();
        assert!(frames[0]
            .labels
            .iter()
            .all(|l| *l == 0 || labels.contains(l)));
        let out = dir.path().join(name);
        let w = write_outputs(
            &out,
            &e.robot,
            &frames,
            WriteOptions {
                pngs: true,
                depth: true,
            },
        )
        .expect("write");
        assert!(w.empty_frames.is_empty());
        let masks = read_npy(&out.join("masks.npy")).expect("masks");
        assert_eq!(masks.shape, vec![3, 240, 320]);
        assert_eq!(masks.descr, "|u1");
        assert!(masks.data.iter().all(|&v| v == 0.0 || v == 1.0));
        let lab = read_npy(&out.join("labels.npy")).expect("labels");
        assert_eq!(lab.descr, "<u2");
        assert_eq!(
            read_npy(&out.join("depth.npy")).expect("depth").descr,
            "<f4"
        );
        assert!(out.join("frames/000002.png").is_file());
        let names: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("labels.json")).expect("json"))
                .expect("json");
        assert_eq!(names["labels"].as_array().map(Vec::len), Some(labels.len()));
    }
}

#[test]
fn camera_looking_away_gives_empty_frames() {
    let e = Embodiment::builtin("franka").expect("franka");
    let intr = Intrinsics::centered(300.0, 320, 240);
    let cam = Camera::look_at(
        intr,
        Point3::new(2.0, 0.0, 0.5),
        Point3::new(4.0, 0.0, 0.5),
        Vector3::z(),
    )
    .expect("cam");
    let frames = render_trajectory(&e.robot, &cam, std::slice::from_ref(&e.home), &|| {});
    let dir = tempfile::tempdir().expect("tmp");
    let w = write_outputs(
        dir.path(),
        &e.robot,
        &frames,
        WriteOptions {
            pngs: false,
            depth: false,
        },
    )
    .expect("write");
    assert_eq!(w.empty_frames, vec![0]);
}

/// Back-face culling of closed meshes must not change the output.
#[test]
fn back_face_culling_is_exact_for_closed_meshes() {
    use bridgev2w_embodiment::kinematics::{random_q, SplitMix64};
    use bridgev2w_embodiment::masks::render_items;
    use bridgev2w_embodiment::raster::Rasterizer;
    let e = Embodiment::builtin("franka").expect("franka");
    let r = &e.robot;
    assert!(
        r.links
            .iter()
            .filter(|l| l.mesh.is_some())
            .all(|l| l.mesh_closed),
        "primitive links are closed"
    );
    let mut rng = SplitMix64::new(11);
    let intr = Intrinsics::centered(400.0, 400, 300);
    let eyes = [
        Point3::new(1.5, 0.5, 0.8),
        Point3::new(-0.8, -1.2, 1.5),
        Point3::new(0.6, 0.0, 2.0),
        Point3::new(0.3, 0.3, 0.35),
    ];
    let mut drawn = 0;
    for eye in eyes {
        let cam =
            Camera::look_at(intr, eye, Point3::new(0.3, 0.0, 0.4), Vector3::z()).expect("cam");
        let raster = Rasterizer::new(&cam);
        for _ in 0..5 {
            let q = random_q(r, &mut rng);
            let poses = r.link_poses(&q);
            let a = raster.render(&render_items(r, &poses, false));
            let b = raster.render(&render_items(r, &poses, true));
            assert_eq!(a.labels, b.labels);
            for (x, y) in a.depth_m.iter().zip(&b.depth_m) {
                assert!(x == y || (x - y).abs() < 1e-5, "{x} vs {y}");
            }
            drawn += a.coverage();
        }
    }
    assert!(drawn > 10_000);
}

/// The labels-only render equals the labels of the full render, frame by
/// frame (also after other frames reused its per-thread depth buffer), with
/// and without lens distortion.
#[test]
fn labels_only_trajectory_matches_full_render() {
    use bridgev2w_embodiment::masks::render_trajectory_labels;
    let distortion = (-0.2, 0.05, 0.001, -0.001);
    let (e, joints, cams) = franka_scenes(5, 6, (300.0, 320, 240), distortion);
    for cam in cams {
        let full = render_trajectory(&e.robot, &cam, &joints, &|| {});
        let labels = render_trajectory_labels(&e.robot, &cam, &joints, &|| {});
        assert_eq!(full.len(), labels.len());
        for (f, l) in full.iter().zip(&labels) {
            assert!(f.coverage() > 500);
            assert_eq!(&f.labels, l);
        }
    }
}

/// The `[T, H, W]` label array equals the per-frame label maps, for one and
/// several threads, with and without lens distortion; drawing into a
/// non-zero map writes exactly the covered pixels.
#[test]
fn label_array_matches_per_frame_labels_for_any_threads() {
    use bridgev2w_embodiment::masks::{
        render_frame_labels_into, render_trajectory_label_array, render_trajectory_labels,
    };
    use bridgev2w_embodiment::raster::Rasterizer;
    let distortion = (-0.15, 0.02, 0.001, 0.0);
    let (e, joints, cams) = franka_scenes(9, 7, (280.0, 200, 150), distortion);
    for cam in cams {
        let frames = render_trajectory_labels(&e.robot, &cam, &joints, &|| {});
        let expected: Vec<u16> = frames.concat();
        assert!(expected.iter().filter(|&&l| l != 0).count() > 2000);
        for threads in [1, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("pool");
            let count = std::sync::atomic::AtomicUsize::new(0);
            let array = pool.install(|| {
                render_trajectory_label_array(&e.robot, &cam, &joints, &|| {
                    count.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                })
            });
            assert_eq!(array, expected, "{threads} threads");
            assert_eq!(count.into_inner(), joints.len());
        }
        // Over a non-zero map: covered pixels get their labels, the rest
        // keep the old value.
        let rasterizer = Rasterizer::new(&cam);
        let mut over = vec![u16::MAX; frames[0].len()];
        render_frame_labels_into(&e.robot, &rasterizer, &joints[0], &mut over);
        for (o, &l) in over.iter().zip(&frames[0]) {
            assert_eq!(*o, if l != 0 { l } else { u16::MAX });
        }
    }
}

/// The built-in Franka at `n` random joint configurations (seed `seed`),
/// seen by the same camera pose with intrinsics `(focal, width, height)`
/// without and with lens distortion `(k1, k2, p1, p2)`.
fn franka_scenes(
    seed: u64,
    n: usize,
    (focal, width, height): (f64, u32, u32),
    (k1, k2, p1, p2): (f64, f64, f64, f64),
) -> (Embodiment, Vec<Vec<f64>>, Vec<Camera>) {
    use bridgev2w_embodiment::camera::Distortion;
    use bridgev2w_embodiment::kinematics::{random_q, SplitMix64};
    let e = Embodiment::builtin("franka").expect("franka");
    let mut rng = SplitMix64::new(seed);
    let joints: Vec<Vec<f64>> = (0..n).map(|_| random_q(&e.robot, &mut rng)).collect();
    let plain = Intrinsics::centered(focal, width, height);
    let mut distorted = plain;
    distorted.distortion = Some(Distortion {
        k1,
        k2,
        p1,
        p2,
        k3: 0.0,
    });
    let cams = [plain, distorted]
        .into_iter()
        .map(|intr| {
            Camera::look_at(
                intr,
                Point3::new(1.6, 0.7, 1.0),
                Point3::new(0.3, 0.0, 0.4),
                Vector3::z(),
            )
            .expect("cam")
        })
        .collect();
    (e, joints, cams)
}
