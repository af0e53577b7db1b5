//! Softmax attention in bf16 on x86 CPUs with AVX512-BF16
//! (`csrc/cpu_attention.cpp`), for inference.
//!
//! libtorch's CPU flash attention runs its bf16 products through MKL, which
//! on a CPU without AMX widens them to f32 (`sgemm`): bf16 attention there
//! is no faster than f32. This kernel is the same flash-attention algorithm
//! (blocks of 64 queries and 512 keys, an online softmax in f32, the
//! probabilities rounded to bf16 before the product with the values, as
//! libtorch does) with both products on oneDNN's bf16 micro-kernel
//! (`vdpbf16ps`), which libtorch exports as `at::native::cpublas::brgemm`.
//!
//! No autograd formula: call it only where no gradient is recorded.

use crate::{Result, TorchExtError};
use std::ffi::{c_char, c_int, c_void, CStr};
use tch::Tensor;

extern "C" {
    fn bv2w_cpu_attention_available() -> c_int;
    fn bv2w_cpu_attention_bf16(
        q: *mut c_void,
        k: *mut c_void,
        v: *mut c_void,
        scale: f64,
        err: *mut c_char,
        err_len: usize,
    ) -> *mut c_void;
}

const ERR_LEN: usize = 1024;

/// Whether [`attention_bf16`] runs here: an x86-64 CPU with AVX512-BF16 and
/// a libtorch with oneDNN's bf16 micro-kernel (checked once on a small
/// attention against a plain computation).
pub fn available() -> bool {
    // SAFETY: no arguments; the shim catches every C++ exception.
    unsafe { bv2w_cpu_attention_available() == 1 }
}

/// `softmax(q k^T * scale) v` for bf16 CPU tensors `q [B, heads, Lq, D]`,
/// `k` and `v [B, heads, Lk, D]` (`D` even, the last dimension contiguous;
/// other strides free): `[B, heads, Lq, D]`, a view of a
/// `[B, Lq, heads, D]` buffer. An error (never an abort) where the shapes
/// or dtypes do not fit or the CPU cannot run it ([`available`]).
pub fn attention_bf16(q: &Tensor, k: &Tensor, v: &Tensor, scale: f64) -> Result<Tensor> {
    let mut err = [0 as c_char; ERR_LEN];
    // SAFETY: live tensor handles and an ERR_LEN-byte buffer; the shim only
    // reads the tensors and returns a fresh `new at::Tensor` or null.
    let ptr = unsafe {
        bv2w_cpu_attention_bf16(
            q.as_ptr() as *mut c_void,
            k.as_ptr() as *mut c_void,
            v.as_ptr() as *mut c_void,
            scale,
            err.as_mut_ptr(),
            ERR_LEN,
        )
    };
    if ptr.is_null() {
        // SAFETY: the buffer is zero-initialised and the shim writes at most
        // ERR_LEN - 1 bytes plus a NUL.
        let msg = unsafe { CStr::from_ptr(err.as_ptr()) }.to_string_lossy();
        return Err(TorchExtError::OneDnn(format!(
            "bf16 CPU attention: {}",
            msg.trim_end()
        )));
    }
    // SAFETY: a non-null result is a fresh `new at::Tensor` handed over; tch
    // takes ownership and frees it once.
    Ok(unsafe { Tensor::from_ptr(ptr as *mut torch_sys::C_tensor) })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use tch::{Device, Kind};

    fn max_err(a: &Tensor, b: &Tensor) -> f64 {
        (a.to_kind(Kind::Float) - b.to_kind(Kind::Float))
            .abs()
            .max()
            .double_value(&[])
    }

    /// q, k, v as the transformer makes them: views of one projection
    /// `[B, L, 3, heads, D]`, transposed to `[B, heads, L, D]`.
    fn qkv(b: i64, heads: i64, lq: i64, lk: i64, d: i64) -> (Tensor, Tensor, Tensor) {
        let opts = (Kind::Float, Device::Cpu);
        let x = (Tensor::randn([b, lq, 3, heads, d], opts) * 2.0).to_kind(Kind::BFloat16);
        let kv = (Tensor::randn([b, lk, 2, heads, d], opts) * 2.0).to_kind(Kind::BFloat16);
        (
            x.select(2, 0).transpose(1, 2),
            kv.select(2, 0).transpose(1, 2),
            kv.select(2, 1).transpose(1, 2),
        )
    }

    #[test]
    fn availability_follows_the_cpu() {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx512bf16") {
            // The pinned libtorch exports the bf16 micro-kernel: the start-up
            // check (a small attention against a plain one) must pass.
            assert!(
                available(),
                "AVX512-BF16: the kernel's start-up check failed"
            );
        } else {
            assert!(!available(), "no AVX512-BF16: the kernel must not run");
        }
        #[cfg(not(target_arch = "x86_64"))]
        assert!(!available());
    }

    #[test]
    fn matches_libtorch_attention_within_its_own_bf16_error() {
        if !available() {
            eprintln!("skipped: this CPU has no AVX512-BF16");
            return;
        }
        tch::manual_seed(0);
        // One query block and one key block with an odd count; several
        // query blocks and three key blocks (online softmax across blocks,
        // an odd tail); a head size that is not a multiple of 16.
        for (b, heads, lq, lk, d) in [
            (2, 3, 37, 37, 64),
            (1, 2, 130, 1100, 64),
            (1, 2, 70, 515, 40),
        ] {
            let (q, k, v) = qkv(b, heads, lq, lk, d);
            let scale = 1.0 / (d as f64).sqrt();
            let f32 = |t: &Tensor| t.to_kind(Kind::Float);
            let reference = Tensor::scaled_dot_product_attention(
                &f32(&q),
                &f32(&k),
                &f32(&v),
                None::<Tensor>,
                0.0,
                false,
                Some(scale),
                false,
            );
            let libtorch = Tensor::scaled_dot_product_attention(
                &q,
                &k,
                &v,
                None::<Tensor>,
                0.0,
                false,
                Some(scale),
                false,
            );
            let got = attention_bf16(&q, &k, &v, scale).unwrap();
            assert_eq!(got.size(), [b, heads, lq, d]);
            assert_eq!(got.kind(), Kind::BFloat16);
            // The [B, Lq, heads, D] buffer: the model's reshape copies nothing.
            assert!(got.transpose(1, 2).is_contiguous());
            let ours = max_err(&got, &reference);
            let theirs = max_err(&libtorch, &reference);
            assert!(
                ours <= 1.5 * theirs + 1e-3,
                "{b}x{heads}x{lq}x{lk}x{d}: error vs f32 {ours} (libtorch bf16: {theirs})"
            );
            let mean = (f32(&got) - &reference)
                .abs()
                .mean(Kind::Float)
                .double_value(&[]);
            assert!(mean < 4e-3, "mean error {mean}");
        }
    }

    #[test]
    fn bad_inputs_are_errors_not_aborts() {
        let bf = |s: &[i64]| Tensor::zeros(s, (Kind::BFloat16, Device::Cpu));
        let cases = [
            (bf(&[1, 2, 4, 8]), bf(&[1, 2, 5, 8]), bf(&[1, 2, 4, 8])),
            (bf(&[1, 2, 4, 7]), bf(&[1, 2, 5, 7]), bf(&[1, 2, 5, 7])),
            (
                bf(&[1, 2, 4, 8]).to_kind(Kind::Float),
                bf(&[1, 2, 5, 8]),
                bf(&[1, 2, 5, 8]),
            ),
            (bf(&[2, 4, 8]), bf(&[2, 5, 8]), bf(&[2, 5, 8])),
            (bf(&[1, 2, 4, 8]), bf(&[1, 2, 0, 8]), bf(&[1, 2, 0, 8])),
        ];
        for (q, k, v) in cases {
            let err = attention_bf16(&q, &k, &v, 0.5).unwrap_err().to_string();
            assert!(err.starts_with("bf16 CPU attention: "), "{err}");
        }
    }
}
