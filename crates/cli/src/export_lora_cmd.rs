//! `bridgev2w export-lora`: the backbone's LoRA of a BridgeV2W weights file in
//! diffusers' `pytorch_lora_weights.safetensors` layout.

use anyhow::Result;
use bridgev2w_world_model::lora_export::export_lora_file;
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct ExportLoraArgs {
    /// The backbone: a CogVideoX image-to-video diffusers folder (only its
    /// transformer config is read, to check the adapters' layers and shapes).
    #[arg(long)]
    model: PathBuf,
    /// BridgeV2W weights (ControlNet + LoRA safetensors written by `bridgev2w train`).
    #[arg(long)]
    weights: PathBuf,
    /// Output folder: OUT/pytorch_lora_weights.safetensors, for diffusers'
    /// `CogVideoXImageToVideoPipeline.load_lora_weights(OUT)` (the ControlNet
    /// branch has no diffusers counterpart and is left out).
    #[arg(long)]
    out: PathBuf,
    /// Replace an existing OUT/pytorch_lora_weights.safetensors.
    #[arg(long)]
    overwrite: bool,
}

pub fn run(a: &ExportLoraArgs) -> Result<()> {
    let e = export_lora_file(&a.weights, &a.model, &a.out, a.overwrite)?;
    crate::print_stdout(&format!(
        "wrote {} ({} LoRA layers, rank {}, alpha {} folded into lora_B as alpha/rank = {})\n",
        e.path.display(),
        e.layers,
        e.rank,
        e.alpha,
        e.alpha / e.rank as f64
    ))
}
