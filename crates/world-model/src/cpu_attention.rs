//! The transformer's softmax attention on the CPU: libtorch's
//! `scaled_dot_product_attention`, or in bf16 on a CPU with AVX512-BF16
//! [`bridgev2w_torch_ext::cpu_attention`]'s kernel.
//!
//! libtorch's CPU flash attention runs its bf16 products through MKL, which
//! on a CPU without AMX widens them to f32: on this project's 2-core AMD
//! EPYC (Zen 4) bf16 attention took as long as f32 attention and 12% of a
//! bf16 transformer forward (`docs/benchmarks.md`). The kernel runs the same
//! algorithm on oneDNN's bf16 micro-kernel, about twice as fast there.
//!
//! It is taken only where it computes what libtorch's does: bf16 tensors on
//! the CPU, no gradient recorded for them (prediction, planning, evaluation;
//! training keeps libtorch's differentiable attention), an even head size,
//! and a CPU it runs on. Its results differ from libtorch's bf16 attention
//! by the order of summation (both round the probabilities to bf16 before
//! the product with the values); f32 and CUDA stay on libtorch.
//! `BRIDGEV2W_CPU_ATTENTION=aten|onednn|auto` chooses process-wide
//! ([`init_from_env`], called by the binary and the Python module at
//! start-up).

use crate::error::WorldModelError;
use crate::process_mode::{ModeCell, ProcessMode};
use bridgev2w_torch_ext::cpu_attention as kernel;
use std::sync::atomic::{AtomicU64, Ordering};
use tch::{Device, Kind, Tensor};

/// The environment variable [`init_from_env`] reads.
pub const ENV: &str = "BRIDGEV2W_CPU_ATTENTION";

/// Which kernel runs bf16 attention on the CPU outside autograd.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum CpuAttention {
    /// `OneDnn` where the CPU runs it (AVX512-BF16), else `Aten`.
    #[default]
    Auto,
    /// libtorch's `scaled_dot_product_attention`, as diffusers runs.
    Aten,
    /// Flash attention on oneDNN's bf16 micro-kernel.
    OneDnn,
}

crate::named_enum!(CpuAttention, WorldModelError, WorldModelError::input, ENV, {
    Auto => "auto",
    Aten => "aten",
    OneDnn => "onednn",
});

impl ProcessMode for CpuAttention {
    const ENV: &'static str = ENV;
    const VARIANTS: &'static [Self] = Self::ALL;
    /// `Auto` and `OneDnn` decided for this CPU (`Aten` where the kernel
    /// cannot run).
    fn resolve(self) -> Self {
        match self {
            Self::Auto | Self::OneDnn if kernel::available() => Self::OneDnn,
            _ => Self::Aten,
        }
    }
}

static MODE: ModeCell = ModeCell::new();

/// Sets the process-wide mode (`OneDnn` falls back to `Aten` where the CPU
/// cannot run the kernel).
pub fn set(mode: CpuAttention) {
    MODE.set(mode);
}

/// Sets the mode from [`ENV`] (unset: `Auto`) and returns it resolved; an
/// unknown value is an error naming the variable, the value and the choices.
pub fn init_from_env() -> Result<CpuAttention, WorldModelError> {
    MODE.init_from_env()
}

/// The mode in effect (`Aten` or `OneDnn`).
pub fn mode() -> CpuAttention {
    MODE.get()
}

static FALLBACKS: AtomicU64 = AtomicU64::new(0);

/// How many calls on the kernel's path failed there and ran libtorch's
/// attention instead, in this process: 0 unless something is wrong (`bench
/// model` reports a non-zero count).
pub fn fallbacks() -> u64 {
    FALLBACKS.load(Ordering::Relaxed)
}

/// Whether `mode` runs this call on the kernel.
fn on_kernel(mode: CpuAttention, q: &Tensor, k: &Tensor, v: &Tensor) -> bool {
    let fits = |t: &Tensor| {
        t.device() == Device::Cpu
            && t.kind() == Kind::BFloat16
            && t.dim() == 4
            && t.stride()[3] == 1
    };
    // Cheapest first: in `aten` mode, f32 or on CUDA nothing more is asked
    // of libtorch.
    let recorded = || {
        bridgev2w_torch_ext::onednn::grad_mode_enabled()
            && (q.requires_grad() || k.requires_grad() || v.requires_grad())
    };
    mode == CpuAttention::OneDnn
        && fits(q)
        && fits(k)
        && fits(v)
        && q.size()[3] % 2 == 0
        && !recorded()
}

/// `softmax(q k^T / sqrt(D)) v` for `q [B, heads, T, D]`, `k`, `v
/// [B, heads, S, D]`: `[B, heads, T, D]`.
pub fn attention(q: &Tensor, k: &Tensor, v: &Tensor) -> Tensor {
    attention_in(mode(), q, k, v)
}

/// [`attention`] in `mode`.
fn attention_in(mode: CpuAttention, q: &Tensor, k: &Tensor, v: &Tensor) -> Tensor {
    if on_kernel(mode, q, k, v) {
        let scale = 1.0 / (q.size()[3] as f64).sqrt();
        match kernel::attention_bf16(q, k, v, scale) {
            Ok(out) => return out,
            Err(_) => FALLBACKS.fetch_add(1, Ordering::Relaxed),
        };
    }
    Tensor::scaled_dot_product_attention(q, k, v, None::<Tensor>, 0.0, false, None, false)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn qkv(kind: Kind) -> (Tensor, Tensor, Tensor) {
        let opts = (Kind::Float, Device::Cpu);
        let t = |l: i64| Tensor::randn([1, 2, l, 64], opts).to_kind(kind);
        (t(70), t(90), t(90))
    }

    fn sdpa(q: &Tensor, k: &Tensor, v: &Tensor) -> Tensor {
        Tensor::scaled_dot_product_attention(q, k, v, None::<Tensor>, 0.0, false, None, false)
    }

    #[test]
    fn aten_mode_and_off_path_calls_are_libtorch_bit_for_bit() {
        tch::manual_seed(0);
        let (q, k, v) = qkv(Kind::BFloat16);
        assert!(attention_in(CpuAttention::Aten, &q, &k, &v).equal(&sdpa(&q, &k, &v)));
        // f32 stays on libtorch in any mode.
        let (q, k, v) = qkv(Kind::Float);
        assert!(attention_in(CpuAttention::OneDnn, &q, &k, &v).equal(&sdpa(&q, &k, &v)));
        // A gradient recorded: libtorch's differentiable attention.
        let (q, k, v) = qkv(Kind::BFloat16);
        let q = q.set_requires_grad(true);
        let out = attention_in(CpuAttention::OneDnn, &q, &k, &v);
        assert!(out.requires_grad());
        assert!(out.equal(&sdpa(&q, &k, &v)));
    }

    #[test]
    fn the_kernel_runs_bf16_inference_where_the_cpu_has_it() {
        tch::manual_seed(1);
        let (q, k, v) = qkv(Kind::BFloat16);
        let _guard = tch::no_grad_guard();
        let mode = CpuAttention::Auto.resolve();
        assert_eq!(mode == CpuAttention::OneDnn, kernel::available());
        let got = attention_in(mode, &q, &k, &v);
        let want = sdpa(&q, &k, &v);
        assert_eq!(got.size(), want.size());
        let err = (got.to_kind(Kind::Float) - want.to_kind(Kind::Float))
            .abs()
            .max()
            .double_value(&[]);
        // Two bf16 roundings of values below ~1: a few bf16 steps at most.
        assert!(err < 2e-2, "{err}");
        if mode == CpuAttention::OneDnn {
            assert!(!got.equal(&want), "the kernel ran (not libtorch's result)");
        }
    }

    #[test]
    fn a_failing_kernel_call_runs_libtorch_and_is_counted() {
        if !kernel::available() {
            return;
        }
        let _guard = tch::no_grad_guard();
        let opts = (Kind::BFloat16, Device::Cpu);
        let q = Tensor::ones([1, 2, 3, 8], opts);
        let kv = Tensor::ones([1, 2, 0, 8], opts); // no keys: the kernel refuses
        let before = fallbacks();
        let got = attention_in(CpuAttention::OneDnn, &q, &kv, &kv);
        assert_eq!(fallbacks(), before + 1);
        assert_eq!(got.size(), [1, 2, 3, 8]);
        assert!(got
            .to_kind(Kind::Float)
            .equal(&sdpa(&q, &kv, &kv).to_kind(Kind::Float)));
    }

    #[test]
    fn modes_parse_and_unknown_names_are_errors_naming_the_variable() {
        assert_eq!("aten".parse::<CpuAttention>().unwrap(), CpuAttention::Aten);
        assert_eq!(
            "onednn".parse::<CpuAttention>().unwrap(),
            CpuAttention::OneDnn
        );
        let err = "flash".parse::<CpuAttention>().unwrap_err().to_string();
        assert!(err.contains(ENV) && err.contains("flash"), "{err}");
        assert_eq!(CpuAttention::Aten.resolve(), CpuAttention::Aten);
    }
}
