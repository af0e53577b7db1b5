//! Numerical parity with diffusers on fixtures written by
//! `scripts/parity/make_parity_fixture.py`.
//!
//! A fixture directory holds `meta.json` (`{"kind": "transformer" | "vae" |
//! "scheduler", ...}`), `model/` (diffusers `save_pretrained` output, or
//! `scheduler_config.json` for schedulers) and `io.safetensors` (inputs and the
//! expected outputs). The Rust implementation loads `model/`, computes every output
//! from the inputs, and each is compared with diffusers' value:
//! `max_abs = max |rust - diffusers|`, `max_rel = max_abs / max |diffusers|`
//! (the error relative to the output's scale, robust to elements near zero).
//!
//! Fixtures made with `--bf16` (transformer and VAE) also hold diffusers'
//! outputs in bfloat16 (`NAME_bf16`): [`run_fixture_bf16`] runs the Rust model in
//! bf16 and compares both bf16 errors against diffusers' f32 output (the bound:
//! [`Bf16Output::within`]).

mod bf16;
mod i3d;
mod lpips;
mod raft;
mod scheduler;
mod table;
mod transformer;
mod vae;

pub use bf16::{run_fixture_bf16, Bf16Error, Bf16Output, Bf16Report, BF16_EPSILON, BF16_FACTOR};
pub use table::{parity_table, parity_table_bf16, ParityTable};

use crate::device::Precision;
use crate::error::{Result, WorldModelError};
use crate::weights::read_safetensors;
use bridgev2w_io::json::read_json;
use std::collections::HashMap;
use std::path::Path;
use tch::Tensor;

/// The relative error above which `bridgev2w parity` fails (f32).
pub const DEFAULT_TOLERANCE: f64 = 1e-4;

/// One compared output.
#[derive(Debug, Clone)]
pub struct ParityOutput {
    /// Output name in `io.safetensors`.
    pub name: String,
    /// Its shape.
    pub shape: Vec<i64>,
    /// Largest absolute difference.
    pub max_abs: f64,
    /// `max_abs` divided by the largest magnitude of the expected output.
    pub max_rel: f64,
}

/// The result of running one fixture.
#[derive(Debug, Clone)]
pub struct ParityReport {
    /// The fixture's kind.
    pub kind: String,
    /// Every output compared.
    pub outputs: Vec<ParityOutput>,
}

impl ParityReport {
    /// The largest relative error over all outputs.
    pub fn worst_rel(&self) -> f64 {
        self.outputs.iter().map(|o| o.max_rel).fold(0.0, f64::max)
    }
}

/// The inputs and expected outputs of a fixture.
#[derive(Debug)]
pub struct FixtureIo {
    tensors: HashMap<String, Tensor>,
    path: std::path::PathBuf,
}

impl FixtureIo {
    /// Reads `io.safetensors`.
    pub fn read(path: &Path) -> Result<Self> {
        Ok(Self {
            tensors: read_safetensors(path)?.into_iter().collect(),
            path: path.to_path_buf(),
        })
    }

    /// A tensor by name, or an error naming the file and the key.
    pub fn get(&self, name: &str) -> Result<&Tensor> {
        self.tensors.get(name).ok_or_else(|| {
            WorldModelError::input(name, format!("not found in {}", self.path.display()))
        })
    }

    /// Whether a tensor exists.
    pub fn contains(&self, name: &str) -> bool {
        self.tensors.contains_key(name)
    }
}

/// Compares computed outputs with the expected tensors of the same names.
pub fn compare(io: &FixtureIo, computed: &[(String, Tensor)]) -> Result<Vec<ParityOutput>> {
    computed
        .iter()
        .map(|(name, got)| {
            let want = io.get(name)?;
            if got.size() != want.size() {
                return Err(WorldModelError::input(
                    name.as_str(),
                    format!(
                        "shape {:?} computed, diffusers gave {:?}",
                        got.size(),
                        want.size()
                    ),
                ));
            }
            let got = got.to_device(tch::Device::Cpu).to_kind(tch::Kind::Double);
            let want = want.to_kind(tch::Kind::Double);
            let max_abs = if want.numel() == 0 {
                0.0
            } else {
                (&got - &want).abs().max().double_value(&[])
            };
            let scale = if want.numel() == 0 {
                0.0
            } else {
                want.abs().max().double_value(&[])
            };
            let max_rel = if scale > 0.0 {
                max_abs / scale
            } else {
                max_abs
            };
            Ok(ParityOutput {
                name: name.clone(),
                shape: want.size(),
                max_abs,
                max_rel,
            })
        })
        .collect()
}

/// Runs one fixture directory with the Rust implementation.
pub fn run_fixture(dir: &Path) -> Result<ParityReport> {
    let c = fixture_computed(dir, Precision::F32)?;
    let outputs = compare(&c.io, &c.outputs)?;
    Ok(ParityReport {
        kind: c.kind,
        outputs,
    })
}

/// A fixture read and its outputs computed here.
struct Computed {
    /// The fixture's kind.
    kind: String,
    /// Its inputs and diffusers' outputs.
    io: FixtureIo,
    /// The outputs computed here, by name.
    outputs: Vec<(String, Tensor)>,
}

/// Reads a fixture and computes its outputs in `precision`.
fn fixture_computed(dir: &Path, precision: Precision) -> Result<Computed> {
    let meta_path = dir.join("meta.json");
    let meta: serde_json::Value = read_json(&meta_path)?;
    let kind = meta
        .get("kind")
        .and_then(|k| k.as_str())
        .ok_or_else(|| WorldModelError::config(&meta_path, "kind", "missing or not a string"))?
        .to_owned();
    if precision != Precision::F32 && kind != "transformer" && kind != "vae" {
        return Err(WorldModelError::config(
            &meta_path,
            "kind",
            format!("`{kind}`: only transformer and vae fixtures run in {precision:?}"),
        ));
    }
    let io = FixtureIo::read(&dir.join("io.safetensors"))?;
    let model_dir = dir.join("model");
    let computed = tch::no_grad(|| -> Result<Vec<(String, Tensor)>> {
        // One arm per kind: each submodule computes its outputs from `model_dir` and `io`.
        match kind.as_str() {
            "scheduler" => scheduler::fixture_outputs(&model_dir, &io),
            "lpips" => lpips::fixture_outputs(&model_dir, &io),
            "raft" => raft::fixture_outputs(&model_dir, &meta, &io),
            "i3d" => i3d::fixture_outputs(&model_dir, &io),
            "transformer" => transformer::fixture_outputs(&model_dir, &io, precision),
            "vae" => vae::fixture_outputs(&model_dir, &meta, &meta_path, &io, precision),
            other => Err(WorldModelError::config(
                &meta_path,
                "kind",
                format!("`{other}`: expected transformer, vae, scheduler, lpips, raft or i3d"),
            )),
        }
    })?;
    Ok(Computed {
        kind,
        io,
        outputs: computed,
    })
}
