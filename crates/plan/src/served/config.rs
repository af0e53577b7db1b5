//! How a served policy's observations and actions map to this project's:
//! a small TOML file (`eval-policy-rollout --policy-config FILE`). Every
//! field has a default: openpi's DROID example (`pi0_fast_droid`'s keys, a
//! 224x224 exterior image, joint and gripper positions, a prompt), with the
//! actions taken as absolute end-effector poses.
//!
//! ```toml
//! keys = "flat"                 # "nested": "images/cam_high" is {"images": {"cam_high": ..}}
//! timeout_s = 30.0              # connect and per-request limit
//!
//! [observation]
//! image = "observation/exterior_image_1_left"
//! blank_images = ["observation/wrist_image_left"]   # sent black (one camera here)
//! image_size = [224, 224]       # [height, width], resized, uint8
//! image_layout = "hwc"          # or "chw"
//! joints = "observation/joint_position"              # "" to leave out
//! arm_joints = 7                # the first N of the robot's joints
//! gripper = "observation/gripper_position"           # "" to leave out
//! ee_pose = ""                  # [x, y, z, roll, pitch, yaw] when named
//! prompt_key = "prompt"
//! prompt = "do the task"
//!
//! [action]
//! key = "actions"
//! layout = "ee_absolute"        # [x, y, z, roll, pitch, yaw, gripper] per step; "ee_delta": added to the current pose;
//!                               # "joint_position" / "joint_velocity": [arm joints.., gripper] through forward kinematics
//! execute = 0                   # actions of each chunk executed (0: all)
//! control_hz = 15.0             # rows per second of joint velocities
//! ```

use super::msgpack_numpy::KeyStyle;
use serde::Deserialize;
use std::path::Path;
use std::str::FromStr;

/// The image's memory layout.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ImageLayout {
    /// `[height, width, 3]` (openpi's DROID and LIBERO examples).
    #[default]
    Hwc,
    /// `[3, height, width]` (openpi's ALOHA example).
    Chw,
}

/// What each row of the returned action chunk means.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ActionLayout {
    /// `[x, y, z, roll, pitch, yaw, gripper]`: the end effector's pose in
    /// the robot's base frame (metres, radians) and the gripper's closure
    /// (0 open, 1 closed).
    #[default]
    EeAbsolute,
    /// `[dx, dy, dz, droll, dpitch, dyaw, gripper]`: added to the pose
    /// before the chunk (each row relative to that pose, not chained); the
    /// gripper absolute.
    EeDelta,
    /// `[q_1 .. q_n, gripper]` with `n = observation.arm_joints`: the arm's
    /// joint positions (radians), through the robot's forward kinematics.
    JointPosition,
    /// `[dq_1/dt .. dq_n/dt, gripper]`: joint velocities (radians per
    /// second), integrated over `action.control_hz` from the joints before
    /// the chunk, row after row (openpi's DROID policies), then forward
    /// kinematics.
    JointVelocity,
}

impl FromStr for ActionLayout {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "ee_absolute" => Ok(Self::EeAbsolute),
            "ee_delta" => Ok(Self::EeDelta),
            "joint_position" => Ok(Self::JointPosition),
            "joint_velocity" => Ok(Self::JointVelocity),
            _ => Err(format!(
                "{s:?}: expected \"ee_absolute\", \"ee_delta\", \"joint_position\" or \"joint_velocity\""
            )),
        }
    }
}

/// The observation's keys and formats.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ObservationMap {
    /// The camera image's key.
    pub image: String,
    /// Further image keys the server expects, sent black.
    pub blank_images: Vec<String>,
    /// `[height, width]` the image is resized to.
    pub image_size: [usize; 2],
    /// The image's layout.
    pub image_layout: ImageLayout,
    /// The arm joints' key (`""`: not sent).
    pub joints: String,
    /// How many of the robot's joints (URDF actuated order) are the arm's.
    pub arm_joints: usize,
    /// The gripper closure's key, a `[1]` array (`""`: not sent).
    pub gripper: String,
    /// The end-effector pose's key, `[x, y, z, roll, pitch, yaw]` (`""`: not sent).
    pub ee_pose: String,
    /// The prompt's key (`""`: not sent).
    pub prompt_key: String,
    /// The prompt.
    pub prompt: String,
}

impl Default for ObservationMap {
    fn default() -> Self {
        Self {
            image: "observation/exterior_image_1_left".into(),
            blank_images: vec!["observation/wrist_image_left".into()],
            image_size: [224, 224],
            image_layout: ImageLayout::Hwc,
            joints: "observation/joint_position".into(),
            arm_joints: 7,
            gripper: "observation/gripper_position".into(),
            ee_pose: String::new(),
            prompt_key: "prompt".into(),
            prompt: "do the task".into(),
        }
    }
}

/// The action chunk's key and meaning.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ActionMap {
    /// The chunk's key in the response, an array `[steps, 7]`.
    pub key: String,
    /// What a row means.
    pub layout: ActionLayout,
    /// Actions of each chunk executed before the policy is asked again (0: all).
    pub execute: usize,
    /// Rows per second of a `joint_velocity` chunk (DROID: 15).
    pub control_hz: f64,
}

impl Default for ActionMap {
    fn default() -> Self {
        Self {
            key: "actions".into(),
            layout: ActionLayout::EeAbsolute,
            execute: 0,
            control_hz: 15.0,
        }
    }
}

/// A served policy's mapping (see the module docs).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ServedPolicyConfig {
    /// Whether `/` in keys nests maps.
    pub keys: KeyStyle,
    /// Seconds allowed to connect, and for each answer.
    pub timeout_s: f64,
    /// The observation.
    pub observation: ObservationMap,
    /// The actions.
    pub action: ActionMap,
}

impl Default for ServedPolicyConfig {
    fn default() -> Self {
        Self {
            keys: KeyStyle::Flat,
            timeout_s: 30.0,
            observation: ObservationMap::default(),
            action: ActionMap::default(),
        }
    }
}

impl ServedPolicyConfig {
    /// Reads and checks a TOML file; errors name the file and the field.
    pub fn read(path: &Path) -> Result<Self, String> {
        let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
        let c: Self = toml::from_str(&text).map_err(|e| format!("{}: {e}", path.display()))?;
        c.check().map_err(|e| format!("{}: {e}", path.display()))?;
        Ok(c)
    }

    /// Checks the values.
    pub fn check(&self) -> Result<(), String> {
        if !(self.timeout_s.is_finite() && self.timeout_s > 0.0) {
            return Err(format!(
                "timeout_s = {}: expected seconds > 0",
                self.timeout_s
            ));
        }
        let [h, w] = self.observation.image_size;
        if !(1..=4096).contains(&h) || !(1..=4096).contains(&w) {
            return Err(format!(
                "observation.image_size = [{h}, {w}]: expected [height, width] of 1..=4096 pixels"
            ));
        }
        if self.observation.image.is_empty() {
            return Err("observation.image: expected the image's key".into());
        }
        if !(self.action.control_hz.is_finite() && self.action.control_hz > 0.0) {
            return Err(format!(
                "action.control_hz = {}: expected rows per second > 0",
                self.action.control_hz
            ));
        }
        if self.action.key.is_empty() {
            return Err("action.key: expected the action chunk's key".into());
        }
        Ok(())
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    /// The first ```toml block of `text`, `prefix` stripped from its lines.
    fn toml_block(text: &str, prefix: &str) -> String {
        text.lines()
            .map(|l| l.trim_start_matches(prefix).trim_start())
            .skip_while(|l| !l.starts_with("```toml"))
            .skip(1)
            .take_while(|l| !l.starts_with("```"))
            .map(|l| format!("{l}\n"))
            .collect()
    }

    #[test]
    fn the_documented_example_parses_and_unknown_fields_are_named() {
        let here = toml_block(include_str!("config.rs"), "//!");
        let guide = toml_block(include_str!("../../../../docs/guide/planning.md"), "");
        for example in [here, guide] {
            let c: ServedPolicyConfig = toml::from_str(&example).unwrap();
            assert_eq!(c, ServedPolicyConfig::default(), "{example}");
        }
        let e = toml::from_str::<ServedPolicyConfig>("[action]\nlayot = \"ee_delta\"\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("layot"), "{e}");
        let bad = ServedPolicyConfig {
            timeout_s: 0.0,
            ..ServedPolicyConfig::default()
        };
        assert!(bad.check().unwrap_err().contains("timeout_s = 0"));
    }
}
