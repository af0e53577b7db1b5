//! The VAE's arm of the parity fixtures (`kind: "vae"`).

use super::FixtureIo;
use crate::device::{ComputeDevice, Precision};
use crate::error::{Result, WorldModelError};
use crate::vae::{AutoencoderKLCogVideoX, TilingOptions};
use std::path::{Path, PathBuf};
use tch::Tensor;

/// Options of a VAE parity fixture (`meta.json` `options`).
#[derive(Debug, serde::Deserialize)]
struct FixtureOptions {
    #[serde(default)]
    tiling: Option<FixtureTiling>,
    #[serde(default)]
    slicing: bool,
    #[serde(default)]
    sample_seed: Option<u64>,
}

#[derive(Debug, serde::Deserialize)]
struct FixtureTiling {
    tile_sample_min_height: i64,
    tile_sample_min_width: i64,
    tile_overlap_factor_height: f64,
    tile_overlap_factor_width: f64,
}

/// The `"vae"` arm of [`run_fixture`](super::run_fixture): loads `model_dir`, applies the
/// fixture's tiling/slicing and computes `latent_mean` (and `latent_sample`) from
/// `video`, `decoded` from `latents`, with the weights in `precision` (the
/// inputs are cast to it).
pub(super) fn fixture_outputs(
    model_dir: &Path,
    meta: &serde_json::Value,
    meta_path: &Path,
    io: &FixtureIo,
    precision: Precision,
) -> Result<Vec<(String, Tensor)>> {
    let options: FixtureOptions = match meta.get("options") {
        Some(o) => serde_json::from_value(o.clone()).map_err(|error| WorldModelError::Json {
            path: PathBuf::from(meta_path),
            error,
        })?,
        None => FixtureOptions {
            tiling: None,
            slicing: false,
            sample_seed: None,
        },
    };
    let mut vae = AutoencoderKLCogVideoX::load(model_dir, ComputeDevice::Cpu, precision)?;
    if let Some(t) = &options.tiling {
        vae.enable_tiling(TilingOptions {
            tile_sample_min_height: Some(t.tile_sample_min_height),
            tile_sample_min_width: Some(t.tile_sample_min_width),
            tile_overlap_factor_height: Some(t.tile_overlap_factor_height),
            tile_overlap_factor_width: Some(t.tile_overlap_factor_width),
        })?;
    }
    if options.slicing {
        vae.enable_slicing();
    }
    let mut out = Vec::new();
    if io.contains("video") {
        let posterior = vae.encode(io.get("video")?)?;
        if io.contains("latent_sample") {
            if let Some(seed) = options.sample_seed {
                out.push(("latent_sample".to_owned(), posterior.sample(seed)?));
            }
        }
        out.push(("latent_mean".to_owned(), posterior.mode()));
    }
    if io.contains("latents") {
        out.push(("decoded".to_owned(), vae.decode(io.get("latents")?)?));
    }
    Ok(out)
}
