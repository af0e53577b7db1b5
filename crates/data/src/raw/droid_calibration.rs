//! DROID calibration files, read as they are published (the DROID team's
//! post-hoc calibrations, `KarlP/droid` on Hugging Face) and in the
//! project's simple layouts:
//!
//! ```text
//! intrinsics.json                    {"<episode_id>": {"<serial>": [fx, cx, fy, cy]}}   (1280x720 images)
//! cam2base_extrinsics.json,          {"<episode_id>": {<quality fields>..., "<serial>": [x, y, z, rx, ry, rz]}}
//! cam2base_extrinsic_superset.json
//! simple intrinsics                  {"<serial>": {"fx", "fy", "cx", "cy", "width", "height"}}
//! simple extrinsics                  {"<episode_id>": {"<serial>_left": [6]}} or {"<serial>_left": [6]}
//! ```
//!
//! `<episode_id>` is the episode's metadata `uuid` (`<lab>+<8 hex>+<date>`,
//! e.g. `AUTOLab+84bd5053+2023-08-18-12h-01m-10s`), which is also the
//! metadata file's name (`metadata_<uuid>.json`). Camera keys are the ZED
//! serial numbers (digits), optionally with `_left`/`_right`; other keys of
//! an episode's entry are quality metrics and are ignored. A bare serial's
//! pose and intrinsics are those of the camera's **left** image: DROID's
//! README says `cam2base_extrinsics.json` holds "either the left or right
//! camera" per episode and the superset "both left and right camera" — the
//! two exterior cameras (one or both per episode, 36k and 24k x 2 entries),
//! not the stereo eyes — and its calibration example projects them onto the
//! left images (`exterior_image_*_left`), the images of
//! `recordings/MP4/<serial>.mp4`. A pose given explicitly for the right eye
//! (`<serial>_right`) is moved to the left eye with the stereo offset that
//! the episode's `trajectory.h5` records for the same camera, or refused.

use super::report::Eye;
use super::{json_err, json_intrinsics, json_vec, read_json, RawError};
use bridgev2w_embodiment::camera::Intrinsics;
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The image size DROID's published intrinsics are given for.
pub const PUBLISHED_INTRINSICS_SIZE: (u32, u32) = (1280, 720);

/// What to do when no calibration file has extrinsics for a camera.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum MissingCalibration {
    /// Use the extrinsics recorded in `trajectory.h5`, with a counted
    /// warning in the conversion report.
    #[default]
    Recorded,
    /// Refuse the episode.
    Error,
}

impl std::str::FromStr for MissingCalibration {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "recorded" => Ok(Self::Recorded),
            "error" => Ok(Self::Error),
            _ => Err(format!("\"{s}\": expected \"recorded\" or \"error\"")),
        }
    }
}

/// A camera key: `<serial>`, `<serial>_left` or `<serial>_right`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CameraKey {
    /// The serial number (digits).
    pub serial: String,
    /// The eye; `None` for a bare serial (which DROID gives for the left image).
    pub eye: Option<Eye>,
}

impl CameraKey {
    /// Parses a key; `None` for a key that is not a camera (a quality field).
    pub fn parse(key: &str) -> Option<Self> {
        let (serial, eye) = if let Some(s) = key.strip_suffix("_left") {
            (s, Some(Eye::Left))
        } else if let Some(s) = key.strip_suffix("_right") {
            (s, Some(Eye::Right))
        } else {
            (key, None)
        };
        (!serial.is_empty() && serial.bytes().all(|b| b.is_ascii_digit())).then(|| Self {
            serial: serial.to_string(),
            eye,
        })
    }

    /// The eye the key's values belong to (bare serial: left).
    pub fn eye(&self) -> Eye {
        self.eye.unwrap_or(Eye::Left)
    }
}

/// Intrinsics per camera, per episode (published layout) or for every
/// episode (simple layout).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct IntrinsicsTable {
    /// The file read.
    pub file: PathBuf,
    /// Per serial, for every episode.
    pub global: BTreeMap<String, Intrinsics>,
    /// Per episode id, per serial.
    pub by_episode: BTreeMap<String, BTreeMap<String, Intrinsics>>,
}

impl IntrinsicsTable {
    /// Reads an intrinsics file in either layout (see the module docs).
    pub fn read(path: &Path) -> Result<Self, RawError> {
        let v = read_json(path)?;
        let map = v.as_object().ok_or_else(|| {
            json_err(
                path,
                "",
                "expected an object keyed by episode id or camera serial",
            )
        })?;
        let mut t = Self {
            file: path.to_path_buf(),
            ..Self::default()
        };
        for (key, x) in map {
            if x.get("fx").is_some() {
                t.global.insert(
                    key.clone(),
                    json_intrinsics(path, x, key, ["fx", "fy", "cx", "cy"], None)?,
                );
            } else if let (Some(cam), Value::Array(_)) = (CameraKey::parse(key), x) {
                if cam.eye() == Eye::Left {
                    t.global
                        .insert(cam.serial, published_intrinsics(path, key, x)?);
                }
            } else if let Value::Object(cams) = x {
                let entry = t.by_episode.entry(key.clone()).or_default();
                for (ck, k) in cams {
                    let Some(cam) = CameraKey::parse(ck) else {
                        continue;
                    };
                    let field = format!("{key}.{ck}");
                    let intr = if k.get("fx").is_some() {
                        json_intrinsics(path, k, &field, ["fx", "fy", "cx", "cy"], None)?
                    } else {
                        published_intrinsics(path, &field, k)?
                    };
                    if cam.eye() == Eye::Left {
                        entry.insert(cam.serial, intr);
                    }
                }
            } else {
                return Err(json_err(
                    path,
                    key,
                    format!(
                        "{}: expected {{\"<serial>\": [fx, cx, fy, cy]}} (an episode's entry) or {{\"fx\", \"fy\", \"cx\", \"cy\", \"width\", \"height\"}} (a camera's)",
                        short(x)
                    ),
                ));
            }
        }
        Ok(t)
    }

    /// The intrinsics of camera `serial` in the first of `episode_ids` with an
    /// entry, else for every episode; with the key that matched.
    pub fn lookup(&self, episode_ids: &[&str], serial: &str) -> Option<(Intrinsics, String)> {
        episode_ids
            .iter()
            .find_map(|id| {
                self.by_episode
                    .get(*id)
                    .and_then(|m| m.get(serial))
                    .map(|k| (*k, format!("{id}.{serial}")))
            })
            .or_else(|| self.global.get(serial).map(|k| (*k, serial.to_string())))
    }
}

fn short(v: &Value) -> String {
    let s = v.to_string();
    if s.len() > 60 {
        format!(
            "{}...",
            &s[..s.char_indices().nth(57).map_or(s.len(), |c| c.0)]
        )
    } else {
        s
    }
}

/// DROID's `[fx, cx, fy, cy]` at [`PUBLISHED_INTRINSICS_SIZE`].
fn published_intrinsics(path: &Path, field: &str, v: &Value) -> Result<Intrinsics, RawError> {
    let a = json_vec(path, v, field, 4).map_err(|e| match e {
        RawError::Json { path, field, .. } => RawError::Json {
            path,
            field,
            message: format!(
                "{}: expected [fx, cx, fy, cy] (4 numbers, pixels at 1280x720)",
                short(v)
            ),
        },
        other => other,
    })?;
    let (width, height) = PUBLISHED_INTRINSICS_SIZE;
    let k = Intrinsics {
        fx: a[0],
        cx: a[1],
        fy: a[2],
        cy: a[3],
        width,
        height,
        distortion: None,
    };
    k.validate()
        .map_err(|e| json_err(path, field, format!("[fx, cx, fy, cy] = {a:?}: {e}")))?;
    Ok(k)
}

/// One pose of a calibration file.
#[derive(Debug, Clone, PartialEq)]
pub struct PublishedPose {
    /// The key as written.
    pub key: String,
    /// The camera and eye.
    pub camera: CameraKey,
    /// `[x, y, z, rx, ry, rz]`: `world_from_camera`, extrinsic XYZ angles.
    pub pose: [f64; 6],
}

/// Extrinsics per episode (published layout) or for every episode.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ExtrinsicsTable {
    /// The file read.
    pub file: PathBuf,
    /// For every episode.
    pub global: Vec<PublishedPose>,
    /// Per episode id: its camera poses (quality fields dropped).
    pub by_episode: BTreeMap<String, Vec<PublishedPose>>,
}

impl ExtrinsicsTable {
    /// Reads an extrinsics file in either layout (see the module docs).
    pub fn read(path: &Path) -> Result<Self, RawError> {
        let v = read_json(path)?;
        let map = v.as_object().ok_or_else(|| {
            json_err(
                path,
                "",
                "expected an object keyed by episode id (or by <serial>_left)",
            )
        })?;
        let mut t = Self {
            file: path.to_path_buf(),
            ..Self::default()
        };
        let pose = |field: &str, x: &Value| -> Result<[f64; 6], RawError> {
            let v = json_vec(path, x, field, 6)?;
            Ok([v[0], v[1], v[2], v[3], v[4], v[5]])
        };
        for (key, x) in map {
            if let (Some(camera), false) = (CameraKey::parse(key), x.is_object()) {
                t.global.push(PublishedPose {
                    key: key.clone(),
                    camera,
                    pose: pose(key, x)?,
                });
                continue;
            }
            let fields = x.as_object().ok_or_else(|| {
                json_err(
                    path,
                    key,
                    format!(
                        "{}: expected an episode's entry {{\"<serial>\": [x, y, z, rx, ry, rz], ...}}",
                        short(x)
                    ),
                )
            })?;
            let mut poses = Vec::new();
            for (ck, e) in fields {
                if let Some(camera) = CameraKey::parse(ck) {
                    poses.push(PublishedPose {
                        key: ck.clone(),
                        camera,
                        pose: pose(&format!("{key}.{ck}"), e)?,
                    });
                }
            }
            t.by_episode.insert(key.clone(), poses);
        }
        Ok(t)
    }

    /// The poses for the first of `episode_ids` with an entry (and that
    /// id), else the poses for every episode (id `None`).
    pub fn entry(&self, episode_ids: &[&str]) -> (Option<String>, &[PublishedPose]) {
        episode_ids
            .iter()
            .find_map(|id| {
                self.by_episode
                    .get(*id)
                    .map(|p| (Some(id.to_string()), p.as_slice()))
            })
            .unwrap_or((None, self.global.as_slice()))
    }
}

/// The pose of camera `serial` among `poses`: the left eye's (or bare
/// serial's) if given, else the right eye's.
pub fn find_pose<'a>(poses: &'a [PublishedPose], serial: &str) -> Option<&'a PublishedPose> {
    let of = |eye| {
        poses
            .iter()
            .find(|p| p.camera.serial == serial && p.camera.eye() == eye)
    };
    of(Eye::Left).or_else(|| of(Eye::Right))
}
