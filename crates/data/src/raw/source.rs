//! A raw source folder to a training dataset in one call: find its episodes
//! (DROID or AgiBot World layout), keep the first `limit`, refuse a source
//! without any, convert them into a temporary folder next to `out` and rename
//! it into place (nothing is left behind when the conversion fails). The
//! `convert` command and the Python package's `bw.convert` both call
//! [`convert_source`].

use super::agibot::{self, AgibotOptions};
use super::convert::{
    convert, convert_listing, ConvertError, ConvertOptions, ConvertReport, Skipped,
};
use super::ctrl_world::{self, CtrlWorldOptions};
use super::droid::{self, DroidOptions};
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_io::output::OutputDir;
use std::path::{Path, PathBuf};

/// A raw source: its root folder, its layout and the layout's options.
#[derive(Debug, Clone)]
pub enum RawSource {
    /// DROID raw episodes under `root` (directories with `trajectory.h5`).
    Droid {
        /// Searched for episodes.
        root: PathBuf,
        /// Cameras and calibration.
        options: DroidOptions,
    },
    /// DROID episodes of the Ctrl-World layout under `root`
    /// (`<collection>/annotation/<split>/<id>.json`, `videos/...`), with a
    /// camera JSON per exterior camera ([`ctrl_world`]).
    CtrlWorld {
        /// A collection, or a folder holding several.
        root: PathBuf,
        /// Cameras and episode selection.
        options: CtrlWorldOptions,
    },
    /// An AgiBot World root (`proprio_stats/<task>/<episode>/...`).
    Agibot {
        /// The dataset's root.
        root: PathBuf,
        /// Cameras and gripper readings.
        options: AgibotOptions,
    },
}

impl RawSource {
    /// Checks the source's options before anything is read or written: the
    /// cameras (DROID roles, or AgiBot World camera names) must be at least
    /// one, none named twice ([`super::check_camera_list`]), DROID roles
    /// among [`droid::ROLES`] and AgiBot names plain names. The error names
    /// `cameras`, the list and what was expected; the CLI and the Python
    /// package both get it from [`convert_source`].
    pub fn validate(&self) -> Result<(), String> {
        let (cameras, check) = match self {
            RawSource::Droid { options, .. } => (&options.roles, options.check_roles()),
            RawSource::CtrlWorld { options, .. } => {
                return options.validate().map_err(|e| format!("cameras: {e}"))
            }
            RawSource::Agibot { options, .. } => (
                &options.cameras,
                super::check_camera_list(&options.cameras).and_then(|()| {
                    options.cameras.iter().try_for_each(|c| {
                        bridgev2w_io::confine::check_name(c).map_err(|e| format!("camera name {e}"))
                    })
                }),
            ),
        };
        check.map_err(|e| format!("cameras {cameras:?}: {e}"))
    }
}

/// Progress of [`convert_source`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConvertProgress<'a> {
    /// The episodes to convert were found (after the limit).
    Found(usize),
    /// One episode (its id) was converted or skipped.
    Done(&'a str),
}

/// Converts the episodes of `source` (at most `limit`) into a LeRobot v3.0
/// dataset at `out`, which must not exist unless `options.overwrite`; see
/// the module documentation. The options are checked first
/// ([`RawSource::validate`], [`ConvertOptions::validate`]).
pub fn convert_source(
    source: &RawSource,
    limit: Option<usize>,
    embodiment: &Embodiment,
    out: &Path,
    options: &ConvertOptions,
    progress: &dyn Fn(ConvertProgress),
) -> Result<ConvertReport, ConvertError> {
    source.validate().map_err(ConvertError::Options)?;
    options.validate()?;
    let limit = limit.unwrap_or(usize::MAX);
    let root = match source {
        RawSource::Droid { root, .. }
        | RawSource::CtrlWorld { root, .. }
        | RawSource::Agibot { root, .. } => root,
    };
    // An output equal to, inside or containing the source would delete it.
    let output = OutputDir::create_for(out, options.overwrite, &[root])
        .map_err(|e| ConvertError::Options(format!("out: {e}")))?;
    let tmp = output.path().to_path_buf();
    let on_item = |id: &str| progress(ConvertProgress::Done(id));
    let report = match source {
        RawSource::Droid { root, options: o } => {
            let dirs: Vec<PathBuf> = droid::find_episodes(root)?
                .into_iter()
                .take(limit)
                .collect();
            if dirs.is_empty() {
                return Err(ConvertError::Options(format!(
                    "{}: no DROID episodes (directories with trajectory.h5) found",
                    root.display()
                )));
            }
            progress(ConvertProgress::Found(dirs.len()));
            let items = dirs
                .iter()
                .map(|d| (d.display().to_string(), droid::read_episode(d, o)));
            convert(items, embodiment, &tmp, options, &on_item)?
        }
        RawSource::CtrlWorld { root, options: o } => {
            let found = ctrl_world::select(ctrl_world::find_episodes(root)?, o.include.as_deref())?;
            let (kept, repeats) = ctrl_world::dedupe(found)?;
            let kept: Vec<_> = kept.into_iter().take(limit).collect();
            progress(ConvertProgress::Found(kept.len()));
            let items = kept
                .iter()
                .map(|e| (e.name(), ctrl_world::read_episode(e, o)));
            // Repeats are listed, not converted twice (their frames would
            // sit on both sides of a train/test split).
            let repeats = repeats
                .into_iter()
                .map(|(repeat, original)| Skipped {
                    item: repeat,
                    error: format!("the same joint recording as {original}: not converted twice"),
                })
                .collect();
            convert_listing(items, repeats, embodiment, &tmp, options, &on_item)?
        }
        RawSource::Agibot { root, options: o } => {
            let keys: Vec<_> = agibot::find_episodes(root)?
                .into_iter()
                .take(limit)
                .collect();
            if keys.is_empty() {
                return Err(ConvertError::Options(format!(
                    "{}: no AgiBot World episodes (proprio_stats/<task>/<episode>/proprio_stats.h5) found",
                    root.display()
                )));
            }
            progress(ConvertProgress::Found(keys.len()));
            let items = keys
                .iter()
                .map(|k| (k.to_string(), agibot::read_episode(root, k, o)));
            convert(items, embodiment, &tmp, options, &on_item)?
        }
    };
    output
        .commit()
        .map_err(|e| ConvertError::Options(format!("out: {e}")))?;
    Ok(report)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn an_output_overlapping_the_source_is_refused_and_the_source_kept() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("agibot");
        std::fs::create_dir_all(root.join("proprio_stats")).unwrap();
        std::fs::write(root.join("proprio_stats/keep.txt"), "k").unwrap();
        let source = RawSource::Agibot {
            root: root.clone(),
            options: AgibotOptions::default(),
        };
        let embodiment = Embodiment::builtin("agibot-g1").unwrap();
        let options = ConvertOptions {
            width: 64,
            height: 48,
            fps: 15,
            joint_names: None,
            skip_bad: false,
            split: None,
            source_format: "agibot".into(),
            overwrite: true,
        };
        for (out, how) in [
            (root.clone(), "is the input"),
            (root.join("out"), "is inside the input"),
            (dir.path().to_path_buf(), "contains the input"),
        ] {
            let e = convert_source(&source, None, &embodiment, &out, &options, &|_| {})
                .unwrap_err()
                .to_string();
            assert!(
                e.contains(how) && e.contains(&*root.to_string_lossy()),
                "{e}"
            );
        }
        let kept = std::fs::read_to_string(root.join("proprio_stats/keep.txt")).unwrap();
        assert_eq!(kept, "k");
    }
}
