//! The diffusers side of `bench model`: `scripts/bench/diffusers_model.py`
//! (in the project venv, with torch and diffusers) times the same operations
//! as [`super::time_model`] on the same configs, shapes, threads and precision.

use super::{torch_threads, BenchError, ModelBenchShape, ModelTimings};
use crate::device::{ComputeDevice, Precision};
use crate::transformer::TransformerConfig;
use crate::vae::VaeConfig;
use bridgev2w_io::json::write_json_atomic;
use bridgev2w_io::peer::{self, PeerError};
use std::path::{Path, PathBuf};
use std::process::Command;

/// The peer script, under `scripts/bench/`.
const SCRIPT: &str = "diffusers_model.py";

/// Where diffusers runs from: a Python with torch and diffusers, and the
/// repository root that holds the peer script.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DiffusersPeer {
    /// The interpreter.
    pub python: PathBuf,
    /// The repository root.
    pub repo: PathBuf,
}

impl DiffusersPeer {
    /// The repository root (`repo`, else found above the current directory)
    /// and `python`, else the project venv's.
    pub fn find(python: Option<&Path>, repo: Option<&Path>) -> Result<Self, PeerError> {
        let repo = peer::find_repo(repo)?;
        let python = match python {
            Some(p) => p.to_path_buf(),
            None => peer::project_python(&repo, " (or pass --python / --no-diffusers)")?,
        };
        Ok(Self { python, repo })
    }

    /// Times diffusers' transformer forward and VAE encode/decode (best of
    /// `repeat` after a warm-up, like [`super::time_model`]).
    pub fn time_model(
        &self,
        tf: &TransformerConfig,
        vae: &VaeConfig,
        shape: &ModelBenchShape,
        device: ComputeDevice,
        precision: Precision,
        repeat: usize,
    ) -> Result<ModelTimings, BenchError> {
        let tmp = peer::scratch_dir()?;
        let (tf_path, vae_path) = (
            tmp.path().join("transformer.json"),
            tmp.path().join("vae.json"),
        );
        write_json_atomic(&tf_path, tf)?;
        write_json_atomic(&vae_path, vae)?;
        let dtype = match precision {
            Precision::F32 => "f32",
            Precision::Bf16 => "bf16",
        };
        let result = peer::run_peer_json(
            Command::new(&self.python)
                .arg(self.repo.join("scripts/bench").join(SCRIPT))
                .arg("--transformer-config")
                .arg(&tf_path)
                .arg("--vae-config")
                .arg(&vae_path)
                .args(["--frames", &shape.frames.to_string()])
                .args(["--height", &shape.height.to_string()])
                .args(["--width", &shape.width.to_string()])
                .args(["--text-len", &shape.text_len.to_string()])
                .args(["--repeat", &repeat.to_string()])
                .args(["--batch", &shape.batch.to_string()])
                .args(["--threads", &torch_threads().to_string()])
                .args(["--dtype", dtype, "--device", &device.to_string()])
                .args(shape.vae_tiling.then_some("--vae-tiling")),
            SCRIPT,
        )?;
        Ok(ModelTimings {
            transformer_forward_s: result.number("transformer_forward_s")?,
            vae_encode_s: result.number("vae_encode_s")?,
            vae_decode_s: result.number("vae_decode_s")?,
        })
    }
}
