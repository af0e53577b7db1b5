//! The world model of BridgeV2W: a CogVideoX-architecture image-to-video diffusion
//! transformer with a 3D causal VAE, conditioned on embodiment-mask videos through a
//! ControlNet branch and fine-tuned with LoRA. Numerically compatible with diffusers
//! (`AutoencoderKLCogVideoX`, `CogVideoXTransformer3DModel`, the CogVideoX DDIM/DPM
//! schedulers) and loading their checkpoints unchanged.
//!
//! The tensor engine is libtorch through `tch`; the public entry points take and
//! return this crate's own types.

pub mod bench;
pub mod bridge;
pub mod checkpoint;
pub mod conditioning;
pub mod controlnet;
pub mod cpu_attention;
pub mod cpu_bf16;
pub mod cpu_linear;
pub mod device;
pub mod error;
pub mod hub;
pub mod lora;
pub mod lora_export;
pub mod mask_coding;
pub mod named;
pub mod nets;
pub mod parity;
pub mod pipeline;
pub mod process_mode;
pub mod scheduler;
pub mod spec;
pub mod static_scene;
pub mod transformer;
pub mod vae;
pub mod video;
pub mod weights;

pub use device::{ComputeDevice, DeviceSpec, Precision};
pub use error::{Result, WorldModelError};
