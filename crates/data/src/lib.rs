//! Data for BridgeV2W: a synthetic tabletop world with held-out cameras and
//! scenes ([`synth`]), its software RGB renderer ([`render`]), and the
//! LeRobot v3.0 (writer and reader) and v2.1 (reader) dataset layouts
//! ([`lerobot`]) with H.264 video in MP4 ([`video`], [`mp4`]), and readers for
//! the raw DROID and AgiBot World layouts ([`raw`]).
//!
//! Frames and units: transforms are named `a_from_b`, lengths are metres and
//! angles radians unless a name says otherwise; the world frame of the
//! synthetic scenes is the robot base frame.

pub mod calibrate;
pub mod clip_masks;
pub mod lerobot;
pub mod mp4;
pub mod overlay;
pub mod raw;
pub mod render;
pub mod synth;
pub mod video;
