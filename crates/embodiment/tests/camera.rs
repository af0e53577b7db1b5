//! Camera model and camera JSON tests.

use bridgev2w_embodiment::camera::{
    world_from_camera_from_xyz_rpy, Camera, CameraError, Distortion,
};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use proptest::prelude::*;

use crate::cameras;

use cameras::{identity_camera, intrinsics, lens};

// ---------------------------------------------------------------- camera

#[test]
fn projects_known_points() {
    let cam = identity_camera(640, 480);
    // cx = 319.5, cy = 239.5
    let p = cam.project(&Point3::new(0.0, 0.0, 2.0)).expect("in front");
    assert!((p.x - 319.5).abs() < 1e-12 && (p.y - 239.5).abs() < 1e-12);
    let p = cam.project(&Point3::new(0.2, -0.1, 2.0)).expect("in front");
    // u = 500 * 0.1 + 319.5, v = 480 * -0.05 + 239.5
    assert!((p.x - 369.5).abs() < 1e-9, "{p}");
    assert!((p.y - 215.5).abs() < 1e-9, "{p}");
    assert!(cam.project(&Point3::new(0.0, 0.0, -1.0)).is_none());
    assert!(cam.project(&Point3::new(0.0, 0.0, 0.0)).is_none());

    // A translated camera: world point (1, 0, 3) with the camera at x = 1.
    let cam =
        Camera::new(intrinsics(640, 480), Isometry3::translation(1.0, 0.0, 1.0)).expect("valid");
    let p = cam.project(&Point3::new(1.5, 0.0, 3.0)).expect("in front");
    assert!((p.x - (500.0 * 0.25 + 319.5)).abs() < 1e-9);
}

#[test]
fn pixel_ray_inverts_project() {
    for distortion in [None, Some(lens())] {
        let mut k = intrinsics(640, 480);
        k.distortion = distortion;
        let world_from_camera = Isometry3::from_parts(
            Translation3::new(0.3, -0.2, 1.5),
            UnitQuaternion::from_euler_angles(0.3, -0.5, 2.0),
        );
        let cam = Camera::new(k, world_from_camera).expect("valid");
        let eye = Point3::from(world_from_camera.translation.vector);
        for &(x, y, z) in &[(0.1, 0.2, 1.0), (-0.4, 0.3, 2.0), (0.5, -0.35, 1.2)] {
            let p_world = world_from_camera * Point3::new(x, y, z);
            let uv = cam.project(&p_world).expect("in front");
            let ray = cam.pixel_ray(uv.x, uv.y);
            assert!((ray.norm() - 1.0).abs() < 1e-12);
            let expected = (p_world - eye).normalize();
            assert!((ray - expected).norm() < 1e-9, "{ray} vs {expected}");
        }
    }
}

#[test]
fn rescaled_intrinsics_scale_projections() {
    let cam = identity_camera(640, 480);
    let half = cam.rescaled(320, 240);
    assert_eq!(half.intrinsics.width, 320);
    assert!((half.intrinsics.fx - 250.0).abs() < 1e-12);
    assert!((half.intrinsics.cx - 159.5).abs() < 1e-12);
    for p in [Point3::new(0.1, 0.2, 1.0), Point3::new(-0.3, 0.05, 2.5)] {
        let a = cam.project(&p).expect("in front");
        let b = half.project(&p).expect("in front");
        // Pixel-centre convention: (u + 0.5) scales by the factor.
        assert!(((a.x + 0.5) * 0.5 - 0.5 - b.x).abs() < 1e-9);
        assert!(((a.y + 0.5) * 0.5 - 0.5 - b.y).abs() < 1e-9);
    }
}

#[test]
fn undistort_inverts_distort_on_grid() {
    let d = lens();
    assert!(!d.is_zero());
    assert!(Distortion::default().is_zero());
    let mut worst = 0.0f64;
    for i in -10..=10 {
        for j in -10..=10 {
            let (x, y) = (f64::from(i) * 0.06, f64::from(j) * 0.05);
            let (xd, yd) = d.distort(x, y);
            let (xu, yu) = d.undistort(xd, yd);
            worst = worst.max((xu - x).abs()).max((yu - y).abs());
        }
    }
    assert!(worst < 1e-10, "worst error {worst}");
    // Distortion actually moves points.
    let (xd, _) = d.distort(0.5, 0.0);
    assert!((xd - 0.5).abs() > 1e-3);
}

proptest! {
    #[test]
    fn undistort_inverts_distort(x in -0.6f64..0.6, y in -0.45f64..0.45,
                                 k1 in -0.2f64..0.2, k2 in -0.05f64..0.05,
                                 p1 in -0.002f64..0.002, p2 in -0.002f64..0.002) {
        let d = Distortion { k1, k2, p1, p2, k3: 0.0 };
        let (xd, yd) = d.distort(x, y);
        let (xu, yu) = d.undistort(xd, yd);
        prop_assert!((xu - x).abs() < 1e-10 && (yu - y).abs() < 1e-10,
            "({x}, {y}) -> ({xu}, {yu})");
    }
}

#[test]
fn look_at_target_projects_to_principal_point() {
    let k = intrinsics(640, 480);
    let target = Point3::new(0.4, -0.2, 0.3);
    let cam = Camera::look_at(
        k,
        Point3::new(1.5, 1.0, 1.2),
        target,
        Vector3::new(0.0, 0.0, 1.0),
    )
    .expect("valid");
    let p = cam.project(&target).expect("in front");
    assert!(
        (p.x - k.cx).abs() < 1e-9 && (p.y - k.cy).abs() < 1e-9,
        "{p}"
    );
    // World up appears towards the top of the image (smaller v).
    let above = cam
        .project(&(target + Vector3::new(0.0, 0.0, 0.1)))
        .expect("in front");
    assert!(above.y < k.cy - 1.0);
    assert!((above.x - k.cx).abs() < 1e-6);

    assert!(Camera::look_at(k, target, target, Vector3::z()).is_err());
    assert!(Camera::look_at(
        k,
        Point3::new(0.0, 0.0, 2.0),
        Point3::origin(),
        Vector3::z()
    )
    .is_err());
}

#[test]
fn intrinsics_validation() {
    let good = intrinsics(64, 48);
    assert!(good.validate().is_ok());
    let mut k = good;
    k.fx = f64::NAN;
    let err = k.validate().expect_err("NaN fx");
    assert!(err.to_string().contains("fx"), "{err}");
    let mut k = good;
    k.height = 0;
    assert!(k
        .validate()
        .expect_err("zero height")
        .to_string()
        .contains("height"));
    let mut k = good;
    k.distortion = Some(Distortion {
        k2: f64::INFINITY,
        ..Distortion::default()
    });
    assert!(k.validate().expect_err("inf k2").to_string().contains("k2"));
    let mut k = good;
    k.cy = f64::NAN;
    assert!(Camera::new(k, Isometry3::identity()).is_err());
}

// ---------------------------------------------------------------- JSON

const XYZ_RPY: [f64; 6] = [0.5, -0.25, 1.1, -2.1, 0.15, 0.7];

fn matrix_json(m: &nalgebra::Matrix4<f64>) -> String {
    let rows: Vec<String> = (0..4)
        .map(|r| {
            let cols: Vec<String> = (0..4).map(|c| format!("{:.17e}", m[(r, c)])).collect();
            format!("[{}]", cols.join(", "))
        })
        .collect();
    format!("[{}]", rows.join(", "))
}

const HEAD: &str =
    r#""fx": 600.0, "fy": 601.5, "cx": 359.5, "cy": 239.5, "width": 720, "height": 480"#;

#[test]
fn json_matrix_and_xyz_rpy_agree() {
    let expected = world_from_camera_from_xyz_rpy(XYZ_RPY);
    let text_rpy = format!(
        r#"{{{HEAD}, "distortion": [0.1, -0.02, 0.001, 0.0005, 0.003], "extrinsics_xyz_rpy": {XYZ_RPY:?}}}"#
    );
    let a = Camera::from_json_str(&text_rpy, "<string>").expect("xyz_rpy form");
    let text_m = format!(
        r#"{{{HEAD}, "distortion": {{"k1": 0.1, "k2": -0.02, "p1": 0.001, "p2": 0.0005, "k3": 0.003}},
           "world_from_camera": {}}}"#,
        matrix_json(&expected.to_homogeneous())
    );
    let b = Camera::from_json_str(&text_m, "<string>").expect("matrix form");
    assert_eq!(a.intrinsics, b.intrinsics);
    assert_eq!(a.intrinsics.fy, 601.5);
    assert_eq!(a.intrinsics.width, 720);
    assert_eq!(
        a.intrinsics.distortion.map(|d| d.coefficients()),
        Some([0.1, -0.02, 0.001, 0.0005, 0.003])
    );
    for cam in [&a, &b] {
        let diff = (cam.world_from_camera.to_homogeneous() - expected.to_homogeneous())
            .abs()
            .max();
        assert!(diff < 1e-12, "diff {diff}");
    }
    // R = Rz * Ry * Rx (extrinsic XYZ).
    let [_, _, _, rx, ry, rz] = XYZ_RPY;
    let r = nalgebra::Rotation3::from_axis_angle(&Vector3::z_axis(), rz)
        * nalgebra::Rotation3::from_axis_angle(&Vector3::y_axis(), ry)
        * nalgebra::Rotation3::from_axis_angle(&Vector3::x_axis(), rx);
    let diff = (expected.rotation.to_rotation_matrix().matrix() - r.matrix())
        .abs()
        .max();
    assert!(diff < 1e-12);
    assert_eq!(expected.translation.vector, Vector3::new(0.5, -0.25, 1.1));
}

#[test]
fn json_matrix_is_reorthonormalized_within_tolerance() {
    let mut m = world_from_camera_from_xyz_rpy(XYZ_RPY).to_homogeneous();
    m[(0, 0)] += 2e-5;
    let text = format!(r#"{{{HEAD}, "world_from_camera": {}}}"#, matrix_json(&m));
    let cam = Camera::from_json_str(&text, "<string>").expect("within tolerance");
    let r = cam.world_from_camera.rotation.to_rotation_matrix();
    let err = (r.matrix().transpose() * r.matrix() - nalgebra::Matrix3::identity())
        .abs()
        .max();
    assert!(err < 1e-12);
}

fn json_err(text: &str) -> String {
    match Camera::from_json_str(text, "camera.json") {
        Ok(cam) => panic!("expected an error, got {cam:?}"),
        Err(e) => {
            let s = e.to_string();
            assert!(
                s.contains("camera.json"),
                "message does not name the source: {s}"
            );
            s
        }
    }
}

#[test]
fn json_errors() {
    let ext = r#""extrinsics_xyz_rpy": [0, 0, 0, 0, 0, 0]"#;
    let e = json_err(&format!(
        r#"{{"fx": -3, "fy": 600, "cx": 1, "cy": 1, "width": 4, "height": 4, {ext}}}"#
    ));
    assert!(e.contains("\"fx\" = -3") && e.contains("> 0"), "{e}");

    // JSON has no NaN literal: invalid JSON, located.
    let e = json_err(&format!(
        r#"{{"fx": NaN, "fy": 600, "cx": 1, "cy": 1, "width": 4, "height": 4, {ext}}}"#
    ));
    assert!(e.contains(":1:"), "{e}");

    let e = json_err(&format!("{{{HEAD}}}"));
    assert!(
        e.contains("world_from_camera") && e.contains("extrinsics_xyz_rpy"),
        "{e}"
    );

    let identity = "[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]";
    let e = json_err(&format!(
        r#"{{{HEAD}, "world_from_camera": {identity}, {ext}}}"#
    ));
    assert!(e.contains("exactly one"), "{e}");

    let e = json_err(&format!(
        r#"{{{HEAD}, "world_from_camera": [[1,0,0,0],[0,2,0,0],[0,0,1,0],[0,0,0,1]]}}"#
    ));
    assert!(e.contains("rotation") && e.contains("determinant 2"), "{e}");
    // A reflection is not a rotation either.
    let e = json_err(&format!(
        r#"{{{HEAD}, "world_from_camera": [[-1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}}"#
    ));
    assert!(e.contains("rotation"), "{e}");

    let e = json_err(&format!(
        r#"{{{HEAD}, "world_from_camera": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0.5,1]]}}"#
    ));
    assert!(e.contains("world_from_camera[3]"), "{e}");

    let e = json_err(&format!(r#"{{{HEAD}, "fxx": 1, {ext}}}"#));
    assert!(e.contains("unknown field") && e.contains("fxx"), "{e}");

    let e = json_err(&format!(
        r#"{{{HEAD}, "distortion": [0.1, 0.2, 0.3], {ext}}}"#
    ));
    assert!(
        e.contains("\"distortion\"") && e.contains("3 values"),
        "{e}"
    );
    let e = json_err(&format!(
        r#"{{{HEAD}, "distortion": {{"k1": 0.1, "kk2": 0.2}}, {ext}}}"#
    ));
    assert!(e.contains("distortion") && e.contains("kk2"), "{e}");

    let e = json_err(r#"{"fx": 600,"#);
    assert!(e.contains("invalid camera JSON"), "{e}");

    let e = json_err(&format!(
        r#"{{{HEAD}, "extrinsics_xyz_rpy": [0, 0, 0, 0, 0]}}"#
    ));
    assert!(e.contains("invalid camera JSON"), "{e}");
}

#[test]
fn json_file_and_round_trip() {
    let mut k = intrinsics(720, 480);
    k.distortion = Some(lens());
    let cam = Camera::new(k, world_from_camera_from_xyz_rpy(XYZ_RPY)).expect("valid");
    let text = cam.to_json();
    let back = Camera::from_json_str(&text, "<string>").expect("round trip");
    assert_eq!(back.intrinsics, cam.intrinsics);
    let diff = (back.world_from_camera.to_homogeneous() - cam.world_from_camera.to_homogeneous())
        .abs()
        .max();
    assert!(diff < 1e-12);

    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("cam.json");
    std::fs::write(&path, &text).expect("write");
    let from_file = Camera::from_json_file(&path).expect("file");
    assert_eq!(from_file.intrinsics, cam.intrinsics);
    let missing = dir.path().join("missing.json");
    match Camera::from_json_file(&missing) {
        Err(e @ CameraError::Io { .. }) => assert!(e.to_string().contains("missing.json")),
        other => panic!("expected Io error, got {other:?}"),
    }
}

#[test]
fn absurd_focal_lengths_and_image_sizes_are_refused() {
    let cam = |fx: &str, width: &str| {
        format!(
            r#"{{"fx": {fx}, "fy": 600, "cx": 359.5, "cy": 239.5, "width": {width}, "height": 480, "extrinsics_xyz_rpy": {XYZ_RPY:?}}}"#
        )
    };
    Camera::from_json_str(&cam("600", "720"), "ok.json").expect("a plain camera");
    // A field of view of 4e-5 degrees: every mask would be one pixel or none.
    let e = Camera::from_json_str(&cam("1e9", "720"), "narrow.json")
        .expect_err("refused")
        .to_string();
    assert!(
        e.contains("narrow.json") && e.contains("fx") && e.contains("field of view"),
        "{e}"
    );
    let e = Camera::from_json_str(&cam("0.001", "720"), "wide.json")
        .expect_err("refused")
        .to_string();
    assert!(e.contains("fx") && e.contains("field of view"), "{e}");
    let e = Camera::from_json_str(&cam("600000", "100000"), "huge.json")
        .expect_err("refused")
        .to_string();
    assert!(e.contains("width") && e.contains("16384"), "{e}");
}
