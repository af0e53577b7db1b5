//! Where and in which precision the model runs: the crate's own types, so callers
//! need not depend on tch.

use crate::error::{Result, WorldModelError};
use std::fmt;
use std::str::FromStr;

/// A compute device.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ComputeDevice {
    /// The CPU.
    Cpu,
    /// CUDA GPU by ordinal.
    Cuda(usize),
}

impl ComputeDevice {
    /// CUDA:0 when libtorch sees a GPU, else the CPU.
    pub fn auto() -> Self {
        if tch::Cuda::is_available() {
            Self::Cuda(0)
        } else {
            Self::Cpu
        }
    }

    /// The tch device.
    pub fn to_tch(self) -> tch::Device {
        match self {
            Self::Cpu => tch::Device::Cpu,
            Self::Cuda(i) => tch::Device::Cuda(i),
        }
    }

    /// Checks that the device exists on this machine.
    pub fn check_available(self) -> Result<Self> {
        match self {
            Self::Cpu => Ok(self),
            Self::Cuda(i) => {
                let n = tch::Cuda::device_count();
                if (i as i64) < n {
                    Ok(self)
                } else {
                    Err(WorldModelError::input(
                        "device",
                        format!("cuda:{i} requested but libtorch sees {n} CUDA device(s)"),
                    ))
                }
            }
        }
    }
}

/// Moves the variables of `vs`, built and initialised on the host, onto
/// `device`. Models are built this way so that (as in diffusers, whose
/// random weights and noise come from the CPU generator) a seed gives the
/// same weights on every device, and so that the GPU never holds the f32
/// copy of weights meant for bf16 (whose freed blocks the caching allocator
/// would keep reserved).
pub fn move_to_device(vs: &mut tch::nn::VarStore, device: tch::Device) {
    if vs.device() != device {
        let _guard = tch::no_grad_guard();
        vs.set_device(device);
    }
}

impl fmt::Display for ComputeDevice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Cpu => write!(f, "cpu"),
            Self::Cuda(i) => write!(f, "cuda:{i}"),
        }
    }
}

impl FromStr for ComputeDevice {
    type Err = WorldModelError;
    /// `cpu`, `cuda`, `cuda:N` or `auto` (resolved now: see [`DeviceSpec`]).
    fn from_str(s: &str) -> Result<Self> {
        s.parse::<DeviceSpec>().map(DeviceSpec::resolve)
    }
}

/// A device as a configuration names it: `auto` stays `auto` until the run
/// starts ([`DeviceSpec::resolve`]), and `cuda` stays `cuda` (not `cuda:0`),
/// so a configuration reads back as written.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum DeviceSpec {
    /// CUDA:0 when libtorch sees a GPU, else the CPU.
    Auto,
    /// The CPU.
    #[default]
    Cpu,
    /// A CUDA GPU: `cuda` (`None`, the first) or `cuda:N`.
    Cuda(Option<usize>),
}

impl DeviceSpec {
    /// The device on this machine.
    pub fn resolve(self) -> ComputeDevice {
        match self {
            Self::Auto => ComputeDevice::auto(),
            Self::Cpu => ComputeDevice::Cpu,
            Self::Cuda(i) => ComputeDevice::Cuda(i.unwrap_or(0)),
        }
    }
}

impl FromStr for DeviceSpec {
    type Err = WorldModelError;
    /// `cpu`, `cuda`, `cuda:N` or `auto`.
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "cpu" => Ok(Self::Cpu),
            "cuda" => Ok(Self::Cuda(None)),
            "auto" => Ok(Self::Auto),
            _ => s
                .strip_prefix("cuda:")
                .and_then(|i| i.parse().ok())
                .map(|i| Self::Cuda(Some(i)))
                .ok_or_else(|| {
                    WorldModelError::input(
                        "device",
                        format!("`{s}`: expected cpu, cuda, cuda:N or auto"),
                    )
                }),
        }
    }
}

impl fmt::Display for DeviceSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Auto => write!(f, "auto"),
            Self::Cpu => write!(f, "cpu"),
            Self::Cuda(None) => write!(f, "cuda"),
            Self::Cuda(Some(i)) => write!(f, "cuda:{i}"),
        }
    }
}

impl serde::Serialize for DeviceSpec {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> serde::Deserialize<'de> for DeviceSpec {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        let text = String::deserialize(d)?;
        text.parse().map_err(serde::de::Error::custom)
    }
}

/// Numeric precision of weights and activations.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Precision {
    /// 32-bit float.
    F32,
    /// bfloat16.
    Bf16,
}

impl Precision {
    /// The tch kind.
    pub fn kind(self) -> tch::Kind {
        match self {
            Self::F32 => tch::Kind::Float,
            Self::Bf16 => tch::Kind::BFloat16,
        }
    }
}

impl fmt::Display for Precision {
    /// The name `FromStr` reads back: `f32` or `bf16`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::F32 => "f32",
            Self::Bf16 => "bf16",
        })
    }
}

impl FromStr for Precision {
    type Err = WorldModelError;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "f32" | "fp32" | "float32" => Ok(Self::F32),
            "bf16" | "bfloat16" => Ok(Self::Bf16),
            _ => Err(WorldModelError::input(
                "precision",
                format!("`{s}`: expected f32 or bf16"),
            )),
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn devices_parse_once_for_both_the_spec_and_the_resolved_device() {
        for (text, spec, device) in [
            ("cpu", DeviceSpec::Cpu, ComputeDevice::Cpu),
            ("cuda", DeviceSpec::Cuda(None), ComputeDevice::Cuda(0)),
            ("cuda:2", DeviceSpec::Cuda(Some(2)), ComputeDevice::Cuda(2)),
        ] {
            assert_eq!(text.parse::<DeviceSpec>().unwrap(), spec);
            assert_eq!(spec.to_string(), text);
            assert_eq!(text.parse::<ComputeDevice>().unwrap(), device);
        }
        assert_eq!(
            "auto".parse::<ComputeDevice>().unwrap(),
            ComputeDevice::auto()
        );
        for bad in ["gpu", "cuda:x", ""] {
            let e = bad.parse::<ComputeDevice>().unwrap_err().to_string();
            assert!(e.contains("expected cpu, cuda, cuda:N or auto"), "{e}");
        }
    }
}
