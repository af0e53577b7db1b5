//! bf16 matrix products and convolutions on CPUs without bf16 arithmetic.
//!
//! On an x86 CPU without AVX512-BF16 (and so without AMX), libtorch's bf16
//! GEMMs and oneDNN's bf16 convolutions emulate the format: on this project's
//! 2-core machine (an Intel Xeon whose hypervisor hides both) a bf16 GEMM of
//! the transformer's feed-forward shape ran at 61 GFLOP/s against 284 in f32,
//! and a 3x3x3 VAE convolution 4.5 to 5.3 times slower than in f32
//! (`docs/benchmarks.md`). There the model's linear layers and convolutions
//! widen their bf16 operands to f32 (exactly), compute in f32 and round the
//! result to bf16: what a native bf16 kernel computes (products of bf16
//! values accumulated in f32), up to the order of summation. Activations and
//! weights stay bf16 between the layers, so memory is that of bf16.
//!
//! An Intel CPU whose bf16 arithmetic is AVX512-BF16 alone (no AMX) runs
//! `vdpbf16ps` at half its f32 rate: there too widening is faster (1.6-1.9x
//! on the transformer and the VAE).
//!
//! The mode is process-wide: [`Bf16Compute::Auto`] (the default) widens
//! where the CPU has no AVX512-BF16, or is an Intel one without AMX;
//! `BRIDGEV2W_CPU_BF16=native|f32|auto` chooses ([`init_from_env`], which
//! the binary calls at start-up), or [`set`]. CUDA tensors and f32 tensors
//! are left alone. Inside a CPU autocast region libtorch casts a layer's
//! operands back to bf16 itself, so there (training with `autocast = "bf16"`
//! on the CPU) the widening gains nothing.

use crate::error::WorldModelError;
use crate::process_mode::{ModeCell, ProcessMode};
use tch::{Device, Kind, TchError, Tensor};

/// The environment variable [`init_from_env`] reads.
pub const ENV: &str = "BRIDGEV2W_CPU_BF16";

/// How bf16 linear layers and convolutions run on the CPU.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Bf16Compute {
    /// `Native` where libtorch's bf16 kernels outrun f32 ones
    /// ([`native_bf16_outruns_f32`]), else `F32`.
    #[default]
    Auto,
    /// libtorch's own bf16 kernels.
    Native,
    /// Operands widened to f32, the result rounded back to bf16.
    F32,
}

crate::named_enum!(Bf16Compute, WorldModelError, WorldModelError::input, ENV, {
    Auto => "auto",
    Native => "native",
    F32 => "f32",
});

impl ProcessMode for Bf16Compute {
    const ENV: &'static str = ENV;
    const VARIANTS: &'static [Self] = Self::ALL;
    /// `Auto` decided for this CPU (`Native` or `F32`).
    fn resolve(self) -> Self {
        match self {
            Self::Auto if native_bf16_outruns_f32() => Self::Native,
            Self::Auto => Self::F32,
            other => other,
        }
    }
}

/// Whether the CPU has bf16 arithmetic that libtorch's kernels use
/// (AVX512-BF16; every CPU with AMX has it too). `true` off x86-64, where
/// nothing here second-guesses libtorch.
pub fn cpu_has_bf16_arithmetic() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx512bf16")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        true
    }
}

/// Whether libtorch's own bf16 kernels outrun f32 ones on this CPU: it has
/// bf16 arithmetic, and it is not an Intel CPU whose only bf16 arithmetic is
/// AVX512-BF16 (no AMX). On such a Xeon (2 cores, AMX hidden by the
/// hypervisor) oneDNN's bf16 kernels (`vdpbf16ps`) ran the transformer
/// forward and the VAE 1.6-1.9x slower than f32, while AMD's Zen 4 runs
/// them about 2x faster than f32 (`docs/benchmarks.md`). `true` off x86-64.
pub fn native_bf16_outruns_f32() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        cpu_has_bf16_arithmetic() && (!cpu_is_intel() || cpu_has_amx_bf16())
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        true
    }
}

/// Whether the CPU's vendor string (CPUID leaf 0) is `GenuineIntel`.
pub fn cpu_is_intel() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        let id = std::arch::x86_64::__cpuid(0);
        [id.ebx, id.edx, id.ecx].map(u32::to_le_bytes).concat() == b"GenuineIntel"
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Whether the CPU has AMX's bf16 tile products (CPUID leaf 7, EDX bit 22).
pub fn cpu_has_amx_bf16() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::x86_64::__cpuid(0).eax >= 7
            && std::arch::x86_64::__cpuid_count(7, 0).edx & (1 << 22) != 0
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Whether libtorch's own bf16 convolutions on this CPU fall back to its
/// `slow_conv3d`, a scalar GEMM on one thread: oneDNN has bf16
/// convolutions only with AVX-512 (F, BW, VL, DQ) or AVX-NE-CONVERT, and
/// on an AVX2-only CPU a VAE convolution took 380 times as long as in f32
/// (`docs/benchmarks.md`). What diffusers' bf16 VAE runs on such a CPU;
/// this crate widens to f32 there. `false` off x86-64.
pub fn libtorch_bf16_conv_is_scalar() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::is_x86_feature_detected as has;
        let avx512 = has!("avx512f") && has!("avx512bw") && has!("avx512vl") && has!("avx512dq");
        !(avx512 || has!("avxneconvert"))
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

static MODE: ModeCell = ModeCell::new();

/// Sets the process-wide mode.
pub fn set(mode: Bf16Compute) {
    MODE.set(mode);
}

/// Sets the mode from [`ENV`] (unset: `Auto`) and returns it resolved; an
/// unknown value is an error naming the variable, the value and the choices.
pub fn init_from_env() -> Result<Bf16Compute, WorldModelError> {
    MODE.init_from_env()
}

/// The mode in effect (`Native` or `F32`); `Auto` for this CPU until [`set`].
pub fn mode() -> Bf16Compute {
    MODE.get()
}

/// Whether an op on `x` widens in `mode`: a CPU bf16 tensor in `F32` mode.
fn widens_in(mode: Bf16Compute, x: &Tensor) -> bool {
    x.kind() == Kind::BFloat16 && x.device() == Device::Cpu && mode.resolve() == Bf16Compute::F32
}

fn widens(x: &Tensor) -> bool {
    widens_in(mode(), x)
}

fn f32(t: &Tensor) -> Tensor {
    t.to_kind(Kind::Float)
}

/// `x W^T + b` (`weight [out, in]`), widened on a CPU without bf16 arithmetic.
pub fn linear(x: &Tensor, weight: &Tensor, bias: Option<&Tensor>) -> Tensor {
    linear_widened(widens(x), x, weight, bias)
}

fn linear_widened(widen: bool, x: &Tensor, weight: &Tensor, bias: Option<&Tensor>) -> Tensor {
    if widen {
        f32(x)
            .linear(&f32(weight), bias.map(f32).as_ref())
            .to_kind(Kind::BFloat16)
    } else {
        x.linear(weight, bias)
    }
}

/// A convolution in N = 2 or 3 spatial dimensions (libtorch's `conv2d` /
/// `conv3d` with dilation 1 and one group), widened on a CPU without bf16
/// arithmetic.
pub fn conv<const N: usize>(
    x: &Tensor,
    weight: &Tensor,
    bias: Option<&Tensor>,
    stride: [i64; N],
    padding: [i64; N],
) -> Result<Tensor, TchError> {
    conv_widened(widens(x), x, weight, bias, stride, padding)
}

/// A convolution in N spatial dimensions (dilation 1, one group), widened
/// when `widen`.
fn conv_widened<const N: usize>(
    widen: bool,
    x: &Tensor,
    weight: &Tensor,
    bias: Option<&Tensor>,
    stride: [i64; N],
    padding: [i64; N],
) -> Result<Tensor, TchError> {
    let run = |x: &Tensor, w: &Tensor, b: Option<&Tensor>| {
        x.f_convolution(w, b, stride, padding, [1i64; N], false, [0i64; N], 1)
    };
    if widen {
        run(&f32(x), &f32(weight), bias.map(f32).as_ref())?.f_to_kind(Kind::BFloat16)
    } else {
        run(x, weight, bias)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn widened_ops_equal_f32_rounded_and_native_bf16_closely() {
        tch::manual_seed(3);
        let bf = |t: Tensor| t.to_kind(Kind::BFloat16);
        let x = bf(Tensor::randn([4, 37, 64], (Kind::Float, Device::Cpu)));
        let w = bf(Tensor::randn([48, 64], (Kind::Float, Device::Cpu)) * 0.1);
        let b = bf(Tensor::randn([48], (Kind::Float, Device::Cpu)));
        let v = bf(Tensor::randn([1, 8, 5, 12, 10], (Kind::Float, Device::Cpu)));
        let k3 = bf(Tensor::randn([6, 8, 3, 3, 3], (Kind::Float, Device::Cpu)) * 0.1);
        let k2 = bf(Tensor::randn([6, 8, 3, 3], (Kind::Float, Device::Cpu)) * 0.1);
        let cb = bf(Tensor::randn([6], (Kind::Float, Device::Cpu)));
        let img = v.select(2, 0);

        assert!(widens_in(Bf16Compute::F32, &x));
        assert!(!widens_in(Bf16Compute::Native, &x));
        assert!(
            !widens_in(Bf16Compute::F32, &f32(&x)),
            "f32 tensors are left alone"
        );
        let lin = linear_widened(true, &x, &w, Some(&b));
        let c3 = conv_widened(true, &v, &k3, Some(&cb), [1, 2, 1], [0, 1, 1]).unwrap();
        let c2 = conv_widened(true, &img, &k2, Some(&cb), [1, 1], [1, 1]).unwrap();
        for t in [&lin, &c3, &c2] {
            assert_eq!(t.kind(), Kind::BFloat16);
        }
        // The reference: the same op in f32 on the widened operands, rounded once.
        let lin_ref = bf(f32(&x).linear(&f32(&w), Some(&f32(&b))));
        let c3_ref = bf(f32(&v).conv3d(
            &f32(&k3),
            Some(&f32(&cb)),
            [1, 2, 1],
            [0, 1, 1],
            [1, 1, 1],
            1,
        ));
        let c2_ref = bf(f32(&img).conv2d(&f32(&k2), Some(&f32(&cb)), [1, 1], [1, 1], [1, 1], 1));
        assert!(lin.equal(&lin_ref));
        assert!(c3.equal(&c3_ref));
        assert!(c2.equal(&c2_ref));

        // libtorch's bf16 kernels: the same products, summed in another order
        // (and, for some, rounded in between): within a few bf16 ulps.
        let lin_n = linear_widened(false, &x, &w, Some(&b));
        let c3_n = conv_widened(false, &v, &k3, Some(&cb), [1, 2, 1], [0, 1, 1]).unwrap();
        assert!(lin_n.equal(&x.linear(&w, Some(&b))));
        for (a, r) in [(&lin_n, &lin_ref), (&c3_n, &c3_ref)] {
            let err = (f32(a) - f32(r)).abs().max().double_value(&[]);
            let scale = f32(r).abs().max().double_value(&[]);
            assert!(err <= 0.02 * scale, "native vs widened: {err} of {scale}");
        }
    }

    #[test]
    fn auto_follows_the_cpu() {
        // The CPUID readings agree with the kernel's (/proc/cpuinfo).
        if let Ok(info) = std::fs::read_to_string("/proc/cpuinfo") {
            let field = |name: &str| {
                info.lines()
                    .find_map(|l| l.strip_prefix(name))
                    .map(|v| v.trim_start_matches([' ', '\t', ':']).trim().to_string())
            };
            if let (Some(vendor), Some(flags)) = (field("vendor_id"), field("flags")) {
                assert_eq!(cpu_is_intel(), vendor == "GenuineIntel", "{vendor}");
                let has = |f: &str| flags.split(' ').any(|x| x == f);
                assert_eq!(cpu_has_amx_bf16(), has("amx_bf16"), "{flags}");
                assert_eq!(cpu_has_bf16_arithmetic(), has("avx512_bf16"), "{flags}");
            }
        }
        let expect = if native_bf16_outruns_f32() {
            Bf16Compute::Native
        } else {
            Bf16Compute::F32
        };
        assert_eq!(Bf16Compute::Auto.resolve(), expect);
        // The process-wide default (no test sets another mode).
        assert_eq!(mode(), expect);
    }

    #[test]
    fn modes_parse_and_bad_values_name_the_variable() {
        assert_eq!("auto".parse::<Bf16Compute>().unwrap(), Bf16Compute::Auto);
        assert_eq!(
            "native".parse::<Bf16Compute>().unwrap(),
            Bf16Compute::Native
        );
        assert_eq!("f32".parse::<Bf16Compute>().unwrap(), Bf16Compute::F32);
        let err = "fast".parse::<Bf16Compute>().unwrap_err().to_string();
        assert!(
            err.contains(ENV) && err.contains("\"fast\"") && err.contains("native"),
            "{err}"
        );
        for m in [Bf16Compute::Auto, Bf16Compute::Native, Bf16Compute::F32] {
            assert_eq!(m.to_string().parse::<Bf16Compute>().unwrap(), m);
        }
        assert_ne!(Bf16Compute::Native.resolve(), Bf16Compute::Auto);
        assert_ne!(Bf16Compute::Auto.resolve(), Bf16Compute::Auto);
    }
}
