//! Cameras shared by the camera and rasterizer tests (included with
//! `#[path]`).

// Each test binary that includes this module uses a part of it.
#![allow(dead_code)]

use bridgev2w_embodiment::camera::{Camera, Distortion, Intrinsics};
use nalgebra::Isometry3;

/// A 500 / 480 px focal length with the principal point at the centre.
pub fn intrinsics(width: u32, height: u32) -> Intrinsics {
    Intrinsics {
        fx: 500.0,
        fy: 480.0,
        cx: (f64::from(width) - 1.0) / 2.0,
        cy: (f64::from(height) - 1.0) / 2.0,
        width,
        height,
        distortion: None,
    }
}

/// Camera at the world origin with camera axes = world axes.
pub fn identity_camera(width: u32, height: u32) -> Camera {
    Camera::new(intrinsics(width, height), Isometry3::identity()).expect("valid camera")
}

/// A mild Brown-Conrady lens.
pub fn lens() -> Distortion {
    Distortion {
        k1: -0.12,
        k2: 0.03,
        p1: 0.001,
        p2: -0.0015,
        k3: -0.004,
    }
}
