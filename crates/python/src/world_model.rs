//! The world model's Python class (`bridgev2w.WorldModel`): a model folder,
//! a diffusers folder or `random:PRESET` loaded once, predictions from
//! numpy arrays (or from files, as `bridgev2w predict` writes them).

use crate::{err, no_panic, size_err, Error};
use bridgev2w_io::frame::{u8_from_unit, RgbFrame};
use bridgev2w_world_model::bridge::{BridgeV2W, BridgeV2WConfig};
use bridgev2w_world_model::pipeline::{BatchNoise, PredictOptions, SampleOptions, WorldModel as _};
use bridgev2w_world_model::spec::ModelSpec;
use bridgev2w_world_model::vae::VaeTiling;
use bridgev2w_world_model::video::MaskVideo;
use bridgev2w_world_model::{ComputeDevice, Precision, WorldModelError};
use pyo3::exceptions::{PyFileNotFoundError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyByteArray;
use std::path::PathBuf;

/// `(out, clips [(name or None, mask file)], frames, seconds)` of
/// `WorldModel.predict_files`.
type PredictFilesRun = (String, Vec<(Option<String>, String)>, usize, f64);

/// The action-conditioned world model: a first frame and the masks of the
/// actions in, the predicted video out.
#[pyclass(module = "bridgev2w._core", frozen)]
pub(crate) struct WorldModel {
    // tch tensors are Send, not Sync: one prediction at a time per model
    // (a second Python thread waits, with the GIL released).
    inner: std::sync::Mutex<BridgeV2W>,
    resolution: (usize, usize),
    clip_frames: usize,
    source: String,
}

#[pymethods]
impl WorldModel {
    /// A model folder as `bridgev2w demo` ships it (`backbone/` and
    /// `bridgev2w.safetensors`), a diffusers CogVideoX-I2V folder or Hub name
    /// (with optional BridgeV2W `weights`), or `random:PRESET`. `vae_tile`:
    /// `auto` (the VAE's tiles above 256x256, as `bridgev2w predict`), `off`
    /// or `HxW` pixels.
    #[staticmethod]
    #[pyo3(signature = (model, weights = None, device = "cpu", precision = "f32", seed = 0, vae_tile = "auto"))]
    fn from_pretrained(
        py: Python<'_>,
        model: &str,
        weights: Option<PathBuf>,
        device: &str,
        precision: &str,
        seed: i64,
        vae_tile: &str,
    ) -> PyResult<Self> {
        let tiling: VaeTiling =
            vae_tile
                .parse()
                .map_err(|e: bridgev2w_world_model::WorldModelError| {
                    PyValueError::new_err(e.to_string())
                })?;
        let device: ComputeDevice =
            device
                .parse()
                .map_err(|e: bridgev2w_world_model::WorldModelError| {
                    PyValueError::new_err(format!("device: {e}"))
                })?;
        let precision: Precision =
            precision
                .parse()
                .map_err(|e: bridgev2w_world_model::WorldModelError| {
                    PyValueError::new_err(format!("precision: {e}"))
                })?;
        let dir = PathBuf::from(model);
        let shipped = (dir.join("backbone"), dir.join("bridgev2w.safetensors"));
        let source = model.to_string();
        let inner = py.detach(|| {
            if shipped.0.is_dir() && shipped.1.is_file() && weights.is_none() {
                BridgeV2W::load(
                    &shipped.0,
                    Some(&shipped.1),
                    None,
                    BridgeV2WConfig::paper(),
                    device,
                    precision,
                )
            } else {
                model.parse::<ModelSpec>().and_then(|spec| {
                    spec.load_bridge(weights.as_deref(), None, device, precision, seed)
                })
            }
        });
        // A local path that is not there (not a Hub name OWNER/NAME, not random:).
        let hub_name = model.split('/').count() == 2 && !model.starts_with(['.', '/']);
        let mut inner = inner.map_err(|e| {
            if !model.starts_with("random:") && !dir.exists() && !hub_name {
                PyFileNotFoundError::new_err(e.to_string())
            } else {
                err(e)
            }
        })?;
        let resolution = inner.resolution();
        inner
            .vae
            .set_tiling(tiling, resolution, "vae_tile")
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        Ok(Self {
            resolution: inner.resolution(),
            clip_frames: inner.clip_frames(),
            inner: std::sync::Mutex::new(inner),
            source,
        })
    }

    /// `(height, width)` the model works at.
    #[getter]
    fn resolution(&self) -> (usize, usize) {
        self.resolution
    }

    /// Frames per predicted clip (the number of masks it takes).
    #[getter]
    fn clip_frames(&self) -> usize {
        self.clip_frames
    }

    /// The predicted videos (`B * T * H * W * 3` RGB8 bytes) of a batch of
    /// `batch` first frames (`B * H * W * 3` RGB8 bytes) and mask sequences
    /// (`B * T * H * W` bytes, non-zero = robot), with `steps` denoising
    /// steps from noise seed `seed`, in one batch through the model
    /// (`predict_batch`). Every item gets the noise a batch of one with the
    /// same seed gets (`BatchNoise::Shared`, as `bridgev2w predict` with
    /// several clips): its single prediction. The GIL is released while the
    /// model runs.
    #[pyo3(signature = (first_frames, masks, batch = 1, steps = 20, seed = 0, guidance = 1.0))]
    #[allow(clippy::too_many_arguments)]
    fn predict<'py>(
        &self,
        py: Python<'py>,
        first_frames: &[u8],
        masks: &[u8],
        batch: usize,
        steps: usize,
        seed: u64,
        guidance: f64,
    ) -> PyResult<Bound<'py, PyByteArray>> {
        let (h, w) = self.resolution;
        let t = self.clip_frames;
        if batch == 0 {
            return Err(PyValueError::new_err(
                "first_frame: an empty batch (expected at least one frame)",
            ));
        }
        bridgev2w_world_model::bridge::check_predict_batch("batch", batch)
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        // Within MAX_PREDICT_BATCH clips of a model's bounded clip: no overflow.
        if first_frames.len() != batch * h * w * 3 {
            return Err(PyValueError::new_err(format!(
                "first_frame: {} values, expected [{batch}, {h}, {w}, 3] for this model",
                first_frames.len()
            )));
        }
        if masks.len() != batch * t * h * w {
            return Err(PyValueError::new_err(format!(
                "masks: {} values, expected [{batch}, {t}, {h}, {w}] for this model",
                masks.len()
            )));
        }
        if steps == 0 {
            return Err(PyValueError::new_err("steps: expected at least 1"));
        }
        if !guidance.is_finite() {
            return Err(PyValueError::new_err(format!(
                "guidance: {guidance}, expected a finite number (1 = no guidance)"
            )));
        }
        let images = first_frames
            .chunks_exact(h * w * 3)
            .map(|f| RgbFrame::from_rgb8(w, h, f))
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| PyValueError::new_err(format!("first_frame: {e}")))?;
        let mask_videos: Vec<MaskVideo> = masks
            .chunks_exact(t * h * w)
            .map(|m| MaskVideo {
                frames: t,
                height: h,
                width: w,
                data: m.to_vec(),
            })
            .collect();
        let opts = PredictOptions {
            sample: SampleOptions {
                steps,
                guidance_scale: guidance,
                dynamic_cfg: false,
                seed,
                first_frame: Default::default(),
                // Each item the noise of a batch of one: its single prediction.
                batch_noise: BatchNoise::Shared,
                ..SampleOptions::default()
            },
            max_batch: None,
            ..PredictOptions::default()
        };
        let model = &self.inner;
        let videos = py.detach(|| {
            no_panic("predict", || {
                let m = model
                    .lock()
                    .map_err(|_| Error::new_err("an earlier prediction failed mid-way"))?;
                m.predict_batch(&images, &mask_videos, &opts)
                    .map_err(|e| match e {
                        // A batch beyond the machine's memory, refused before it ran.
                        WorldModelError::Memory(e) => size_err(e),
                        // An argument the model refuses (e.g. steps beyond the
                        // scheduler's training timesteps).
                        e @ WorldModelError::Input { .. } => PyValueError::new_err(e.to_string()),
                        e => err(e),
                    })
            })
        })?;
        let bytes: Vec<u8> = videos
            .iter()
            .flat_map(|v| v.data.iter().map(|&x| u8_from_unit(x)))
            .collect();
        Ok(PyByteArray::new(py, &bytes))
    }

    /// `bridgev2w predict` from files: the first frame `image`, mask files
    /// (or folders of them) `masks`, outputs written to `out` by the
    /// library's `PredictJob` (the CLI's call). Returns `(out, clips,
    /// frames, seconds)`; `clips` the `(name or None, mask file)` pairs. The
    /// GIL is released while the model runs.
    #[pyo3(signature = (image, masks, out, steps, seed, guidance, batch_size, overwrite))]
    #[allow(clippy::too_many_arguments)]
    fn predict_files(
        &self,
        py: Python<'_>,
        image: PathBuf,
        masks: Vec<PathBuf>,
        out: PathBuf,
        steps: usize,
        seed: u64,
        guidance: f64,
        batch_size: usize,
        overwrite: bool,
    ) -> PyResult<PredictFilesRun> {
        use bridgev2w_train::predict_files::{PredictFilesError, PredictJob};
        for p in masks.iter().chain([&image]) {
            if !p.exists() {
                return Err(PyFileNotFoundError::new_err(format!(
                    "{}: no such file",
                    p.display()
                )));
            }
        }
        let job = PredictJob {
            image,
            masks,
            out,
            overwrite,
            batch_size,
            sample: SampleOptions {
                steps,
                guidance_scale: guidance,
                seed,
                batch_noise: BatchNoise::Shared,
                ..SampleOptions::default()
            },
            other_inputs: Vec::new(),
        };
        let value_err = |e: PredictFilesError| match e {
            e @ PredictFilesError::Input { .. } => PyValueError::new_err(e.to_string()),
            PredictFilesError::Model(e @ WorldModelError::Input { .. }) => {
                PyValueError::new_err(e.to_string())
            }
            e => err(e),
        };
        let job = job.prepare().map_err(value_err)?;
        let model = &self.inner;
        let run = py.detach(|| {
            no_panic("predict_files", || {
                let m = model
                    .lock()
                    .map_err(|_| Error::new_err("an earlier prediction failed mid-way"))?;
                job.run(&m, &bridgev2w_io::progress::Silent)
                    .map_err(value_err)
            })
        })?;
        let clips = run
            .clips
            .iter()
            .map(|c| (c.name.clone(), c.masks.to_string_lossy().into_owned()))
            .collect();
        Ok((
            run.out.to_string_lossy().into_owned(),
            clips,
            run.frames,
            run.seconds,
        ))
    }

    fn __repr__(&self) -> String {
        let (h, w) = self.resolution;
        format!(
            "WorldModel({:?}, {} frames at {h}x{w})",
            self.source, self.clip_frames
        )
    }
}
