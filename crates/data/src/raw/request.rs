//! A conversion as a user asks for it (`bridgev2w convert`'s flags,
//! `bw.convert`'s arguments): the source layout, its files and options,
//! checked together and turned into a [`RawSource`] and [`ConvertOptions`],
//! then run by [`convert_source`]. The CLI and the Python package both build
//! a [`ConvertRequest`] and call [`ConvertRequest::run`].

use super::agibot::{AgibotOptions, GripperSource};
use super::convert::{ConvertError, ConvertOptions, ConvertReport, REPORT_FILE};
use super::ctrl_world::{self, CtrlWorldOptions, SplitRule};
use super::droid::DroidOptions;
use super::droid_calibration::MissingCalibration;
use super::source::{convert_source, ConvertProgress, RawSource};
use super::RawError;
use bridgev2w_embodiment::embodiment::Embodiment;
use std::path::{Path, PathBuf};
use std::str::FromStr;

/// A raw source layout.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SourceFormat {
    /// DROID raw episodes (`metadata_*.json`, `trajectory.h5`, recordings/MP4).
    Droid,
    /// AgiBot World (`proprio_stats`, `parameters`, `observations`).
    Agibot,
    /// DROID episodes of the Ctrl-World layout (`annotation/<split>/<id>.json`,
    /// `videos/<split>/<id>/{0,1,2}.mp4`), cameras from camera JSONs.
    CtrlWorld,
}

impl SourceFormat {
    /// The name recorded in `meta/info.json` and accepted by [`FromStr`].
    pub fn name(self) -> &'static str {
        match self {
            Self::Droid => "droid",
            Self::Agibot => "agibot",
            Self::CtrlWorld => "ctrl-world",
        }
    }

    /// The frame rate a conversion records by default (DROID 15, AgiBot
    /// World 30, the Ctrl-World layout 5).
    pub fn default_fps(self) -> u32 {
        match self {
            Self::Droid => 15,
            Self::Agibot => 30,
            Self::CtrlWorld => ctrl_world::FPS,
        }
    }

    /// The built-in robot a conversion uses by default.
    pub fn default_robot(self) -> &'static str {
        match self {
            Self::Droid | Self::CtrlWorld => "franka-robotiq",
            Self::Agibot => "agibot-g1",
        }
    }
}

impl FromStr for SourceFormat {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "droid" => Ok(Self::Droid),
            "agibot" => Ok(Self::Agibot),
            "ctrl-world" => Ok(Self::CtrlWorld),
            _ => Err(format!(
                "{s:?}: expected \"droid\", \"agibot\" or \"ctrl-world\""
            )),
        }
    }
}

impl std::fmt::Display for SourceFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A conversion: what to read, with which options, and where to write.
#[derive(Debug, Clone)]
pub struct ConvertRequest {
    /// The source layout.
    pub format: SourceFormat,
    /// A DROID folder (searched for episodes), an AgiBot World root or a
    /// Ctrl-World collection.
    pub src: PathBuf,
    /// The dataset to write.
    pub out: PathBuf,
    /// Replace an existing `out` once the new dataset is complete.
    pub overwrite: bool,
    /// The robot's names for the recorded joint columns.
    pub joint_names: Option<Vec<String>>,
    /// Output width (pixels, even).
    pub width: usize,
    /// Output height (pixels, even).
    pub height: usize,
    /// Frame rate recorded (default [`SourceFormat::default_fps`]).
    pub fps: Option<u32>,
    /// DROID: the intrinsics file (required).
    pub intrinsics: Option<PathBuf>,
    /// DROID: extrinsics files, earlier first.
    pub calibration: Vec<PathBuf>,
    /// DROID: a camera without published extrinsics.
    pub missing_calibration: MissingCalibration,
    /// DROID roles or AgiBot World camera names (default the layout's).
    pub cameras: Option<Vec<String>>,
    /// Ctrl-World: a camera JSON per exterior role.
    pub camera_json: Vec<(String, PathBuf)>,
    /// Ctrl-World: only these episodes.
    pub include: Option<Vec<String>>,
    /// Ctrl-World: the split of matching views.
    pub split_rules: Vec<SplitRule>,
    /// AgiBot World: where the gripper closure comes from.
    pub gripper_source: GripperSource,
    /// AgiBot World: `state/effector/position` readings (open, closed).
    pub gripper_range: (f64, f64),
    /// The split recorded for every episode.
    pub split: String,
    /// Skip failing episodes/cameras (listed in the report) instead of stopping.
    pub skip_bad: bool,
    /// Convert at most this many episodes.
    pub limit: Option<usize>,
}

impl ConvertRequest {
    /// A request with the defaults of `bridgev2w convert`: 96x64, the
    /// layout's frame rate and cameras, split `train`.
    pub fn new(format: SourceFormat, src: PathBuf, out: PathBuf) -> Self {
        let agibot = AgibotOptions::default();
        Self {
            format,
            src,
            out,
            overwrite: false,
            joint_names: None,
            width: 96,
            height: 64,
            fps: None,
            intrinsics: None,
            calibration: Vec::new(),
            missing_calibration: MissingCalibration::default(),
            cameras: None,
            camera_json: Vec::new(),
            include: None,
            split_rules: Vec::new(),
            gripper_source: agibot.gripper,
            gripper_range: (agibot.gripper_open, agibot.gripper_closed),
            split: "train".into(),
            skip_bad: false,
            limit: None,
        }
    }

    /// The dataset options.
    pub fn options(&self) -> ConvertOptions {
        ConvertOptions {
            width: self.width,
            height: self.height,
            fps: self.fps.unwrap_or(self.format.default_fps()),
            joint_names: self.joint_names.clone(),
            skip_bad: self.skip_bad,
            split: Some(self.split.clone()),
            source_format: self.format.name().into(),
            overwrite: self.overwrite,
        }
    }

    /// The source, every option checked against the layout before anything
    /// is read: options of another layout refused by name, DROID's
    /// intrinsics required, the gripper range two different finite
    /// readings, every named file present.
    pub fn source(&self) -> Result<RawSource, ConvertError> {
        let refuse = |m: &str| Err(ConvertError::Options(m.to_string()));
        let ctrl_world_only =
            !self.camera_json.is_empty() || self.include.is_some() || !self.split_rules.is_empty();
        if self.format != SourceFormat::CtrlWorld && ctrl_world_only {
            return refuse(
                "camera (ROLE=CAMERA_JSON), include, split rules: apply to the ctrl-world format",
            );
        }
        let droid_only = self.intrinsics.is_some() || !self.calibration.is_empty();
        if self.format != SourceFormat::Droid && droid_only {
            return refuse(&format!(
                "intrinsics, calibration: apply to raw DROID; {}",
                match self.format {
                    SourceFormat::Agibot => "AgiBot World episodes carry their camera parameters",
                    _ => "the ctrl-world layout takes a camera JSON per role (ROLE=CAMERA_JSON)",
                }
            ));
        }
        match self.format {
            SourceFormat::CtrlWorld if self.cameras.is_some() => {
                return refuse("cameras: apply to raw DROID and AgiBot World; the ctrl-world layout takes a camera JSON per role (ROLE=CAMERA_JSON)");
            }
            SourceFormat::Droid if self.intrinsics.is_none() => {
                return refuse("intrinsics: a file is required for DROID: the raw episodes' trajectory.h5 records no intrinsics (DROID publishes them as intrinsics.json)");
            }
            SourceFormat::Agibot => {
                let (open, closed) = self.gripper_range;
                if !(open.is_finite() && closed.is_finite()) || open == closed {
                    return refuse(&format!("gripper range ({open}, {closed}): expected two different finite readings (open, closed)"));
                }
            }
            _ => {}
        }
        self.options().validate()?;
        self.check_files()?;
        let source = match self.format {
            SourceFormat::CtrlWorld => RawSource::CtrlWorld {
                root: self.src.clone(),
                options: CtrlWorldOptions {
                    cameras: self.camera_json.clone(),
                    include: self.include.clone(),
                    split_rules: self.split_rules.clone(),
                },
            },
            SourceFormat::Droid => {
                let intrinsics = self.intrinsics.as_deref().unwrap_or(Path::new(""));
                let mut options =
                    DroidOptions::from_calibration_files(intrinsics, &self.calibration)?;
                options.missing_calibration = self.missing_calibration;
                if let Some(c) = &self.cameras {
                    options.roles = c.clone();
                }
                RawSource::Droid {
                    root: self.src.clone(),
                    options,
                }
            }
            SourceFormat::Agibot => {
                let mut options = AgibotOptions {
                    gripper: self.gripper_source,
                    gripper_open: self.gripper_range.0,
                    gripper_closed: self.gripper_range.1,
                    ..AgibotOptions::default()
                };
                if let Some(c) = &self.cameras {
                    options.cameras = c.clone();
                }
                RawSource::Agibot {
                    root: self.src.clone(),
                    options,
                }
            }
        };
        source.validate().map_err(ConvertError::Options)?;
        if !self.src.exists() {
            return Err(ConvertError::Raw(RawError::Missing {
                path: self.src.clone(),
                what: "source folder".into(),
            }));
        }
        Ok(source)
    }

    /// The intrinsics and calibration files exist (camera JSONs are read,
    /// and named, by the Ctrl-World options' check; the source folder is
    /// checked after the cameras, so that a camera list's error comes first).
    fn check_files(&self) -> Result<(), ConvertError> {
        let missing = |path: &Path, what: String| {
            Err(ConvertError::Raw(RawError::Missing {
                path: path.to_path_buf(),
                what,
            }))
        };
        for p in self.intrinsics.iter().chain(&self.calibration) {
            if !p.is_file() {
                return missing(p, "file".into());
            }
        }
        Ok(())
    }

    /// Checks the request, then converts (into a temporary folder beside
    /// `out`, renamed when complete).
    pub fn run(
        &self,
        embodiment: &Embodiment,
        progress: &dyn Fn(ConvertProgress),
    ) -> Result<ConvertReport, ConvertError> {
        let source = self.source()?;
        convert_source(
            &source,
            self.limit,
            embodiment,
            &self.out,
            &self.options(),
            progress,
        )
    }
}

impl ConvertReport {
    /// What a finished conversion tells its user: the counts, the skipped
    /// items, the action frames, the notes by kind and empty-mask views.
    pub fn summary(&self, request: &ConvertRequest, robot: &str) -> String {
        let out = &request.out;
        let mut text = format!(
            "wrote {} (LeRobot v3.0): {} episodes read, {} camera episodes of {}x{} with calc masks, robot {robot}\n",
            out.display(),
            self.episodes,
            self.views_written,
            request.width,
            request.height,
        );
        if !self.skipped.is_empty() {
            text.push_str(&format!(
                "  skipped {} item(s), listed in {}:\n",
                self.skipped.len(),
                out.join("skipped.json").display()
            ));
            for s in &self.skipped {
                text.push_str(&format!("    {}: {}\n", s.item, s.error));
            }
        }
        if !self.ee_frames.is_empty() {
            text.push_str(&format!(
                "  actions: flange poses of {} (meta/info.json bridgev2w_source.ee_frame)\n",
                self.ee_frames.join(", ")
            ));
        }
        for (kind, notes, episodes, warning) in self.note_summary() {
            text.push_str(&format!(
                "  {}{kind}: {notes} in {episodes} episode(s)\n",
                if warning { "warning: " } else { "" }
            ));
        }
        if !self.notes.is_empty() {
            text.push_str(&format!("  details: {}\n", out.join(REPORT_FILE).display()));
        }
        for v in &self.empty_mask_views {
            text.push_str(&format!("  warning: {v}: the robot is outside the image in every frame (check the calibration)\n"));
        }
        text
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn formats_round_trip_and_an_unknown_one_is_named() {
        for f in [
            SourceFormat::Droid,
            SourceFormat::Agibot,
            SourceFormat::CtrlWorld,
        ] {
            assert_eq!(f.name().parse::<SourceFormat>(), Ok(f));
        }
        let e = "rlds".parse::<SourceFormat>().unwrap_err();
        assert!(e.contains("\"rlds\"") && e.contains("ctrl-world"), "{e}");
    }

    #[test]
    fn options_are_refused_before_any_file_is_looked_at() {
        let absent = PathBuf::from("/nonexistent/src");
        let out = PathBuf::from("/nonexistent/out");
        let refused = |r: ConvertRequest, want: &str| {
            let e = r.source().unwrap_err().to_string();
            assert!(e.contains(want), "{want:?} not in {e}");
        };
        let droid = ConvertRequest::new(SourceFormat::Droid, absent.clone(), out.clone());
        refused(droid.clone(), "intrinsics: a file is required for DROID");
        let agibot = ConvertRequest::new(SourceFormat::Agibot, absent.clone(), out.clone());
        refused(
            ConvertRequest {
                gripper_range: (35.0, 35.0),
                ..agibot.clone()
            },
            "gripper range (35, 35)",
        );
        refused(
            ConvertRequest {
                intrinsics: Some("i.json".into()),
                ..agibot.clone()
            },
            "AgiBot World episodes carry their camera parameters",
        );
        refused(
            ConvertRequest {
                include: Some(vec!["a/val/1".into()]),
                ..droid.clone()
            },
            "apply to the ctrl-world format",
        );
        refused(
            ConvertRequest {
                fps: Some(0),
                ..agibot.clone()
            },
            "--fps 0",
        );
        // Options fine: the missing source is named.
        refused(agibot, "/nonexistent/src: missing source folder");
        refused(
            ConvertRequest {
                intrinsics: Some("/nonexistent/i.json".into()),
                ..droid
            },
            "/nonexistent/i.json: missing file",
        );
    }
}
