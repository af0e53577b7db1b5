//! The CUDA caching allocator's memory figures (`csrc/cuda_memory.cpp`):
//! what `torch.cuda.memory_allocated`, `max_memory_allocated`,
//! `memory_reserved` and `max_memory_reserved` report, and
//! `reset_peak_memory_stats`. Exact peaks, where polling `nvidia-smi` can
//! miss a short one and counts the CUDA context.

use crate::{Result, TorchExtError};
use std::ffi::{c_char, c_int, CStr};

extern "C" {
    fn bv2w_cuda_memory(device: c_int, out: *mut u64, err: *mut c_char, err_len: usize) -> c_int;
    fn bv2w_cuda_reset_peak(device: c_int, err: *mut c_char, err_len: usize) -> c_int;
}

const ERR_LEN: usize = 1024;

/// One device's figures, bytes; the peaks since the last [`reset_peak`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CudaMemory {
    /// Held by tensors now.
    pub allocated: u64,
    /// The most held by tensors at once.
    pub peak_allocated: u64,
    /// Reserved from the device by the caching allocator now (tensors and
    /// its free blocks).
    pub reserved: u64,
    /// The most reserved at once: what the device must have, besides the
    /// CUDA context.
    pub peak_reserved: u64,
}

fn check(code: c_int, err: &[c_char; ERR_LEN], what: &str) -> Result<bool> {
    match code {
        1 => Ok(true),
        0 => Ok(false),
        _ => {
            // SAFETY: the buffer is zero-initialised and the shim writes at
            // most ERR_LEN - 1 bytes and a NUL.
            let message = unsafe { CStr::from_ptr(err.as_ptr()) }.to_string_lossy();
            Err(TorchExtError::Cuda(format!("{what}: {message}")))
        }
    }
}

fn device_index(device: usize) -> Result<c_int> {
    c_int::try_from(device)
        .map_err(|_| TorchExtError::Cuda(format!("device {device}: not a CUDA device index")))
}

/// The figures of CUDA device `device`; `None` where this build has no CUDA.
/// An error (never an abort) for a device that is not there.
pub fn memory(device: usize) -> Result<Option<CudaMemory>> {
    let mut out = [0u64; 4];
    let mut err = [0 as c_char; ERR_LEN];
    // SAFETY: a 4-value output and an ERR_LEN-byte buffer; the shim catches
    // every C++ exception.
    let code = unsafe {
        bv2w_cuda_memory(
            device_index(device)?,
            out.as_mut_ptr(),
            err.as_mut_ptr(),
            ERR_LEN,
        )
    };
    Ok(
        check(code, &err, "CUDA memory figures")?.then_some(CudaMemory {
            allocated: out[0],
            peak_allocated: out[1],
            reserved: out[2],
            peak_reserved: out[3],
        }),
    )
}

/// Starts device `device`'s peaks again from its current figures; `false`
/// where this build has no CUDA.
pub fn reset_peak(device: usize) -> Result<bool> {
    let mut err = [0 as c_char; ERR_LEN];
    // SAFETY: an ERR_LEN-byte buffer; the shim catches every C++ exception.
    let code = unsafe { bv2w_cuda_reset_peak(device_index(device)?, err.as_mut_ptr(), ERR_LEN) };
    check(code, &err, "CUDA memory peak reset")
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn figures_of_a_device_or_an_error_never_an_abort() {
        let devices = tch::Cuda::device_count().max(0) as usize;
        // A device past the last: an error naming it (or no CUDA in this build).
        match memory(devices) {
            Ok(None) => assert!(!reset_peak(devices).unwrap()),
            Ok(Some(m)) => panic!("device {devices} of {devices}: {m:?}"),
            Err(e) => {
                let e = e.to_string();
                assert!(e.contains(&format!("no CUDA device {devices}")), "{e}");
                assert!(reset_peak(devices).is_err());
            }
        }
        if devices > 0 {
            // 64 MiB allocated and freed: the peak holds it, the current not.
            reset_peak(0).unwrap();
            let before = memory(0).unwrap().unwrap();
            drop(tch::Tensor::zeros(
                [16 << 20],
                (tch::Kind::Float, tch::Device::Cuda(0)),
            ));
            let after = memory(0).unwrap().unwrap();
            assert!(
                after.peak_allocated >= before.allocated + (64 << 20),
                "{after:?}"
            );
            assert_eq!(after.allocated, before.allocated);
            assert!(after.peak_reserved >= after.peak_allocated);
        }
    }
}
