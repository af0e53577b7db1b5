//! DROID episodes in the Ctrl-World layout (the DROID video + state excerpts
//! that world-model papers ship, e.g. Ctrl-World's `dataset_example/`):
//!
//! ```text
//! <collection>/annotation/<split>/<id>.json   texts, video_length, states (T x 7:
//!                                             flange x, y, z, roll, pitch, yaw
//!                                             [extrinsic XYZ], gripper), joints
//!                                             (T x 8: panda_joint1..7 [rad],
//!                                             gripper 0 open .. 1 closed), or the
//!                                             15 Hz observation.state.joint_position
//!                                             and .gripper_position arrays
//! <collection>/videos/<split>/<id>/0.mp4      exterior camera 1 (left eye)
//! <collection>/videos/<split>/<id>/1.mp4      exterior camera 2 (left eye)
//! <collection>/videos/<split>/<id>/2.mp4      wrist camera
//! ```
//!
//! The layout carries no camera parameters: each exterior camera's comes
//! from a camera JSON, usually the output of `bridgev2w calibrate` on the
//! same rig ([`CtrlWorldOptions::cameras`]); a view without one is not
//! converted. The wrist camera moves with the hand and cannot be given a
//! fixed camera. Collections often repeat an episode under another name
//! (five of the 33 `droid_new_setup*` episodes): [`dedupe`] keeps the first
//! of identical joint recordings and lists the others.

use super::droid::{EE_FRAME, JOINT_NAMES};
use super::report::Note;
use super::{confined, json_err, read_json, sub_dirs, RawEpisode, RawError, RawView};
use bridgev2w_embodiment::camera::Camera;
use bridgev2w_io::confine;
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The camera roles of the layout, in file order (`0.mp4`, `1.mp4`, `2.mp4`).
pub const ROLES: [&str; 3] = ["ext1", "ext2", "wrist"];

/// The frame rate of the layout's videos (DROID subsampled to 5 Hz).
pub const FPS: u32 = 5;

/// One episode of the layout.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
pub struct CtrlWorldEpisode {
    /// Its collection: the folder holding `annotation/` and `videos/`,
    /// relative to the root (`droid_new_setup_full/drawer`).
    pub collection: String,
    /// `train` or `val`.
    pub split: String,
    /// The episode's id (its folder name).
    pub id: String,
    /// `videos/<split>/<id>`.
    pub dir: PathBuf,
    /// `annotation/<split>/<id>.json`.
    pub annotation: PathBuf,
}

impl CtrlWorldEpisode {
    /// Whether the episode was recorded on the Ctrl-World authors' shared
    /// rig (`droid_new_setup*`: the same cameras across its episodes).
    pub fn shared_rig(&self) -> bool {
        self.collection.starts_with("droid_new_setup")
    }

    /// `collection/split/id`: the episode's name in reports and in
    /// [`CtrlWorldOptions::include`].
    pub fn name(&self) -> String {
        format!("{}/{}/{}", self.collection, self.split, self.id)
    }

    /// The video of a camera role (`ext1` is `0.mp4`).
    pub fn video(&self, role: usize) -> PathBuf {
        self.dir.join(format!("{role}.mp4"))
    }
}

/// Import settings.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CtrlWorldOptions {
    /// Per camera role to convert (`ext1`, `ext2`), its camera JSON (the
    /// `camera.json` that `bridgev2w calibrate` writes, or any camera file
    /// `bridgev2w masks --camera` reads), used for every episode (one rig).
    pub cameras: Vec<(String, PathBuf)>,
    /// Only these episodes (`collection/split/id`, as [`CtrlWorldEpisode::name`]);
    /// `None`: all. A name that matches no episode is an error.
    pub include: Option<Vec<String>>,
    /// Which split each view is written with, first match wins; a view no
    /// rule matches takes the conversion's split.
    pub split_rules: Vec<SplitRule>,
}

/// `EPISODE:ROLE=SPLIT`: the views of an episode (`collection/split/id`,
/// or `*` for any) and camera role (`ext1`, `ext2`; omitted or `*` for
/// any) are written with split SPLIT, or not converted when SPLIT is `-`.
/// E.g. `droid_new_setup/val/0002:ext2=unseen_camera` (a held-out view),
/// `*:ext2=-` (that camera only where another rule asks for it).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SplitRule {
    /// The episode's name; `None`: any.
    pub episode: Option<String>,
    /// The camera role; `None`: any.
    pub role: Option<String>,
    /// The split; `None`: the view is not converted.
    pub split: Option<String>,
}

impl std::str::FromStr for SplitRule {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let bad = |why: &str| {
            format!("split rule {s:?}: {why}: expected EPISODE[:ROLE]=SPLIT (EPISODE collection/split/id or *, ROLE ext1 or ext2, SPLIT a name or - for not converted)")
        };
        let (pattern, split) = s.rsplit_once('=').ok_or_else(|| bad("no '='"))?;
        let (episode, role) = match pattern.split_once(':') {
            Some((e, r)) => (e.trim(), r.trim()),
            None => (pattern.trim(), "*"),
        };
        let any = |x: &str| (x != "*").then(|| x.to_string());
        let role = any(role);
        if let Some(r) = &role {
            if r != "ext1" && r != "ext2" {
                return Err(bad(&format!("role {r:?}")));
            }
        }
        if episode.is_empty() {
            return Err(bad("no episode"));
        }
        let split = split.trim();
        let split = match split {
            "-" => None,
            "" => return Err(bad("no split")),
            s if s.contains(['/', '\\', ':']) => return Err(bad(&format!("split {s:?}"))),
            s => Some(s.to_string()),
        };
        Ok(SplitRule {
            episode: any(episode),
            role,
            split,
        })
    }
}

impl SplitRule {
    fn matches(&self, episode: &str, role: &str) -> bool {
        self.episode.as_deref().is_none_or(|e| e == episode)
            && self.role.as_deref().is_none_or(|r| r == role)
    }
}

impl CtrlWorldOptions {
    /// Checks the camera list: at least one, each role among the exterior
    /// roles and named once, each file a regular file.
    pub fn validate(&self) -> Result<(), String> {
        if self.cameras.is_empty() {
            return Err(
                "no camera given: expected ROLE=CAMERA_JSON for ext1 and/or ext2 (the layout has no calibration; `bridgev2w calibrate` makes one)"
                    .into(),
            );
        }
        let mut seen = Vec::new();
        for (role, path) in &self.cameras {
            match role.as_str() {
                "ext1" | "ext2" => {}
                "wrist" => {
                    return Err(
                        "wrist: the wrist camera moves with the hand, a fixed camera JSON cannot describe it: expected ext1 or ext2"
                            .into(),
                    )
                }
                other => return Err(format!("role {other:?}: expected ext1 or ext2")),
            }
            if seen.contains(role) {
                return Err(format!("role {role} given twice: expected each once"));
            }
            seen.push(role.clone());
            confine::regular_file(path, confine::MAX_METADATA_BYTES)
                .map_err(|e| format!("{role} camera {}: {e}", path.display()))?;
        }
        for rule in &self.split_rules {
            if let Some(role) = &rule.role {
                if !self.cameras.iter().any(|(r, _)| r == role) {
                    return Err(format!(
                        "split rule for {role}: no camera {role} is converted (expected one of the --camera roles)"
                    ));
                }
            }
        }
        Ok(())
    }

    /// The cameras read: (role index, role, camera).
    fn read_cameras(&self) -> Result<Vec<(usize, String, Camera)>, RawError> {
        self.cameras
            .iter()
            .map(|(role, path)| {
                let index = ROLES.iter().position(|r| r == role).unwrap_or(0);
                let camera = Camera::from_json_file(path)
                    .map_err(|e| json_err(path, "", format!("camera for {role}: {e}")))?;
                Ok((index, role.clone(), camera))
            })
            .collect()
    }
}

/// Every episode under `root`: each folder `<collection>/videos/<split>/<id>`
/// holding `0.mp4` whose `<collection>/annotation/<split>/<id>.json` exists,
/// sorted. `root` may be a collection itself or hold several. Symbolic
/// links to folders are not followed. No episode is an error naming the
/// root and the layout expected.
pub fn find_episodes(root: &Path) -> Result<Vec<CtrlWorldEpisode>, RawError> {
    if !root.is_dir() {
        return Err(RawError::Missing {
            path: root.to_path_buf(),
            what: "Ctrl-World DROID folder".into(),
        });
    }
    let mut out = Vec::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(dir) = stack.pop() {
        let videos = dir.join("videos");
        if videos.is_dir() && dir.join("annotation").is_dir() {
            // The root itself may be a collection: then its own name.
            let relative = dir.strip_prefix(root).unwrap_or(&dir);
            let collection = if relative.as_os_str().is_empty() {
                file_name(&root.canonicalize().unwrap_or_else(|_| root.to_path_buf()))
            } else {
                relative.to_string_lossy().replace('\\', "/")
            };
            for split in sub_dirs(&videos)? {
                let split_name = file_name(&split);
                for ep in sub_dirs(&split)? {
                    let id = file_name(&ep);
                    let annotation = dir
                        .join("annotation")
                        .join(&split_name)
                        .join(format!("{id}.json"));
                    if ep.join("0.mp4").is_file() && annotation.is_file() {
                        out.push(CtrlWorldEpisode {
                            collection: collection.clone(),
                            split: split_name.clone(),
                            id,
                            dir: ep,
                            annotation,
                        });
                    }
                }
            }
        } else {
            stack.extend(sub_dirs(&dir)?);
        }
    }
    if out.is_empty() {
        return Err(RawError::Missing {
            path: root.to_path_buf(),
            what: "DROID episode of the Ctrl-World layout (<collection>/videos/<split>/<id>/0.mp4 with <collection>/annotation/<split>/<id>.json)".into(),
        });
    }
    out.sort();
    Ok(out)
}

/// Keeps the episodes named in `include` (all when `None`), in the order
/// found; a name that matches none is an error listing a few that exist.
pub fn select(
    episodes: Vec<CtrlWorldEpisode>,
    include: Option<&[String]>,
) -> Result<Vec<CtrlWorldEpisode>, RawError> {
    let Some(names) = include else {
        return Ok(episodes);
    };
    for n in names {
        if !episodes.iter().any(|e| &e.name() == n) {
            let known: Vec<String> = episodes.iter().take(4).map(|e| e.name()).collect();
            return Err(RawError::Inconsistent {
                episode: n.clone(),
                message: format!(
                    "named in include but not found: expected collection/split/id, e.g. {}",
                    known.join(", ")
                ),
            });
        }
    }
    Ok(episodes
        .into_iter()
        .filter(|e| names.contains(&e.name()))
        .collect())
}

/// For an episode left out as a repeat: its name and the name of the
/// earlier episode with the same joint recording.
pub type Repeat = (String, String);

/// Splits `episodes` into those kept and, for each repeat of an earlier
/// episode's joint recording (bit for bit), `(repeat, original)` names.
pub fn dedupe(
    episodes: Vec<CtrlWorldEpisode>,
) -> Result<(Vec<CtrlWorldEpisode>, Vec<Repeat>), RawError> {
    let mut seen: BTreeMap<Vec<u64>, String> = BTreeMap::new();
    let mut kept = Vec::new();
    let mut repeats = Vec::new();
    for ep in episodes {
        let (joints, grippers) = read_annotation_joints(&ep.annotation)?;
        let key: Vec<u64> = joints
            .iter()
            .zip(&grippers)
            .flat_map(|(j, g)| j.iter().chain(std::iter::once(g)).map(|v| v.to_bits()))
            .collect();
        match seen.get(&key) {
            Some(first) => repeats.push((ep.name(), first.clone())),
            None => {
                seen.insert(key, ep.name());
                kept.push(ep);
            }
        }
    }
    Ok((kept, repeats))
}

/// Reads one episode with the views of `options.cameras`.
pub fn read_episode(
    ep: &CtrlWorldEpisode,
    options: &CtrlWorldOptions,
) -> Result<RawEpisode, RawError> {
    let path = &ep.annotation;
    let value = read_json(path)?;
    let map = value
        .as_object()
        .ok_or_else(|| json_err(path, "", "expected a JSON object (a Ctrl-World annotation)"))?;
    let (joints, grippers) = annotation_joints(path, map)?;
    let states = matrix(path, map, "states", 7)?
        .ok_or_else(|| json_err(path, "states", "missing: expected T x 7 flange poses"))?;
    if states.len() != joints.len() {
        return Err(RawError::Inconsistent {
            episode: ep.name(),
            message: format!(
                "{} states but {} joint rows: expected one of each per frame",
                states.len(),
                joints.len()
            ),
        });
    }
    let frames = joints.len();
    let task = match map.get("texts") {
        Some(Value::Array(a)) => a.first().and_then(Value::as_str).map(str::to_string),
        Some(Value::String(s)) => Some(s.clone()),
        _ => None,
    }
    .filter(|t| !t.is_empty());
    let mut clamped = 0;
    let mut worst = 0.0f64;
    let grippers: Vec<Vec<f64>> = grippers
        .into_iter()
        .map(|g| {
            if !(0.0..=1.0).contains(&g) {
                clamped += 1;
                if (g - g.clamp(0.0, 1.0)).abs() > (worst - worst.clamp(0.0, 1.0)).abs() {
                    worst = g;
                }
            }
            vec![g.clamp(0.0, 1.0)]
        })
        .collect();
    // The actions: the recorded flange pose with the gripper closure.
    let ee_actions: Vec<Vec<f64>> = states
        .iter()
        .zip(&grippers)
        .map(|(s, g)| {
            let mut row = s[..6].to_vec();
            row.push(g[0]);
            row
        })
        .collect();
    let mut views = Vec::new();
    for (index, role, camera) in options.read_cameras()? {
        let video = confined(
            &ep.dir,
            &format!("{index}.mp4"),
            confine::MAX_VIDEO_BYTES,
            role.as_str(),
        )?;
        let split = match options
            .split_rules
            .iter()
            .find(|r| r.matches(&ep.name(), &role))
        {
            Some(rule) => match &rule.split {
                Some(s) => Some(s.clone()),
                None => continue, // not converted, as asked
            },
            None => None,
        };
        views.push(RawView {
            name: role,
            video,
            intrinsics: camera.intrinsics,
            world_from_camera: vec![camera.world_from_camera; frames],
            frame_times: None,
            split,
        });
    }
    let mut raw = RawEpisode {
        id: ep.name(),
        source: ep.dir.clone(),
        task,
        frames,
        joints,
        joint_names: JOINT_NAMES.iter().map(|s| s.to_string()).collect(),
        grippers,
        ee_actions,
        ee_frames: vec![EE_FRAME.to_string()],
        views,
        notes: Vec::new(),
    };
    if clamped > 0 {
        raw.note(
            None,
            Note::GripperClamped {
                arm: 0,
                field: "joints[:, 7]".into(),
                count: clamped,
                worst,
                open: 0.0,
                closed: 1.0,
            },
        );
    }
    Ok(raw)
}

/// The arm joints (T x 7) and gripper closures (T) of an annotation file.
fn read_annotation_joints(path: &Path) -> Result<(Vec<Vec<f64>>, Vec<f64>), RawError> {
    let value = read_json(path)?;
    let map = value
        .as_object()
        .ok_or_else(|| json_err(path, "", "expected a JSON object (a Ctrl-World annotation)"))?;
    annotation_joints(path, map)
}

/// `joints` (T x 8), or the 15 Hz `observation.state.joint_position` and
/// `.gripper_position` taken every `n`-th row for `video_length` frames
/// (`droid_subset`: frame k is row 3k).
fn annotation_joints(
    path: &Path,
    map: &serde_json::Map<String, Value>,
) -> Result<(Vec<Vec<f64>>, Vec<f64>), RawError> {
    if let Some(rows) = matrix(path, map, "joints", 8)? {
        let grippers = rows.iter().map(|r| r[7]).collect();
        let arm = rows.into_iter().map(|r| r[..7].to_vec()).collect();
        return Ok((arm, grippers));
    }
    let field = "observation.state.joint_position";
    let Some(arm) = matrix(path, map, field, 7)? else {
        return Err(json_err(
            path,
            "joints",
            "missing, and no \"observation.state.joint_position\": expected T x 8 joints (7 Franka joints + gripper) or the 15 Hz arrays",
        ));
    };
    let grip_field = "observation.state.gripper_position";
    let grip = matrix(path, map, grip_field, 1)?.ok_or_else(|| {
        json_err(
            path,
            grip_field,
            format!("missing beside \"{field}\": expected both"),
        )
    })?;
    if grip.len() != arm.len() {
        return Err(json_err(
            path,
            grip_field,
            format!(
                "{} rows but \"{field}\" has {}: expected equal counts",
                grip.len(),
                arm.len()
            ),
        ));
    }
    let frames = match map.get("video_length").and_then(Value::as_u64) {
        Some(n) if n > 0 => n as usize,
        _ => {
            return Err(json_err(
                path,
                "video_length",
                "missing or not a positive integer: needed to match the 15 Hz arrays to the video's frames",
            ))
        }
    };
    let stride = ((arm.len() as f64 / frames as f64).round() as usize).max(1);
    let picked: Vec<usize> = (0..arm.len()).step_by(stride).take(frames).collect();
    Ok((
        picked.iter().map(|&i| arm[i].clone()).collect(),
        picked.iter().map(|&i| grip[i][0]).collect(),
    ))
}

/// A numeric matrix field (`cols` finite numbers per row, at least one row);
/// `None` when absent.
fn matrix(
    path: &Path,
    map: &serde_json::Map<String, Value>,
    field: &str,
    cols: usize,
) -> Result<Option<Vec<Vec<f64>>>, RawError> {
    let Some(v) = map.get(field) else {
        return Ok(None);
    };
    let rows = v
        .as_array()
        .ok_or_else(|| json_err(path, field, "expected an array of frames"))?;
    if rows.is_empty() {
        return Err(json_err(path, field, "no frames: expected at least one"));
    }
    let mut out = Vec::with_capacity(rows.len());
    for (t, row) in rows.iter().enumerate() {
        let values: Vec<f64> = match row {
            Value::Number(n) => vec![n.as_f64().unwrap_or(f64::NAN)],
            Value::Array(items) => items
                .iter()
                .map(|x| x.as_f64().unwrap_or(f64::NAN))
                .collect(),
            other => {
                return Err(json_err(
                    path,
                    field,
                    format!("frame {t} is {other}: expected numbers"),
                ))
            }
        };
        if values.len() != cols {
            return Err(json_err(
                path,
                field,
                format!("frame {t} has {} values: expected {cols}", values.len()),
            ));
        }
        if let Some(x) = values.iter().find(|x| !x.is_finite()) {
            return Err(json_err(
                path,
                field,
                format!("frame {t} holds {x}: expected finite numbers"),
            ));
        }
        out.push(values);
    }
    Ok(Some(out))
}

fn file_name(p: &Path) -> String {
    p.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default()
}
