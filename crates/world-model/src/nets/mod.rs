//! Frozen reference networks used by the metrics and losses: LPIPS (AlexNet
//! trunk with the v0.1 linear heads), RAFT optical flow (large, small) and
//! I3D (the FVD feature network). Weights come from user-supplied
//! safetensors files with torchvision's and the `lpips` package's key names
//! (`scripts/convert_reference_weights.py` converts the `.pth` releases).

pub mod i3d;
pub mod lpips;
pub mod raft;
