//! Downstream use of an action-conditioned world model (the paper's
//! "Downstream Applications"):
//!
//! * goal-image planning with CEM inside a receding-horizon MPC loop
//!   ([`cem`], [`mpc`]; the paper's Algorithm "CEM-MPC planning"), with the
//!   paper's options (translation-only search, discretised steps, gripper
//!   heuristic, two goal images, rotation refinements) and VLA-proposal
//!   selection;
//! * policy evaluation by autoregressive world-model rollouts ([`policy`]):
//!   success rates per policy, MMRV and Pearson r against real success;
//! * the synthetic tabletop world as the "real robot" and as a perfect
//!   world model ([`synthetic`]);
//! * a diagnostic of whether a model's goal distance orders candidate
//!   actions as the real world does ([`fidelity`]).
//!
//! Models are reached through [`model::ActionWorldModel`]: any
//! [`bridgev2w_world_model::pipeline::WorldModel`] fits through
//! [`model::MaskConditioned`] (actions -> IK -> embodiment masks -> one
//! `predict_batch` per CEM iteration).
//!
//! Frames and units: the world frame is the robot base frame; positions are
//! metres and angles radians unless a name says otherwise.

pub mod cem;
pub mod choice;
pub mod error;
pub mod experiment;
pub mod fidelity;
pub mod goal_latent;
pub mod model;
pub mod mpc;
pub mod policy;
pub mod served;
pub mod synthetic;

pub use error::{PlanError, Result};

/// One end-effector action of the acting arm: `[x, y, z, roll, pitch, yaw,
/// gripper]`, the target pose `world_from_tcp` (metres, radians, Euler as
/// the embodiment crate's `xyz_rpy`) and the gripper command (0 open, 1
/// closed).
pub type EeAction = [f64; 7];

/// What the planner or a policy sees at one moment, and what a model
/// continues from.
#[derive(Debug, Clone)]
pub struct Observation {
    /// The camera image at the model's resolution.
    pub image: bridgev2w_io::frame::RgbFrame,
    /// Robot joints (URDF actuated order).
    pub joints: Vec<f64>,
    /// The acting arm's current end-effector action (pose + gripper): the
    /// robot pose `p0` of the paper's algorithm.
    pub ee: EeAction,
    /// The full synthetic-world state, where the observation comes from the
    /// synthetic world (a perfect world model needs it; others ignore it).
    pub scene: Option<bridgev2w_data::synth::SceneState>,
}
