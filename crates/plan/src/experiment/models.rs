//! The world model of an experiment: named by [`ModelOptions`], loaded once
//! into a [`LoadedModel`], and wrapped per task instance (its camera, scene
//! and start pose) as an [`ActionWorldModel`].

use crate::choice::PlanModel;
use crate::goal_latent::GoalLatent;
use crate::model::{ActionWorldModel, MaskConditioned};
use crate::synthetic::{PerfectWorldModel, TaskInstance};
use crate::{PlanError, Result};
use bridgev2w_data::synth::{SynthConfig, World};
use bridgev2w_world_model::bridge::BridgeV2W;
use bridgev2w_world_model::pipeline::{
    BatchNoise, DecodeFrames, PredictOptions, SampleOptions, WorldModel as _,
};
use bridgev2w_world_model::vae::VaeTiling;
use bridgev2w_world_model::{ComputeDevice, Precision};
use std::path::PathBuf;

/// How a diffusion model samples and where goal distances are measured
/// (flags of the planning commands and of `plan-report`).
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct Sampling {
    /// Denoising steps of a diffusion model.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = Sampling::default().denoise_steps))]
    pub denoise_steps: usize,
    /// How a diffusion model draws the noise of a batch of candidates:
    /// `shared` (common random numbers: candidates differ by their actions
    /// alone) or `independent`.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = Sampling::default().batch_noise))]
    pub batch_noise: BatchNoise,
    /// Where a diffusion model's sampling starts, in (0, 1]: 1 from pure
    /// noise; s < 1 from the first frame's latent in every frame, noised to
    /// the level a fraction s from the end (only the last ceil(s * steps)
    /// denoising steps run; `SampleOptions::strength`).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = Sampling::default().strength))]
    pub strength: f64,
    /// Keep the static scene of a diffusion model's predictions (beyond the
    /// paper): outside the region the candidate's masks have swept so far,
    /// dilated by this many pixels, each frame is the first frame. Off when
    /// not given.
    #[cfg_attr(feature = "clap", arg(long = "keep-static", value_name = "MARGIN_PX"))]
    pub keep_static_margin_px: Option<u32>,
    /// Where goal distances are measured: `model` (a diffusion model's VAE
    /// latent, the paper) or `pyramid` (a Gaussian pyramid of the image, the
    /// perfect model's latent: it keeps growing with the arm's displacement
    /// where a fine latent is flat; beyond the paper).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = Sampling::default().goal_latent))]
    pub goal_latent: GoalLatent,
}

impl Default for Sampling {
    fn default() -> Self {
        Self {
            denoise_steps: 4,
            batch_noise: BatchNoise::Shared,
            strength: 1.0,
            keep_static_margin_px: None,
            goal_latent: GoalLatent::Model,
        }
    }
}

/// Which world model to plan or evaluate with, and how a diffusion model
/// samples (flags of the planning commands).
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct ModelOptions {
    /// `perfect` (the synthetic world's own renderer), `random` (BridgeV2W
    /// with random tiny weights at 64x96, 9 frames: a smoke test), or a
    /// CogVideoX image-to-video diffusers folder (with --weights).
    #[cfg_attr(feature = "clap", arg(long, default_value = "perfect"))]
    pub model: PlanModel,
    /// BridgeV2W weights (ControlNet + LoRA safetensors) for a model folder.
    #[cfg_attr(feature = "clap", arg(long))]
    pub weights: Option<PathBuf>,
    /// The fixed prompt's T5 embedding for a model folder.
    #[cfg_attr(feature = "clap", arg(long))]
    pub prompt_embeds: Option<PathBuf>,
    /// How a diffusion model samples and where goal distances are measured.
    #[cfg_attr(feature = "clap", command(flatten))]
    pub sampling: Sampling,
    /// cpu, cuda, cuda:N or auto.
    #[cfg_attr(feature = "clap", arg(long, default_value = "auto"))]
    pub device: ComputeDevice,
    /// Precision of a diffusion model: f32 or bf16 (bf16 halves the memory
    /// of a GPU run).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = ModelOptions::default().precision))]
    pub precision: Precision,
    /// At most this many candidates through a diffusion model at once (all
    /// of a CEM iteration's by default): a smaller batch bounds the device
    /// memory; with shared batch noise the plan is the same.
    #[cfg_attr(feature = "clap", arg(long, value_name = "N"))]
    pub max_batch: Option<usize>,
    /// Image width of the synthetic world with the perfect model (pixels, even).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = ModelOptions::default().width))]
    pub width: u32,
    /// Image height of the synthetic world with the perfect model (pixels, even).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = ModelOptions::default().height))]
    pub height: u32,
    /// Frames of each predicted clip (default: the model's own, 9 for the
    /// perfect model, a diffusion model's training clip). A planned action
    /// needs one more than its frames; a shorter clip is cheaper (beyond
    /// the paper).
    #[cfg_attr(feature = "clap", arg(long, value_name = "N"))]
    pub clip_frames: Option<usize>,
    /// Which frames of a diffusion model's predictions are decoded: `all`,
    /// or `last` (only the VAE decoder's last batch of latent frames: the
    /// planner scores the clip's last frame; without the earlier frames'
    /// conv cache, an approximation; beyond the paper).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = ModelOptions::default().decode_frames))]
    pub decode_frames: DecodeFrames,
    /// The synthetic world's robot (a built-in robot: `bridgev2w robot-info
    /// --list`): the one a trained model's data had (`synth --robot`;
    /// `franka-robotiq` for data made with `--engine mujoco` by the
    /// reproduction script). MuJoCo loads its URDF.
    #[cfg_attr(feature = "clap", arg(long, default_value = "franka"))]
    pub robot: String,
}

/// The perfect model's clip frames unless [`ModelOptions::clip_frames`] says
/// otherwise.
pub const PERFECT_CLIP_FRAMES: usize = 9;

impl Default for ModelOptions {
    fn default() -> Self {
        Self {
            model: PlanModel::Perfect,
            weights: None,
            prompt_embeds: None,
            sampling: Sampling::default(),
            device: ComputeDevice::auto(),
            precision: Precision::F32,
            max_batch: None,
            width: 96,
            height: 64,
            clip_frames: None,
            decode_frames: DecodeFrames::All,
            robot: "franka".into(),
        }
    }
}

impl ModelOptions {
    /// Refuses `weights` or `prompt_embeds` with a model that would ignore
    /// them: the perfect renderer (no weights, no prompt), or a `random:`
    /// model ([`bridgev2w_world_model::spec::ModelSpec::check_inputs`]).
    pub fn check_inputs(&self) -> Result<()> {
        match &self.model {
            PlanModel::Perfect => {
                let given = [
                    ("--weights", &self.weights),
                    ("--prompt-embeds", &self.prompt_embeds),
                ];
                if let Some((flag, Some(path))) = given.into_iter().find(|(_, p)| p.is_some()) {
                    return Err(PlanError::input(
                        flag,
                        format!(
                            "{} given with --model perfect: the synthetic renderer has no weights and no prompt and would ignore it (expected a diffusers model folder as --model, or no {flag})",
                            path.display()
                        ),
                    ));
                }
            }
            PlanModel::World(spec) => {
                spec.check_inputs(self.weights.as_deref(), self.prompt_embeds.as_deref())?
            }
        }
        Ok(())
    }
}

/// A loaded world model.
#[derive(Debug)]
pub enum LoadedModel {
    /// The synthetic world's renderer.
    Perfect {
        /// Rendered width (pixels).
        width: u32,
        /// Rendered height (pixels).
        height: u32,
        /// Clip frames.
        clip_frames: usize,
        /// The synthetic world's robot.
        robot: String,
    },
    /// A BridgeV2W diffusion model.
    Diffusion {
        /// The model.
        model: Box<BridgeV2W>,
        /// How it samples and where goal distances are measured.
        sampling: Sampling,
        /// At most this many candidates per model call.
        max_batch: Option<usize>,
        /// Which frames are decoded.
        decode_frames: DecodeFrames,
        /// The synthetic world's robot (the one the model's data had).
        robot: String,
    },
}

impl LoadedModel {
    /// Frames per predicted clip (a chunk of actions is one fewer).
    pub fn clip_frames(&self) -> usize {
        match self {
            Self::Perfect { clip_frames, .. } => *clip_frames,
            Self::Diffusion { model, .. } => {
                bridgev2w_world_model::pipeline::WorldModel::clip_frames(model.as_ref())
            }
        }
    }

    /// Loads the model `o` names.
    pub fn load(o: &ModelOptions) -> Result<Self> {
        o.check_inputs()?;
        Ok(match &o.model {
            PlanModel::Perfect => Self::Perfect {
                width: o.width,
                height: o.height,
                clip_frames: o.clip_frames.unwrap_or(PERFECT_CLIP_FRAMES),
                robot: o.robot.clone(),
            },
            PlanModel::World(spec) => {
                let mut model = spec.load_bridge(
                    o.weights.as_deref(),
                    o.prompt_embeds.as_deref(),
                    o.device,
                    o.precision,
                    0,
                )?;
                if let Some(frames) = o.clip_frames {
                    model.set_clip_frames(frames)?;
                }
                // The VAE as `predict` runs it: in its tiles above 256x256.
                let resolution = model.resolution();
                model
                    .vae
                    .set_tiling(VaeTiling::Auto, resolution, "the VAE's tiles")?;
                Self::Diffusion {
                    model: Box::new(model),
                    sampling: o.sampling,
                    max_batch: o.max_batch,
                    decode_frames: o.decode_frames,
                    robot: o.robot.clone(),
                }
            }
        })
    }

    /// Whether this is a diffusion model (not the perfect renderer).
    pub fn is_diffusion(&self) -> bool {
        matches!(self, Self::Diffusion { .. })
    }

    /// How this model sees the scene: a diffusion model the executing
    /// world's frames (in MuJoCo: a model trained on `synth --engine
    /// mujoco`); the perfect model, the built-in world stepped
    /// kinematically, the built-in renderer's drawing of the same states.
    pub fn look(&self) -> crate::synthetic::GoalLook {
        match self.is_diffusion() {
            true => crate::synthetic::GoalLook::Executed,
            false => crate::synthetic::GoalLook::Builtin,
        }
    }

    /// `(height, width)` the synthetic world must render at.
    pub fn resolution(&self) -> (u32, u32) {
        match self {
            Self::Perfect { width, height, .. } => (*height, *width),
            Self::Diffusion { model, .. } => {
                (model.config().height as u32, model.config().width as u32)
            }
        }
    }

    /// The synthetic world at this model's resolution, with its robot.
    pub fn world(&self, episode_frames: usize, seed: u64) -> Result<World> {
        let (h, w) = self.resolution();
        let robot = match self {
            Self::Perfect { robot, .. } | Self::Diffusion { robot, .. } => robot.clone(),
        };
        Ok(World::new(&SynthConfig {
            frames: episode_frames,
            width: w,
            height: h,
            seed,
            robot,
            ..SynthConfig::default()
        })?)
    }

    /// Runs `f` with the world model of task instance `inst`.
    pub fn with_model<T>(
        &self,
        world: &World,
        inst: &TaskInstance,
        f: &mut dyn FnMut(&dyn ActionWorldModel) -> Result<T>,
    ) -> Result<T> {
        match self {
            Self::Perfect { clip_frames, .. } => f(&PerfectWorldModel {
                world,
                instance: inst.clone(),
                clip_frames: *clip_frames,
            }),
            Self::Diffusion {
                model,
                sampling,
                max_batch,
                decode_frames,
                ..
            } => {
                let predict = PredictOptions {
                    sample: SampleOptions {
                        steps: sampling.denoise_steps,
                        guidance_scale: 1.0,
                        batch_noise: sampling.batch_noise,
                        strength: sampling.strength,
                        keep_static_margin_px: sampling.keep_static_margin_px,
                        ..SampleOptions::default()
                    },
                    max_batch: *max_batch,
                    decode_frames: *decode_frames,
                };
                let mut wrapped = MaskConditioned::new(
                    model.as_ref(),
                    world.embodiment.clone(),
                    inst.expert.meta.arm,
                    inst.expert.camera.clone(),
                    inst.expert.actions[0].clone(),
                    predict,
                )?;
                wrapped.goal_latent = sampling.goal_latent;
                f(&wrapped)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_perfect_model_refuses_weights_and_prompt_embeds_it_would_ignore() {
        let path = PathBuf::from("trained/bridgev2w.safetensors");
        for (weights, prompt_embeds, flag) in [
            (Some(path.clone()), None, "--weights"),
            (None, Some(path.clone()), "--prompt-embeds"),
        ] {
            let o = ModelOptions {
                weights,
                prompt_embeds,
                ..ModelOptions::default()
            };
            let e = LoadedModel::load(&o)
                .expect_err("ignored input")
                .to_string();
            assert!(
                e.contains(flag)
                    && e.contains("--model perfect")
                    && e.contains(&path.display().to_string()),
                "{e}"
            );
        }
        assert!(ModelOptions::default().check_inputs().is_ok());
        // A random: model, as `ModelSpec::check_inputs` refuses it.
        let o = ModelOptions {
            model: "random".parse().expect("random"),
            weights: Some(path),
            ..ModelOptions::default()
        };
        let e = o.check_inputs().expect_err("ignored weights").to_string();
        assert!(e.contains("--weights") && e.contains("random:tiny"), "{e}");
    }
}
