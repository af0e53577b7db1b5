//! Robot actions to pixel-aligned embodiment masks.
//!
//! The pipeline of BridgeV2W's "Embodiment Mask Extraction from Actions":
//! actions (end-effector poses or joint positions) -> inverse kinematics ->
//! forward kinematics on the URDF -> link meshes placed in the world ->
//! projected through a calibrated camera -> rasterized per frame into a binary
//! mask, a per-link label map and a depth map.
//!
//! Frames and units: transforms are named `a_from_b` (maps coordinates in
//! frame `b` to frame `a`), lengths are metres and angles radians unless a
//! name says otherwise. Cameras use OpenCV axes (x right, y down, z forward).

pub mod actions;
pub mod bench;
pub mod camera;
pub mod embodiment;
pub mod kinematics;
pub mod masks;
pub mod masks_folder;
pub mod mesh;
pub mod overlay;
pub mod posture;
pub mod raster;
pub mod robot;
pub mod robot_info;
