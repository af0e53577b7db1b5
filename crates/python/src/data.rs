//! The data commands over the library crates: `synth.generate`, `convert`
//! and `read_episode` (the GIL released while they run).

use super::*;

/// An output folder that must not exist yet.
fn check_new_output(out: &Path) -> PyResult<()> {
    if out.exists() {
        return Err(PyFileExistsError::new_err(format!(
            "{}: already exists; choose another out or remove it",
            out.display()
        )));
    }
    Ok(())
}

/// Writes the synthetic tabletop dataset (LeRobot v3.0) of `bridgev2w synth`
/// to `out` (written to a temporary folder beside it, then renamed) with the GIL released;
/// returns its summary as a dict (`out`, `episodes`, `total_frames`,
/// `episodes_per_split`, `episodes_per_task`, `contact_events`,
/// `perturbed`, `perturbed_failed`).
#[pyfunction]
#[pyo3(signature = (out, robot, episodes_per_split, frames, width, height, fps, seed, tasks, perturbed_fraction, perturb_mm, engine = "builtin".to_string()))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn synth_generate<'py>(
    py: Python<'py>,
    out: PathBuf,
    robot: String,
    episodes_per_split: [usize; 4],
    frames: usize,
    width: u32,
    height: u32,
    fps: u32,
    seed: u64,
    tasks: Vec<String>,
    perturbed_fraction: f64,
    perturb_mm: f64,
    engine: String,
) -> PyResult<Bound<'py, PyDict>> {
    let tasks = tasks
        .iter()
        .map(|t| {
            Task::parse(t).ok_or_else(|| {
                PyValueError::new_err(format!(
                    "tasks: unknown task {t:?}, expected reach, push, pick_place or play"
                ))
            })
        })
        .collect::<PyResult<Vec<_>>>()?;
    let config = SynthConfig {
        robot,
        frames,
        width,
        height,
        fps,
        seed,
        tasks,
        episodes_per_split,
        perturb: Perturbation {
            fraction: perturbed_fraction,
            offset_mm: perturb_mm,
        },
        engine: engine
            .parse()
            .map_err(|e: String| PyValueError::new_err(format!("engine: {e}")))?,
    };
    config
        .validate()
        .map_err(|e| PyValueError::new_err(e.to_string()))?;
    let n = plan(&config).len();
    if n == 0 {
        return Err(PyValueError::new_err(
            "episodes_per_split: no episodes to generate",
        ));
    }
    check_new_output(&out)?;
    let summary = py
        .detach(|| {
            no_panic("synth.generate", || {
                Ok(write_dataset(&config, &out, &|| {}))
            })
        })?
        .map_err(|e| match e {
            WriteDatasetError::Exists(p) => PyFileExistsError::new_err(format!(
                "{}: already exists; choose another out or remove it",
                p.display()
            )),
            WriteDatasetError::Synth(SynthError::Config(m)) => PyValueError::new_err(m),
            e => err(e),
        })?;
    let d = PyDict::new(py);
    d.set_item("out", summary.out.to_string_lossy().into_owned())?;
    d.set_item("episodes", n)?;
    d.set_item("total_frames", summary.total_frames)?;
    d.set_item("episodes_per_split", summary.episodes_per_split)?;
    d.set_item("episodes_per_task", summary.episodes_per_task)?;
    d.set_item("contact_events", summary.contact_events)?;
    d.set_item("perturbed", summary.perturbed)?;
    d.set_item("perturbed_failed", summary.perturbed_failed)?;
    Ok(d)
}

fn missing(path: &Path, what: &str) -> PyErr {
    PyFileNotFoundError::new_err(format!("{}: no such {what}", path.display()))
}

/// Converts raw DROID (`format="droid"`), AgiBot World (`"agibot"`) or
/// Ctrl-World (`"ctrl-world"`) episodes under `src` into a LeRobot v3.0
/// training dataset at `out` with `calc` masks of `robot`, as `bridgev2w
/// convert` does (the same [`ConvertRequest`]), with the GIL released;
/// returns the report as a dict (`out`, `episodes`, `views_written`,
/// `skipped` as `(item, error)` pairs, `empty_mask_views`, `ee_frames`, and
/// `report_json`: the whole conversion report, notes included, as JSON text).
#[pyfunction]
#[pyo3(signature = (format, src, out, robot, joint_names, width, height, fps, intrinsics, calibration, missing_calibration, cameras, gripper_source, gripper_range, split, skip_bad, limit, camera_json = Vec::new(), include = None, split_rules = Vec::new()))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn convert<'py>(
    py: Python<'py>,
    format: &str,
    src: PathBuf,
    out: PathBuf,
    robot: &Robot,
    joint_names: Option<Vec<String>>,
    width: usize,
    height: usize,
    fps: Option<u32>,
    intrinsics: Option<PathBuf>,
    calibration: Vec<PathBuf>,
    missing_calibration: &str,
    cameras: Option<Vec<String>>,
    gripper_source: &str,
    gripper_range: (f64, f64),
    split: String,
    skip_bad: bool,
    limit: Option<usize>,
    camera_json: Vec<(String, PathBuf)>,
    include: Option<Vec<String>>,
    split_rules: Vec<String>,
) -> PyResult<Bound<'py, PyDict>> {
    fn value(field: &'static str) -> impl Fn(String) -> PyErr {
        move |e| PyValueError::new_err(format!("{field}: {e}"))
    }
    let request = ConvertRequest {
        joint_names,
        width,
        height,
        fps,
        intrinsics,
        calibration,
        missing_calibration: missing_calibration
            .parse()
            .map_err(value("missing_calibration"))?,
        cameras,
        camera_json,
        include,
        split_rules: split_rules
            .iter()
            .map(|r| r.parse::<SplitRule>())
            .collect::<Result<Vec<_>, _>>()
            .map_err(value("split_rules"))?,
        gripper_source: gripper_source.parse().map_err(value("gripper_source"))?,
        gripper_range,
        split,
        skip_bad,
        limit,
        ..ConvertRequest::new(format.parse().map_err(value("format"))?, src, out)
    };
    // Every option checked before the output is looked at.
    request.source().map_err(convert_err)?;
    check_new_output(&request.out)?;
    let embodiment = &robot.inner;
    let run = || request.run(embodiment, &|_| {});
    let report = py
        .detach(|| no_panic("convert", || Ok(run())))?
        .map_err(convert_err)?;
    let d = PyDict::new(py);
    d.set_item("out", request.out.to_string_lossy().into_owned())?;
    d.set_item("episodes", report.episodes)?;
    d.set_item("views_written", report.views_written)?;
    let skipped: Vec<(String, String)> = report
        .skipped
        .iter()
        .map(|s| (s.item.clone(), s.error.clone()))
        .collect();
    d.set_item("skipped", skipped)?;
    d.set_item("empty_mask_views", report.empty_mask_views.clone())?;
    d.set_item("ee_frames", report.ee_frames.clone())?;
    d.set_item(
        "report_json",
        serde_json::to_string(&report).map_err(|e| PyValueError::new_err(e.to_string()))?,
    )?;
    Ok(d)
}

/// A conversion error: a missing file or folder as `FileNotFoundError`, a
/// bad option as `ValueError`.
fn convert_err(e: ConvertError) -> PyErr {
    match e {
        ConvertError::Raw(RawError::Missing { path, what }) => {
            PyFileNotFoundError::new_err(format!("{}: missing {what}", path.display()))
        }
        ConvertError::Options(m) => PyValueError::new_err(m),
        e => err(e),
    }
}

/// One episode of a LeRobot v3.0/v2.1 dataset (what `synth` and `convert`
/// write, or `LeRobotDataset.create`), read with the GIL released: a dict of
/// `frames` (`T * H * W * 3` RGB8 bytes of video `key`, default the first),
/// `shape` (`(T, H, W)`), `states` and `actions` (`[T][n]`), `camera` (the
/// episode's calibration for `key`, or None), `masks` (`T * H * W` bytes of
/// `masks/episode_N.npy`, or None), `tasks`, `key` and `split`.
#[pyfunction]
#[pyo3(signature = (root, episode, key = None))]
pub(crate) fn read_episode<'py>(
    py: Python<'py>,
    root: PathBuf,
    episode: i64,
    key: Option<String>,
) -> PyResult<Bound<'py, PyDict>> {
    use bridgev2w_data::lerobot::{DatasetError, LeRobotDataset};
    if !root.join("meta/info.json").is_file() {
        return Err(missing(
            &root.join("meta/info.json"),
            "dataset (meta/info.json)",
        ));
    }
    // A failure to read, or a bad `key` (named in a ValueError).
    enum Failed {
        Read(DatasetError),
        Key(String),
    }
    let read_all = || {
        let ds = LeRobotDataset::open(&root).map_err(Failed::Read)?;
        let info = ds.episode(episode).map_err(Failed::Read)?.clone();
        let key = match key {
            Some(k) if ds.video_keys.contains(&k) => k,
            Some(k) => {
                return Err(Failed::Key(format!(
                    "{k:?}: no such video in {} (videos: {})",
                    root.display(),
                    ds.video_keys.join(", ")
                )))
            }
            None => ds.video_keys.first().cloned().ok_or_else(|| {
                Failed::Key(format!("{}: the dataset has no videos", root.display()))
            })?,
        };
        // The library checks what it reads against meta/info.json's features:
        // state and action widths, the frames' size and count, the masks'
        // [T, H, W]; a mismatch is an error naming the file and feature.
        let shape = ds.video_size(&key).map_err(Failed::Read)?;
        let rows = ds.read_episode(episode).map_err(Failed::Read)?;
        let frames = ds.read_video(episode, &key).map_err(Failed::Read)?;
        let camera = match ds.read_calibration(episode, &key) {
            Ok(c) => Some(c),
            Err(DatasetError::MissingCalibration { .. }) => None,
            Err(e) => return Err(Failed::Read(e)),
        };
        let masks = ds.stored_masks(episode).map_err(Failed::Read)?;
        Ok((
            rows, frames, shape, camera, masks, info.tasks, key, info.split,
        ))
    };
    let read = py.detach(|| no_panic("read_episode", || Ok(read_all())))?;
    let (rows, frames, (h, w), camera, masks, tasks, key, split) = read.map_err(|e| match e {
        Failed::Read(e) => err(e),
        Failed::Key(m) => PyValueError::new_err(format!("key: {m}")),
    })?;
    let t = frames.len();
    if let Some((shape, _)) = masks.as_ref().filter(|(s, _)| s[..] != [t, h, w]) {
        // Masks of another of the dataset's videos.
        return Err(err(format!(
            "{}: masks/episode_{episode:06}.npy has shape {shape:?}, not the [{t}, {h}, {w}] of video {key}",
            root.display()
        )));
    }
    let d = PyDict::new(py);
    d.set_item("frames", PyByteArray::new(py, &frames.concat()))?;
    d.set_item("shape", (t, h, w))?;
    let states: Vec<Vec<f32>> = rows.frames.iter().map(|r| r.state.clone()).collect();
    let actions: Vec<Vec<f32>> = rows.frames.iter().map(|r| r.action.clone()).collect();
    d.set_item("states", states)?;
    d.set_item("actions", actions)?;
    d.set_item(
        "camera",
        camera
            .map(|c| Camera { inner: (&c).into() })
            .map(|c| Bound::new(py, c))
            .transpose()?,
    )?;
    d.set_item("masks", masks.map(|(_, m)| PyByteArray::new(py, &m)))?;
    d.set_item("tasks", tasks)?;
    d.set_item("key", key)?;
    d.set_item("split", split)?;
    Ok(d)
}
