//! Autocast (automatic mixed precision) with a chosen device type and dtype.
//!
//! Inside an autocast region libtorch runs the ops of its "lower precision"
//! list (matmul, linear, convolutions, ...) in the region's dtype and those of
//! its "fp32" list (reductions, norms, losses, ...) in float32, whatever the
//! dtype of the weights; parameters stay float32 and their gradients arrive in
//! float32. The state is thread-local, as in PyTorch.

use crate::{Result, TorchExtError};
use std::os::raw::c_int;

extern "C" {
    fn bv2w_autocast_is_enabled(device: c_int) -> c_int;
    fn bv2w_autocast_set_enabled(device: c_int, enabled: c_int) -> c_int;
    fn bv2w_autocast_get_dtype(device: c_int) -> c_int;
    fn bv2w_autocast_set_dtype(device: c_int, dtype: c_int) -> c_int;
    fn bv2w_autocast_increment_nesting() -> c_int;
    fn bv2w_autocast_decrement_nesting() -> c_int;
    fn bv2w_autocast_clear_cache() -> c_int;
}

/// The device type whose autocast state is set (autocast is per device type,
/// not per device index).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AutocastDevice {
    /// CPU tensors.
    Cpu,
    /// CUDA tensors (any GPU).
    Cuda,
}

impl AutocastDevice {
    /// The device type of a tch device (`None` for devices autocast is not
    /// offered for here, e.g. MPS).
    pub fn of(device: tch::Device) -> Option<Self> {
        match device {
            tch::Device::Cpu => Some(Self::Cpu),
            tch::Device::Cuda(_) => Some(Self::Cuda),
            _ => None,
        }
    }

    fn code(self) -> c_int {
        match self {
            Self::Cpu => 0,
            Self::Cuda => 1,
        }
    }
}

/// The lower-precision dtype of an autocast region.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AutocastDtype {
    /// bfloat16 (the range of float32, 8 bits of mantissa).
    BFloat16,
    /// IEEE half precision.
    Float16,
}

impl AutocastDtype {
    /// The tch kind of this dtype.
    pub fn kind(self) -> tch::Kind {
        match self {
            Self::BFloat16 => tch::Kind::BFloat16,
            Self::Float16 => tch::Kind::Half,
        }
    }

    fn code(self) -> c_int {
        match self {
            Self::Float16 => 1,
            Self::BFloat16 => 2,
        }
    }
}

fn check(what: &str, rc: c_int) -> Result<c_int> {
    if rc < 0 {
        Err(TorchExtError::Autocast(format!(
            "{what} failed in libtorch"
        )))
    } else {
        Ok(rc)
    }
}

/// Whether autocast is on for `device` on this thread.
pub fn is_enabled(device: AutocastDevice) -> Result<bool> {
    // SAFETY: a plain C function taking an int; the shim validates the code
    // and catches every C++ exception.
    let rc = unsafe { bv2w_autocast_is_enabled(device.code()) };
    Ok(check("is_autocast_enabled", rc)? == 1)
}

/// The dtype autocast uses for `device` (`None`: a dtype other than f16/bf16/f32,
/// which this crate never sets).
fn raw_dtype(device: AutocastDevice) -> Result<c_int> {
    // SAFETY: as in `is_enabled`.
    let rc = unsafe { bv2w_autocast_get_dtype(device.code()) };
    if rc == -2 {
        return Err(TorchExtError::Autocast(
            "get_autocast_dtype failed in libtorch".into(),
        ));
    }
    Ok(rc)
}

/// The dtype autocast uses for `device` on this thread (`None` when it is
/// not one of [`AutocastDtype`]'s, e.g. float32).
pub fn dtype(device: AutocastDevice) -> Result<Option<AutocastDtype>> {
    Ok(match raw_dtype(device)? {
        1 => Some(AutocastDtype::Float16),
        2 => Some(AutocastDtype::BFloat16),
        _ => None,
    })
}

fn set_enabled(device: AutocastDevice, enabled: bool) -> Result<()> {
    // SAFETY: as in `is_enabled`.
    let rc = unsafe { bv2w_autocast_set_enabled(device.code(), c_int::from(enabled)) };
    check("set_autocast_enabled", rc).map(|_| ())
}

fn set_raw_dtype(device: AutocastDevice, code: c_int) -> Result<()> {
    // SAFETY: as in `is_enabled`; unknown dtype codes are rejected by the shim.
    let rc = unsafe { bv2w_autocast_set_dtype(device.code(), code) };
    check("set_autocast_dtype", rc).map(|_| ())
}

/// An autocast region: created by [`AutocastGuard::new`], it enables autocast
/// for a device type with a dtype; dropping it restores the previous
/// enabled flag and dtype, and clears the cast cache when the outermost
/// region ends (as PyTorch's `torch.autocast.__exit__`).
#[derive(Debug)]
pub struct AutocastGuard {
    device: AutocastDevice,
    prev_enabled: bool,
    prev_dtype: c_int,
    // Not Send: the autocast state is thread-local.
    _not_send: std::marker::PhantomData<*const ()>,
}

impl AutocastGuard {
    /// Enters an autocast region for `device` with `dtype` (`enabled =
    /// false`: a region with autocast off, e.g. an f32 island inside a bf16
    /// region).
    pub fn new(device: AutocastDevice, dtype: AutocastDtype, enabled: bool) -> Result<Self> {
        let prev_enabled = is_enabled(device)?;
        let prev_dtype = raw_dtype(device)?;
        set_raw_dtype(device, dtype.code())?;
        if let Err(e) = set_enabled(device, enabled) {
            let _ = set_raw_dtype(device, prev_dtype);
            return Err(e);
        }
        // SAFETY: no arguments; the shim catches exceptions.
        let rc = unsafe { bv2w_autocast_increment_nesting() };
        if rc < 0 {
            let _ = set_enabled(device, prev_enabled);
            let _ = set_raw_dtype(device, prev_dtype);
            return Err(TorchExtError::Autocast(
                "increment_nesting failed in libtorch".into(),
            ));
        }
        Ok(Self {
            device,
            prev_enabled,
            prev_dtype,
            _not_send: std::marker::PhantomData,
        })
    }

    /// The device type of the region.
    pub fn device(&self) -> AutocastDevice {
        self.device
    }
}

impl Drop for AutocastGuard {
    fn drop(&mut self) {
        // Errors cannot be reported from drop; none is expected (the codes
        // were accepted when the guard was made).
        // SAFETY: no arguments; the shim catches exceptions.
        let depth = unsafe { bv2w_autocast_decrement_nesting() };
        if depth == 0 {
            // SAFETY: as above.
            let _ = unsafe { bv2w_autocast_clear_cache() };
        }
        let _ = set_enabled(self.device, self.prev_enabled);
        if self.prev_dtype >= 0 {
            let _ = set_raw_dtype(self.device, self.prev_dtype);
        }
    }
}

/// Runs `f` with autocast on for `device`'s type in `dtype` (off when
/// `dtype` is `None`: `f` runs as is), restoring the previous state after,
/// also when `f` panics.
pub fn autocast<T>(
    device: tch::Device,
    dtype: Option<AutocastDtype>,
    f: impl FnOnce() -> T,
) -> Result<T> {
    match (dtype, AutocastDevice::of(device)) {
        (Some(dtype), Some(dev)) => {
            let _guard = AutocastGuard::new(dev, dtype, true)?;
            Ok(f())
        }
        (Some(_), None) => Err(TorchExtError::Autocast(format!(
            "no autocast for device {device:?} (cpu and cuda only)"
        ))),
        (None, _) => Ok(f()),
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use tch::{Device, Kind, Tensor};

    fn mm() -> Tensor {
        let a = Tensor::ones([4, 8], (Kind::Float, Device::Cpu));
        let b = Tensor::ones([8, 3], (Kind::Float, Device::Cpu));
        a.matmul(&b)
    }

    #[test]
    fn cpu_bf16_region_casts_matmul_and_restores_the_state() {
        assert!(!is_enabled(AutocastDevice::Cpu).unwrap());
        assert_eq!(mm().kind(), Kind::Float);
        let (kind, on, sum_kind) = autocast(Device::Cpu, Some(AutocastDtype::BFloat16), || {
            let y = mm();
            // A reduction with an explicit dtype stays f32.
            (
                y.kind(),
                is_enabled(AutocastDevice::Cpu).unwrap(),
                y.sum(Kind::Float).kind(),
            )
        })
        .unwrap();
        assert_eq!(kind, Kind::BFloat16);
        assert!(on);
        assert_eq!(sum_kind, Kind::Float);
        assert!(!is_enabled(AutocastDevice::Cpu).unwrap());
        assert_eq!(mm().kind(), Kind::Float);
        // Values: 8 ones summed, exact in bf16.
        let y = autocast(Device::Cpu, Some(AutocastDtype::BFloat16), mm).unwrap();
        assert_eq!(y.to_kind(Kind::Float).double_value(&[0, 0]), 8.0);
        // `None`: no region.
        assert_eq!(autocast(Device::Cpu, None, mm).unwrap().kind(), Kind::Float);
    }

    #[test]
    fn nested_regions_restore_the_outer_one_also_after_a_panic() {
        let outer = AutocastGuard::new(AutocastDevice::Cpu, AutocastDtype::BFloat16, true).unwrap();
        {
            let _off =
                AutocastGuard::new(AutocastDevice::Cpu, AutocastDtype::BFloat16, false).unwrap();
            assert_eq!(mm().kind(), Kind::Float);
        }
        assert_eq!(mm().kind(), Kind::BFloat16);
        let r = std::panic::catch_unwind(|| {
            let _g = AutocastGuard::new(AutocastDevice::Cpu, AutocastDtype::Float16, true).unwrap();
            assert_eq!(
                dtype(AutocastDevice::Cpu).unwrap(),
                Some(AutocastDtype::Float16)
            );
            panic!("inside the region");
        });
        assert!(r.is_err());
        assert_eq!(
            dtype(AutocastDevice::Cpu).unwrap(),
            Some(AutocastDtype::BFloat16)
        );
        assert_eq!(mm().kind(), Kind::BFloat16);
        drop(outer);
        assert!(!is_enabled(AutocastDevice::Cpu).unwrap());
        assert_eq!(mm().kind(), Kind::Float);
    }

    #[test]
    fn gradients_of_f32_parameters_stay_f32() {
        let w = Tensor::ones([8, 3], (Kind::Float, Device::Cpu)).set_requires_grad(true);
        let x = Tensor::ones([4, 8], (Kind::Float, Device::Cpu));
        let loss = autocast(Device::Cpu, Some(AutocastDtype::BFloat16), || {
            x.matmul(&w).sum(Kind::Float)
        })
        .unwrap();
        loss.backward();
        assert_eq!(w.kind(), Kind::Float);
        assert_eq!(w.grad().kind(), Kind::Float);
        assert_eq!(w.grad().double_value(&[0, 0]), 4.0);
    }
}
