//! oneDNN's inference linear layer (`csrc/onednn_linear.cpp`): `x W^T + b`
//! with an optional fused tanh GELU, on a plain `[out, in]` weight or on one
//! reordered once into oneDNN's blocked layout ([`pack_linear_weight`]).
//!
//! These are the ops torch.compile's CPU backend runs for frozen f32 and
//! bf16 linear layers (`mkldnn::_linear_pointwise`,
//! `mkldnn::_reorder_linear_weight`). They have no autograd formula: call
//! them only where no gradient is recorded ([`grad_mode_enabled`] false).
//! A packed weight gives the same result as the plain one, bit for bit (the
//! same kernel; the plain call reorders the weight at every call).

use crate::{Result, TorchExtError};
use std::ffi::{c_char, c_int, c_void, CStr};
use tch::Tensor;

extern "C" {
    fn bv2w_onednn_available() -> c_int;
    fn bv2w_grad_mode_enabled() -> c_int;
    fn bv2w_tensor_version(tensor: *mut c_void) -> u64;
    fn bv2w_onednn_pack_linear_weight(
        weight: *mut c_void,
        err: *mut c_char,
        err_len: usize,
    ) -> *mut c_void;
    fn bv2w_onednn_linear(
        input: *mut c_void,
        weight: *mut c_void,
        bias: *mut c_void,
        post_op: c_int,
        err: *mut c_char,
        err_len: usize,
    ) -> *mut c_void;
}

const ERR_LEN: usize = 1024;

/// What runs on the linear layer's output inside the same kernel.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PostOp {
    /// Nothing: `x W^T + b`.
    None,
    /// The tanh approximation of GELU (`gelu(approximate="tanh")`).
    GeluTanh,
}

impl PostOp {
    fn code(self) -> c_int {
        match self {
            Self::None => 0,
            Self::GeluTanh => 1,
        }
    }
}

/// Whether this libtorch registers oneDNN's linear ops (builds with
/// oneDNN, which every x86-64 and aarch64 PyPI wheel is).
pub fn available() -> bool {
    // SAFETY: looks the schemas up in libtorch's dispatcher; no arguments.
    unsafe { bv2w_onednn_available() == 1 }
}

/// Whether autograd records operations on this thread (off inside
/// `tch::no_grad`).
pub fn grad_mode_enabled() -> bool {
    // SAFETY: reads a thread-local flag of libtorch; no arguments.
    unsafe { bv2w_grad_mode_enabled() == 1 }
}

/// The version counter of `t`'s data: every in-place change (an optimiser
/// step, `copy_`, a LoRA merge) increases it.
pub fn tensor_version(t: &Tensor) -> u64 {
    // SAFETY: `as_ptr` is the live `at::Tensor*` behind `t`; the shim only
    // reads its version counter.
    unsafe { bv2w_tensor_version(t.as_ptr() as *mut c_void) }
}

fn take(ptr: *mut c_void, err: &[c_char; ERR_LEN], what: &str) -> Result<Tensor> {
    if ptr.is_null() {
        // SAFETY: the buffer is zero-initialised and the shim writes at most
        // ERR_LEN - 1 bytes plus a NUL.
        let msg = unsafe { CStr::from_ptr(err.as_ptr()) }.to_string_lossy();
        return Err(TorchExtError::OneDnn(format!("{what}: {}", msg.trim_end())));
    }
    // SAFETY: a non-null result is a fresh `new at::Tensor` the shim hands
    // over; tch's Tensor takes ownership and frees it once.
    Ok(unsafe { Tensor::from_ptr(ptr as *mut torch_sys::C_tensor) })
}

/// `weight` (`[out, in]`, f32 or bf16, on the CPU) reordered into oneDNN's
/// layout: an opaque tensor for [`linear`] only.
pub fn pack_linear_weight(weight: &Tensor) -> Result<Tensor> {
    let mut err = [0 as c_char; ERR_LEN];
    // SAFETY: a live tensor handle and an ERR_LEN-byte buffer.
    let ptr = unsafe {
        bv2w_onednn_pack_linear_weight(weight.as_ptr() as *mut c_void, err.as_mut_ptr(), ERR_LEN)
    };
    take(ptr, &err, "packing a linear weight for oneDNN")
}

/// `input W^T + bias`, then `post_op`, by oneDNN. `weight`: `[out, in]`
/// or [`pack_linear_weight`]'s result. No gradient flows through it.
pub fn linear(
    input: &Tensor,
    weight: &Tensor,
    bias: Option<&Tensor>,
    post_op: PostOp,
) -> Result<Tensor> {
    let mut err = [0 as c_char; ERR_LEN];
    let bias_ptr = bias.map_or(std::ptr::null_mut(), |b| b.as_ptr() as *mut c_void);
    // SAFETY: live tensor handles (bias null or live) and an ERR_LEN-byte
    // buffer; the shim copies the handles onto its own stack.
    let ptr = unsafe {
        bv2w_onednn_linear(
            input.as_ptr() as *mut c_void,
            weight.as_ptr() as *mut c_void,
            bias_ptr,
            post_op.code(),
            err.as_mut_ptr(),
            ERR_LEN,
        )
    };
    take(ptr, &err, "oneDNN linear")
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use tch::{Device, Kind};

    fn close(a: &Tensor, b: &Tensor) -> f64 {
        (a - b).abs().max().double_value(&[])
    }

    #[test]
    fn matches_aten_and_packing_changes_nothing() {
        assert!(
            available(),
            "the project's libtorch registers oneDNN's linear ops"
        );
        tch::manual_seed(0);
        let x = Tensor::randn([2, 37, 96], (Kind::Float, Device::Cpu));
        let w = Tensor::randn([160, 96], (Kind::Float, Device::Cpu)) * 0.1;
        let b = Tensor::randn([160], (Kind::Float, Device::Cpu));
        let reference = x.linear(&w, Some(&b));
        let _guard = tch::no_grad_guard();
        let plain = linear(&x, &w, Some(&b), PostOp::None).unwrap();
        assert_eq!(plain.size(), [2, 37, 160]);
        assert!(
            close(&plain, &reference) < 1e-5,
            "{}",
            close(&plain, &reference)
        );
        let packed = pack_linear_weight(&w).unwrap();
        let y = linear(&x, &packed, Some(&b), PostOp::None).unwrap();
        assert!(y.equal(&plain), "packed and plain weights: the same kernel");
        let no_bias = linear(&x, &packed, None, PostOp::None).unwrap();
        assert!(close(&no_bias, &x.linear::<Tensor>(&w, None)) < 1e-5);
        let gelu = linear(&x, &packed, Some(&b), PostOp::GeluTanh).unwrap();
        let gelu_ref = reference.gelu("tanh");
        assert!(
            close(&gelu, &gelu_ref) < 1e-5,
            "{}",
            close(&gelu, &gelu_ref)
        );
        // Rows are independent: a slice alone gives the same rows.
        let part = linear(
            &x.narrow(1, 0, 5).contiguous(),
            &packed,
            Some(&b),
            PostOp::None,
        )
        .unwrap();
        assert!(part.equal(&plain.narrow(1, 0, 5)));
    }

    #[test]
    fn bad_shapes_are_errors_not_aborts() {
        let _guard = tch::no_grad_guard();
        let x = Tensor::randn([3, 8], (Kind::Float, Device::Cpu));
        let w = Tensor::randn([4, 5], (Kind::Float, Device::Cpu));
        let err = linear(&x, &w, None, PostOp::None).unwrap_err().to_string();
        assert!(err.starts_with("oneDNN linear: "), "{err}");
    }

    #[test]
    fn versions_count_in_place_changes_and_grad_mode_is_read() {
        let mut t = Tensor::zeros([3], (Kind::Float, Device::Cpu));
        let v0 = tensor_version(&t);
        let _ = t.g_add_scalar_(1.0);
        assert!(tensor_version(&t) > v0);
        assert!(grad_mode_enabled());
        let _guard = tch::no_grad_guard();
        assert!(!grad_mode_enabled());
    }
}
