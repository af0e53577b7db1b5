//! The camera file format (JSON): intrinsics and one of four ways to pose
//! the camera: a fixed `world_from_camera` matrix, DROID-style
//! `extrinsics_xyz_rpy`, one matrix per frame (`world_from_camera_per_frame`)
//! or a mount on a robot link (`parent_link` + `link_from_camera`).

use super::track::{CameraPose, CameraTrack};
use super::{
    invalid, isometry_from_rows, world_from_camera_from_xyz_rpy, Camera, CameraError, Distortion,
    Intrinsics,
};
use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;
use std::path::Path;

/// The camera file format.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct CameraJson {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    width: u32,
    height: u32,
    /// An object `{k1, k2, p1, p2, k3}` or an array `[k1, k2, p1, p2, k3]`.
    #[serde(default)]
    distortion: Option<serde_json::Value>,
    #[serde(default)]
    world_from_camera: Option<[[f64; 4]; 4]>,
    #[serde(default)]
    extrinsics_xyz_rpy: Option<[f64; 6]>,
    /// A moving camera: one row-major 4x4 `world_from_camera` per frame.
    #[serde(default)]
    world_from_camera_per_frame: Option<Vec<[[f64; 4]; 4]>>,
    /// A camera mounted on a robot link (posed by forward kinematics).
    #[serde(default)]
    parent_link: Option<String>,
    /// The mount: row-major 4x4 `link_from_camera` (default identity).
    #[serde(default)]
    link_from_camera: Option<[[f64; 4]; 4]>,
}

/// Serialization mirror of the camera file format (matrix extrinsics).
#[derive(Debug, Serialize)]
struct CameraJsonOut {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    width: u32,
    height: u32,
    #[serde(skip_serializing_if = "Option::is_none")]
    distortion: Option<Distortion>,
    world_from_camera: [[f64; 4]; 4],
}

/// Distortion from its JSON value: an object (missing coefficients are 0,
/// unknown keys rejected) or an array of exactly 5 numbers.
fn parse_distortion(value: serde_json::Value, origin: &str) -> Result<Distortion, CameraError> {
    const EXPECTED: &str =
        "an object {\"k1\", \"k2\", \"p1\", \"p2\", \"k3\"} or an array [k1, k2, p1, p2, k3]";
    match value {
        serde_json::Value::Array(items) => {
            if items.len() != 5 {
                return Err(invalid(
                    origin,
                    "distortion",
                    format!("an array of {} values", items.len()),
                    EXPECTED,
                ));
            }
            let mut k = [0.0; 5];
            for (i, (slot, item)) in k.iter_mut().zip(&items).enumerate() {
                *slot = item.as_f64().ok_or_else(|| {
                    invalid(
                        origin,
                        &format!("distortion[{i}]"),
                        item.to_string(),
                        "a number",
                    )
                })?;
            }
            let [k1, k2, p1, p2, k3] = k;
            Ok(Distortion { k1, k2, p1, p2, k3 })
        }
        serde_json::Value::Object(_) => serde_json::from_value::<Distortion>(value)
            .map_err(|e| invalid(origin, "distortion", e.to_string(), EXPECTED)),
        other => Err(invalid(origin, "distortion", other.to_string(), EXPECTED)),
    }
}

/// A camera file's text and its name for messages.
fn read_camera_file(path: &Path) -> Result<(String, String), CameraError> {
    let origin = path.display().to_string();
    match std::fs::read_to_string(path) {
        Ok(text) => Ok((text, origin)),
        Err(error) => Err(CameraError::Io { origin, error }),
    }
}

/// Parses the camera file format into intrinsics and a pose of any kind.
pub(super) fn parse_track(text: &str, source: &str) -> Result<CameraTrack, CameraError> {
    let parsed: CameraJson = serde_json::from_str(text).map_err(|e| CameraError::Json {
        origin: source.to_string(),
        line: e.line(),
        column: e.column(),
        message: e.to_string(),
    })?;
    let distortion = parsed
        .distortion
        .map(|d| parse_distortion(d, source))
        .transpose()?;
    let intrinsics = Intrinsics {
        fx: parsed.fx,
        fy: parsed.fy,
        cx: parsed.cx,
        cy: parsed.cy,
        width: parsed.width,
        height: parsed.height,
        distortion,
    };
    intrinsics.validate_from(source)?;
    const EXPECTED: &str = "exactly one of \"world_from_camera\", \"extrinsics_xyz_rpy\", \"world_from_camera_per_frame\" and \"parent_link\"";
    let given: Vec<&str> = [
        ("world_from_camera", parsed.world_from_camera.is_some()),
        ("extrinsics_xyz_rpy", parsed.extrinsics_xyz_rpy.is_some()),
        (
            "world_from_camera_per_frame",
            parsed.world_from_camera_per_frame.is_some(),
        ),
        ("parent_link", parsed.parent_link.is_some()),
    ]
    .into_iter()
    .filter_map(|(name, present)| present.then_some(name))
    .collect();
    if given.len() != 1 {
        let (field, value) = match given.first() {
            None => (
                "world_from_camera",
                "missing (and no other pose field given)".to_string(),
            ),
            Some(first) => (*first, format!("given together with {:?}", &given[1..])),
        };
        return Err(invalid(source, field, value, EXPECTED));
    }
    if parsed.link_from_camera.is_some() && parsed.parent_link.is_none() {
        return Err(invalid(
            source,
            "link_from_camera",
            "given without \"parent_link\"".to_string(),
            "\"link_from_camera\" only with \"parent_link\" (the link the camera is mounted on)",
        ));
    }
    let pose = if let Some(m) = parsed.world_from_camera {
        CameraPose::Fixed(isometry_from_rows(&m, source, "world_from_camera")?)
    } else if let Some(v) = parsed.extrinsics_xyz_rpy {
        for (i, value) in v.iter().enumerate() {
            if !value.is_finite() {
                return Err(invalid(
                    source,
                    &format!("extrinsics_xyz_rpy[{i}]"),
                    value.to_string(),
                    "a finite number",
                ));
            }
        }
        CameraPose::Fixed(world_from_camera_from_xyz_rpy(v))
    } else if let Some(frames) = parsed.world_from_camera_per_frame {
        if frames.is_empty() {
            return Err(invalid(
                source,
                "world_from_camera_per_frame",
                "[]".to_string(),
                "one 4x4 matrix per frame",
            ));
        }
        CameraPose::PerFrame(
            frames
                .iter()
                .enumerate()
                .map(|(t, m)| {
                    isometry_from_rows(m, source, &format!("world_from_camera_per_frame[{t}]"))
                })
                .collect::<Result<_, _>>()?,
        )
    } else {
        let link = parsed.parent_link.unwrap_or_default();
        if link.is_empty() {
            return Err(invalid(
                source,
                "parent_link",
                "\"\"".to_string(),
                "the name of a robot link",
            ));
        }
        let link_from_camera = match parsed.link_from_camera {
            Some(m) => isometry_from_rows(&m, source, "link_from_camera")?,
            None => Isometry3::identity(),
        };
        CameraPose::Mounted {
            link,
            link_from_camera,
        }
    };
    Ok(CameraTrack { intrinsics, pose })
}

impl Camera {
    /// Parses a camera from JSON text; `source` names the text in errors
    /// (a file path, or `"<string>"`).
    ///
    /// Format (unknown fields are rejected):
    /// ```json
    /// {
    ///   "fx": 600.0, "fy": 600.0, "cx": 359.5, "cy": 239.5,
    ///   "width": 720, "height": 480,
    ///   "distortion": {"k1": 0.1, "k2": 0.0, "p1": 0.0, "p2": 0.0, "k3": 0.0},
    ///   "world_from_camera": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]
    /// }
    /// ```
    /// `distortion` is optional and may also be `[k1, k2, p1, p2, k3]`.
    /// Exactly one of `world_from_camera` (row-major 4x4 rigid transform) and
    /// `extrinsics_xyz_rpy` (see [`world_from_camera_from_xyz_rpy`]) must be
    /// given. The moving-camera fields of [`CameraTrack::from_json_str`]
    /// (`world_from_camera_per_frame`, `parent_link`) are refused here.
    pub fn from_json_str(text: &str, source: &str) -> Result<Camera, CameraError> {
        let track = parse_track(text, source)?;
        match track.pose {
            CameraPose::Fixed(world_from_camera) => Ok(Camera {
                intrinsics: track.intrinsics,
                world_from_camera,
            }),
            CameraPose::PerFrame(_) | CameraPose::Mounted { .. } => Err(invalid(
                source,
                track.pose.kind_field(),
                "a moving camera".to_string(),
                "a fixed camera here (\"world_from_camera\" or \"extrinsics_xyz_rpy\"); moving cameras work with `bridgev2w masks` and `overlay`",
            )),
        }
    }

    /// Reads a camera JSON file (format of [`Camera::from_json_str`]).
    pub fn from_json_file(path: &Path) -> Result<Camera, CameraError> {
        let (text, origin) = read_camera_file(path)?;
        Self::from_json_str(&text, &origin)
    }

    /// Pretty JSON in the format of [`Camera::from_json_str`], extrinsics as
    /// the `world_from_camera` matrix.
    pub fn to_json(&self) -> String {
        let m = self.world_from_camera.to_homogeneous();
        let k = &self.intrinsics;
        let out = CameraJsonOut {
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            width: k.width,
            height: k.height,
            distortion: k.distortion,
            world_from_camera: std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)])),
        };
        match serde_json::to_string_pretty(&out) {
            Ok(text) => text,
            // Serializing plain numbers cannot fail; keep a readable fallback.
            Err(e) => {
                let mut s = String::new();
                let _ = write!(s, "{{\"error\": \"{e}\"}}");
                s
            }
        }
    }
}

impl CameraTrack {
    /// Parses the camera file format ([`Camera::from_json_str`]'s fields)
    /// with the moving-camera fields allowed:
    ///
    /// - `"world_from_camera_per_frame": [[[4x4]], ...]`: one row-major
    ///   `world_from_camera` per frame;
    /// - `"parent_link": "head_camera_link"` with optional
    ///   `"link_from_camera": [[4x4]]` (default identity): mounted on a link.
    pub fn from_json_str(text: &str, source: &str) -> Result<Self, CameraError> {
        parse_track(text, source)
    }

    /// Reads a camera file (format of [`CameraTrack::from_json_str`]).
    pub fn from_json_file(path: &Path) -> Result<Self, CameraError> {
        let (text, origin) = read_camera_file(path)?;
        Self::from_json_str(&text, &origin)
    }
}
