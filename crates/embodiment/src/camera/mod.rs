//! Pinhole cameras with OpenCV distortion.
//!
//! Camera axes follow OpenCV: x points right in the image, y points down and
//! z points forward along the optical axis. Pixel coordinates `(u, v)` follow
//! OpenCV too: the centre of pixel column `x` / row `y` has the integer
//! coordinates `(x, y)`, so pixel `x` covers `[x - 0.5, x + 0.5]`.
//!
//! A [`Camera`] is intrinsics (focal lengths, principal point, image size and
//! an optional [`Distortion`]) plus the pose `world_from_camera`, which maps
//! camera-frame coordinates (metres) to world coordinates (metres).
//!
//! Cameras are read from JSON (see [`Camera::from_json_str`]); a camera that
//! moves over a clip (a pose per frame, or mounted on a robot link) is a
//! [`CameraTrack`].

mod json;
mod track;

pub use track::{read_poses_npy, CameraPose, CameraTrack};

use nalgebra::{
    Isometry3, Matrix3, Point2, Point3, Rotation3, Translation3, UnitQuaternion, Vector3,
};
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Points closer than this to the camera plane (camera-frame z, metres) do
/// not project.
const MIN_PROJECT_Z_M: f64 = 1e-9;
/// Tolerance on the last row `[0, 0, 0, 1]` of a 4x4 extrinsic matrix.
const LAST_ROW_TOL: f64 = 1e-6;
/// Tolerance on `|R^T R - I|` and `|det R - 1|` of a 3x3 rotation block.
const ROTATION_TOL: f64 = 1e-4;
/// The largest image side (pixels) a camera may have: far above any robot
/// camera, far below what would exhaust memory when rasterized.
pub const MAX_IMAGE_SIDE: u32 = 16_384;
/// Focal length per pixel of image side, at the widest field of view (179.4 deg).
const MIN_FOCAL_PER_PIXEL: f64 = 0.005;
/// Focal length per pixel of image side, at the narrowest field of view (0.06 deg).
const MAX_FOCAL_PER_PIXEL: f64 = 1000.0;

/// Errors of camera construction and camera files.
///
/// Every message names where the data came from (a file path, `"<string>"`
/// for JSON text, `"<intrinsics>"` for values built in code).
#[derive(Debug, Error)]
pub enum CameraError {
    /// The camera file could not be read.
    #[error("{origin}: cannot read camera file: {error}")]
    Io {
        /// The file path.
        origin: String,
        /// The I/O error.
        #[source]
        error: std::io::Error,
    },
    /// The text is not valid JSON or does not have the camera format
    /// (missing field, unknown field, wrong type).
    #[error("{origin}:{line}:{column}: invalid camera JSON: {message}")]
    Json {
        /// The file path or `"<string>"`.
        origin: String,
        /// 1-based line of the error (0 if unknown).
        line: usize,
        /// 1-based column of the error (0 if unknown).
        column: usize,
        /// What serde_json reported.
        message: String,
    },
    /// A field has a value outside its valid range.
    #[error("{origin}: field \"{field}\" = {value}: expected {expected}")]
    InvalidField {
        /// The file path, `"<string>"` or `"<intrinsics>"`.
        origin: String,
        /// The field name.
        field: String,
        /// The offending value, formatted.
        value: String,
        /// What a valid value looks like.
        expected: String,
    },
    /// A 3x3 rotation block is not orthonormal with determinant +1.
    #[error(
        "{origin}: field \"{field}\": degenerate rotation matrix ({detail}): \
         expected an orthonormal 3x3 rotation block with determinant +1"
    )]
    DegenerateRotation {
        /// The file path or `"<string>"`.
        origin: String,
        /// The field name.
        field: String,
        /// Determinant and orthonormality error.
        detail: String,
    },
}

pub(crate) fn invalid(origin: &str, field: &str, value: String, expected: &str) -> CameraError {
    CameraError::InvalidField {
        origin: origin.to_string(),
        field: field.to_string(),
        value,
        expected: expected.to_string(),
    }
}

/// OpenCV radial-tangential ("plumb bob") lens distortion.
///
/// On normalized image coordinates `(x, y) = (X/Z, Y/Z)` with
/// `r² = x² + y²`:
/// ```text
/// radial = 1 + k1 r² + k2 r⁴ + k3 r⁶
/// x_d = x radial + 2 p1 x y + p2 (r² + 2 x²)
/// y_d = y radial + p1 (r² + 2 y²) + 2 p2 x y
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Distortion {
    /// Radial coefficient of r².
    #[serde(default)]
    pub k1: f64,
    /// Radial coefficient of r⁴.
    #[serde(default)]
    pub k2: f64,
    /// First tangential coefficient.
    #[serde(default)]
    pub p1: f64,
    /// Second tangential coefficient.
    #[serde(default)]
    pub p2: f64,
    /// Radial coefficient of r⁶.
    #[serde(default)]
    pub k3: f64,
}

impl Distortion {
    /// The coefficients in OpenCV order `[k1, k2, p1, p2, k3]`.
    pub fn coefficients(&self) -> [f64; 5] {
        [self.k1, self.k2, self.p1, self.p2, self.k3]
    }

    /// True when every coefficient is zero (the identity mapping).
    pub fn is_zero(&self) -> bool {
        self.coefficients().iter().all(|&c| c == 0.0)
    }

    /// Distorts undistorted normalized coordinates `(x_n, y_n)`.
    pub fn distort(&self, x_n: f64, y_n: f64) -> (f64, f64) {
        let (x, y) = (x_n, y_n);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        let xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x);
        let yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y;
        (xd, yd)
    }

    /// Jacobian of [`Distortion::distort`] at `(x, y)`, rows `(x_d, y_d)`.
    fn jacobian(&self, x: f64, y: f64) -> [[f64; 2]; 2] {
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        let d_radial = self.k1 + r2 * (2.0 * self.k2 + 3.0 * r2 * self.k3);
        let cross = 2.0 * x * y * d_radial + 2.0 * self.p1 * x + 2.0 * self.p2 * y;
        [
            [
                radial + 2.0 * x * x * d_radial + 2.0 * self.p1 * y + 6.0 * self.p2 * x,
                cross,
            ],
            [
                cross,
                radial + 2.0 * y * y * d_radial + 6.0 * self.p1 * y + 2.0 * self.p2 * x,
            ],
        ]
    }

    /// Inverts [`Distortion::distort`]: the undistorted normalized
    /// coordinates whose distortion is `(x_d, y_d)`.
    ///
    /// Newton iterations started at `(x_d, y_d)`, stopping when the residual
    /// is below 1e-14 (converges to ~1e-10 or better for lenses that are
    /// invertible over the field of view). Returns the best estimate found
    /// when the iteration does not converge (far outside a lens' valid range).
    pub fn undistort(&self, x_d: f64, y_d: f64) -> (f64, f64) {
        if self.is_zero() {
            return (x_d, y_d);
        }
        let (mut x, mut y) = (x_d, y_d);
        let mut best = (x, y, f64::INFINITY);
        for _ in 0..100 {
            let (fx, fy) = self.distort(x, y);
            let (ex, ey) = (fx - x_d, fy - y_d);
            let err = ex.abs().max(ey.abs());
            if !err.is_finite() {
                break;
            }
            if err < best.2 {
                best = (x, y, err);
            }
            if err < 1e-14 {
                break;
            }
            let [[a, b], [c, d]] = self.jacobian(x, y);
            let det = a * d - b * c;
            if !det.is_finite() || det.abs() < 1e-300 {
                break;
            }
            let dx = (d * ex - b * ey) / det;
            let dy = (a * ey - c * ex) / det;
            x -= dx;
            y -= dy;
        }
        (best.0, best.1)
    }
}

/// Pinhole intrinsics in pixels plus optional lens distortion.
///
/// `u = fx * x_d + cx`, `v = fy * y_d + cy` where `(x_d, y_d)` are the
/// (distorted) normalized coordinates; pixel centres are at integer `(u, v)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Lens distortion; `None` for an ideal pinhole.
    pub distortion: Option<Distortion>,
}

impl Intrinsics {
    /// An ideal pinhole camera of `width` x `height` with focal length
    /// `focal_px` (both axes) and the principal point at the image centre
    /// (`(width - 1) / 2`, `(height - 1) / 2` in the pixel-centre
    /// convention), no distortion.
    pub fn centered(focal_px: f64, width: u32, height: u32) -> Self {
        Self {
            fx: focal_px,
            fy: focal_px,
            cx: (f64::from(width) - 1.0) / 2.0,
            cy: (f64::from(height) - 1.0) / 2.0,
            width,
            height,
            distortion: None,
        }
    }

    /// Checks that focal lengths are finite and give a field of view of
    /// 0.06..179.4 degrees, the principal point is finite, the image is
    /// 1..=[`MAX_IMAGE_SIDE`] pixels a side and distortion coefficients are
    /// finite.
    pub fn validate(&self) -> Result<(), CameraError> {
        self.validate_from("<intrinsics>")
    }

    fn validate_from(&self, origin: &str) -> Result<(), CameraError> {
        let bad = |field: &str, value: String, expected: &str| CameraError::InvalidField {
            origin: origin.to_string(),
            field: field.to_string(),
            value,
            expected: expected.to_string(),
        };
        for (name, f) in [("fx", self.fx), ("fy", self.fy)] {
            if !(f.is_finite() && f > 0.0) {
                return Err(bad(name, f.to_string(), "a finite focal length > 0"));
            }
        }
        for (name, c) in [("cx", self.cx), ("cy", self.cy)] {
            if !c.is_finite() {
                return Err(bad(
                    name,
                    c.to_string(),
                    "a finite principal point coordinate",
                ));
            }
        }
        for (name, n) in [("width", self.width), ("height", self.height)] {
            if n == 0 || n > MAX_IMAGE_SIDE {
                return Err(bad(
                    name,
                    n.to_string(),
                    &format!("an image size of 1..={MAX_IMAGE_SIDE} pixels"),
                ));
            }
        }
        // A field of view between about 0.06 and 179.4 degrees: outside it the
        // projection is a point or a line, and the masks garbage.
        for (name, f, side) in [("fx", self.fx, self.width), ("fy", self.fy, self.height)] {
            let ratio = f / f64::from(side);
            if !(MIN_FOCAL_PER_PIXEL..=MAX_FOCAL_PER_PIXEL).contains(&ratio) {
                return Err(bad(
                    name,
                    f.to_string(),
                    &format!(
                        "a focal length of {MIN_FOCAL_PER_PIXEL}..={MAX_FOCAL_PER_PIXEL} times the image's {side} pixels (a field of view of 0.06..179.4 degrees)"
                    ),
                ));
            }
        }
        if let Some(d) = &self.distortion {
            let names = ["k1", "k2", "p1", "p2", "k3"];
            for (name, c) in names.iter().zip(d.coefficients()) {
                if !c.is_finite() {
                    return Err(bad(
                        &format!("distortion.{name}"),
                        c.to_string(),
                        "a finite distortion coefficient",
                    ));
                }
            }
        }
        Ok(())
    }

    /// The distortion if present and non-zero.
    pub fn active_distortion(&self) -> Option<&Distortion> {
        self.distortion.as_ref().filter(|d| !d.is_zero())
    }

    /// Intrinsics for the same camera imaged at `width` x `height` pixels.
    ///
    /// Uses the pixel-centre convention: with `sx = width / self.width`,
    /// `fx' = fx sx` and `cx' = (cx + 0.5) sx - 0.5` (same for y), so that a
    /// scene point keeps its relative position in the image. Distortion acts
    /// on normalized coordinates and is unchanged. A zero `width` or
    /// `height` gives intrinsics that [`Intrinsics::validate`] rejects.
    pub fn rescaled(&self, width: u32, height: u32) -> Intrinsics {
        let sx = f64::from(width) / f64::from(self.width);
        let sy = f64::from(height) / f64::from(self.height);
        Intrinsics {
            fx: self.fx * sx,
            fy: self.fy * sy,
            cx: (self.cx + 0.5) * sx - 0.5,
            cy: (self.cy + 0.5) * sy - 0.5,
            width,
            height,
            distortion: self.distortion,
        }
    }
}

/// A calibrated camera: intrinsics and pose.
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    /// Intrinsics (validated by the constructors).
    pub intrinsics: Intrinsics,
    /// Maps camera-frame points (OpenCV axes: x right, y down, z forward;
    /// metres) to world-frame points (metres).
    pub world_from_camera: Isometry3<f64>,
}

/// The DROID extrinsics convention: `[x, y, z, rx, ry, rz]` (metres,
/// radians) to `world_from_camera`.
///
/// The translation is `(x, y, z)`; the rotation is extrinsic XYZ Euler angles
/// (rotate about world x by `rx`, then world y by `ry`, then world z by
/// `rz`), i.e. `R = Rz(rz) * Ry(ry) * Rx(rx)`, which is nalgebra's
/// `Rotation3::from_euler_angles(rx, ry, rz)` and SciPy's
/// `Rotation.from_euler("xyz", [rx, ry, rz])`.
pub fn world_from_camera_from_xyz_rpy(v: [f64; 6]) -> Isometry3<f64> {
    let [x, y, z, rx, ry, rz] = v;
    Isometry3::from_parts(
        Translation3::new(x, y, z),
        UnitQuaternion::from_euler_angles(rx, ry, rz),
    )
}

impl Camera {
    /// A camera from validated intrinsics and its pose.
    pub fn new(
        intrinsics: Intrinsics,
        world_from_camera: Isometry3<f64>,
    ) -> Result<Self, CameraError> {
        intrinsics.validate()?;
        Ok(Self {
            intrinsics,
            world_from_camera,
        })
    }

    /// A camera at `eye` looking at `target` (world frame, metres) with the
    /// image "up" as close as possible to the world direction `up`.
    ///
    /// The camera z axis points from `eye` to `target`, y points down
    /// (opposite to `up` projected on the image plane), x = y × z points right.
    /// Fails if `eye == target`, `up` is zero or parallel to the view
    /// direction, or values are not finite.
    pub fn look_at(
        intrinsics: Intrinsics,
        eye: Point3<f64>,
        target: Point3<f64>,
        up: Vector3<f64>,
    ) -> Result<Camera, CameraError> {
        let origin = "look_at";
        let forward = target - eye;
        let forward_norm = forward.norm();
        if !(forward_norm.is_finite() && forward_norm > 1e-12) {
            return Err(invalid(
                origin,
                "target",
                format!("{:?}", target.coords.as_slice()),
                "a finite point distinct from eye",
            ));
        }
        let z = forward / forward_norm;
        let x = z.cross(&up);
        let x_norm = x.norm();
        let up_norm = up.norm();
        if !(x_norm.is_finite() && up_norm.is_finite() && x_norm > 1e-9 * up_norm.max(1e-300)) {
            return Err(invalid(
                origin,
                "up",
                format!("{:?}", up.as_slice()),
                "a finite non-zero vector not parallel to the view direction",
            ));
        }
        let x = x / x_norm;
        let y = z.cross(&x);
        let rotation = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
        let world_from_camera = Isometry3::from_parts(
            Translation3::from(eye.coords),
            UnitQuaternion::from_rotation_matrix(&rotation),
        );
        Camera::new(intrinsics, world_from_camera)
    }

    /// Projects a world point to pixel coordinates (OpenCV convention,
    /// distortion applied). `None` if the point's camera-frame z is <= 1e-9 m.
    pub fn project(&self, p_world: &Point3<f64>) -> Option<Point2<f64>> {
        let p_camera = self.world_from_camera.inverse_transform_point(p_world);
        // Also rejects NaN.
        if p_camera.z.is_nan() || p_camera.z <= MIN_PROJECT_Z_M {
            return None;
        }
        let (mut x, mut y) = (p_camera.x / p_camera.z, p_camera.y / p_camera.z);
        if let Some(d) = self.intrinsics.active_distortion() {
            (x, y) = d.distort(x, y);
        }
        let k = &self.intrinsics;
        Some(Point2::new(k.fx * x + k.cx, k.fy * y + k.cy))
    }

    /// The unit direction, in the world frame, of the ray through pixel
    /// coordinates `(u, v)` (distortion removed).
    pub fn pixel_ray(&self, u: f64, v: f64) -> Vector3<f64> {
        let k = &self.intrinsics;
        let (mut x, mut y) = ((u - k.cx) / k.fx, (v - k.cy) / k.fy);
        if let Some(d) = k.active_distortion() {
            (x, y) = d.undistort(x, y);
        }
        self.world_from_camera.rotation * Vector3::new(x, y, 1.0).normalize()
    }

    /// The same camera imaged at `width` x `height` (see
    /// [`Intrinsics::rescaled`]).
    pub fn rescaled(&self, width: u32, height: u32) -> Camera {
        Camera {
            intrinsics: self.intrinsics.rescaled(width, height),
            world_from_camera: self.world_from_camera,
        }
    }
}

/// Converts a row-major 4x4 rigid transform to an isometry, checking the last
/// row and re-orthonormalizing a rotation block within [`ROTATION_TOL`].
pub fn isometry_from_rows(
    m: &[[f64; 4]; 4],
    origin: &str,
    field: &str,
) -> Result<Isometry3<f64>, CameraError> {
    for (r, row) in m.iter().enumerate() {
        for (c, &value) in row.iter().enumerate() {
            if !value.is_finite() {
                return Err(invalid(
                    origin,
                    &format!("{field}[{r}][{c}]"),
                    value.to_string(),
                    "a finite number",
                ));
            }
        }
    }
    let last = m[3];
    let expected_last = [0.0, 0.0, 0.0, 1.0];
    if last
        .iter()
        .zip(expected_last)
        .any(|(a, b)| (a - b).abs() > LAST_ROW_TOL)
    {
        return Err(invalid(
            origin,
            &format!("{field}[3]"),
            format!("{last:?}"),
            "the last row of a rigid transform, [0, 0, 0, 1]",
        ));
    }
    let block = Matrix3::from_fn(|r, c| m[r][c]);
    let det = block.determinant();
    let ortho_err = (block.transpose() * block - Matrix3::identity())
        .abs()
        .max();
    if (det - 1.0).abs() > ROTATION_TOL || ortho_err > ROTATION_TOL {
        return Err(CameraError::DegenerateRotation {
            origin: origin.to_string(),
            field: field.to_string(),
            detail: format!("determinant {det}, max |R^T R - I| = {ortho_err:.3e}"),
        });
    }
    // Nearest rotation (polar decomposition): R = U V^T.
    let svd = block.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(CameraError::DegenerateRotation {
            origin: origin.to_string(),
            field: field.to_string(),
            detail: format!("determinant {det}, SVD failed"),
        });
    };
    let rotation = Rotation3::from_matrix_unchecked(u * v_t);
    let quaternion = UnitQuaternion::from_rotation_matrix(&rotation);
    Ok(Isometry3::from_parts(
        Translation3::new(m[0][3], m[1][3], m[2][3]),
        UnitQuaternion::new_normalize(quaternion.into_inner()),
    ))
}
