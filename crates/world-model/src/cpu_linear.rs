//! Linear layers on the CPU through oneDNN, with weights packed once.
//!
//! The transformer's time on the CPU is its matrix products (84% of a
//! forward in diffusers' profile, `docs/benchmarks.md`). libtorch's
//! `linear` runs them as MKL `sgemm` calls that repack the weight at every
//! call; oneDNN's inference linear layer (the op torch.compile's CPU backend
//! uses for frozen weights, [`bridgev2w_torch_ext::onednn`]) takes the
//! weight reordered once into its blocked layout, and runs the tanh GELU
//! after the feed-forward's first product inside the same kernel. On this
//! project's 2-core AMD EPYC (Zen 4) the feed-forward's products ran 1.15x
//! to 1.44x faster that way, and 1.09x to 1.21x in bf16
//! (`docs/benchmarks.md`).
//!
//! The path is taken only where it computes what `linear` does: f32
//! tensors on the CPU, or bf16 (libtorch's own bf16 kernels are oneDNN's,
//! without the packing; on a CPU without bf16 arithmetic the operands are
//! widened to f32 as [`crate::cpu_bf16`] does, the weight widened and
//! packed once, in f32), no gradient recorded
//! (`tch::no_grad`: prediction, planning, evaluation; training keeps
//! libtorch's differentiable `linear`), no CPU autocast region, and at
//! least [`MIN_ROWS`] rows (a one-row product, the timestep modulation's,
//! gains nothing from a packed copy). In f32 the results differ from MKL's
//! in the order of summation only (about 1e-6 relative); in bf16 the fused
//! GELU rounds once instead of twice.
//!
//! Packed weights live next to the layer ([`PackedWeight`]) and are made at
//! the first call; a weight changed in place (an optimiser step, loading,
//! a LoRA merge) or replaced is packed again. They double the memory of the
//! layers they cover, so packing stops at a budget (half the memory
//! available at the first pack, or [`set_pack_budget`]); beyond it oneDNN
//! reorders the plain weight at each call instead, with the same result bit
//! for bit. `BRIDGEV2W_CPU_LINEAR=aten|onednn|onednn-bf16|auto` chooses
//! the path process-wide ([`init_from_env`], called by the binary at
//! start-up). `auto` is `onednn-bf16` on an Intel CPU, where MKL's `sgemm`
//! runs its own kernels at the CPU's peak and f32 layers stay on libtorch's
//! `linear`, and `onednn` elsewhere.

use crate::cpu_bf16::Bf16Compute;
use crate::error::WorldModelError;
use crate::process_mode::{ModeCell, ProcessMode};
use bridgev2w_torch_ext::onednn::{self, PostOp};
use bridgev2w_torch_ext::{autocast, AutocastDevice};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use tch::{nn, Device, Kind, Tensor};

/// The environment variable [`init_from_env`] reads.
pub const ENV: &str = "BRIDGEV2W_CPU_LINEAR";

/// Products with fewer rows than this stay on libtorch's `linear`.
pub const MIN_ROWS: i64 = 32;

/// Which kernels run linear layers on the CPU outside autograd.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum CpuLinear {
    /// `OneDnn` where libtorch registers oneDNN's linear ops, else `Aten`.
    #[default]
    Auto,
    /// libtorch's `linear` (MKL `sgemm`), as diffusers runs.
    Aten,
    /// oneDNN's linear layer on packed weights, GELU fused.
    OneDnn,
    /// oneDNN (as `OneDnn`) for bf16 layers, libtorch's `linear` for f32
    /// ones: what `Auto` means on an Intel CPU, where MKL's `sgemm` runs
    /// its own kernels at the CPU's peak (306 GFLOP/s on 2 cores of a Xeon
    /// with AVX-512, as fast as oneDNN's or faster: the f32 transformer
    /// forward 3.3-5% faster than on oneDNN, bf16 6% slower;
    /// `docs/benchmarks.md`).
    OneDnnBf16,
}

crate::named_enum!(CpuLinear, WorldModelError, WorldModelError::input, ENV, {
    Auto => "auto",
    Aten => "aten",
    OneDnn => "onednn",
    OneDnnBf16 => "onednn-bf16",
});

impl ProcessMode for CpuLinear {
    const ENV: &'static str = ENV;
    const VARIANTS: &'static [Self] = Self::ALL;
    /// `Auto` decided for this CPU and libtorch (`Aten` where libtorch
    /// lacks oneDNN's linear ops, whatever was chosen).
    fn resolve(self) -> Self {
        match self {
            _ if !onednn::available() => Self::Aten,
            Self::Auto if mkl_runs_its_own_kernels() => Self::OneDnnBf16,
            Self::Auto => Self::OneDnn,
            other => other,
        }
    }
}

impl CpuLinear {
    /// Whether this (resolved) mode runs a layer of dtype `kind` on oneDNN.
    fn takes(self, kind: Kind) -> bool {
        match self {
            Self::OneDnn => kind == Kind::Float || kind == Kind::BFloat16,
            Self::OneDnnBf16 => kind == Kind::BFloat16,
            Self::Auto | Self::Aten => false,
        }
    }
}

/// Whether libtorch's f32 `linear` (MKL's `sgemm`) runs MKL's own kernels
/// here: on an Intel CPU (its vendor string, CPUID leaf 0). Elsewhere MKL
/// takes generic paths, which oneDNN's packed layers beat by 1.15-1.44x on
/// an AMD EPYC (`docs/benchmarks.md`).
pub fn mkl_runs_its_own_kernels() -> bool {
    crate::cpu_bf16::cpu_is_intel()
}

static MODE: ModeCell = ModeCell::new();

/// Sets the process-wide mode (`OneDnn` falls back to `Aten` where libtorch
/// lacks the ops).
pub fn set(mode: CpuLinear) {
    MODE.set(mode);
}

/// Sets the mode from [`ENV`] (unset: `Auto`) and returns it resolved; an
/// unknown value is an error naming the variable, the value and the choices.
pub fn init_from_env() -> Result<CpuLinear, WorldModelError> {
    MODE.init_from_env()
}

/// The mode in effect (`Aten` or `OneDnn`).
pub fn mode() -> CpuLinear {
    MODE.get()
}

static FALLBACKS: AtomicU64 = AtomicU64::new(0);

/// How many calls on the oneDNN path failed there (an error from oneDNN)
/// and ran libtorch's `linear` instead, in this process: 0 unless something
/// is wrong (`bench model` reports a non-zero count).
pub fn fallbacks() -> u64 {
    FALLBACKS.load(Ordering::Relaxed)
}

/// Bytes of packed weights alive and the most there may be.
#[derive(Debug)]
pub struct PackBudget {
    used: AtomicU64,
    // u64::MAX: not decided yet (set at the first pack from /proc/meminfo).
    limit: AtomicU64,
}

impl PackBudget {
    const fn undecided() -> Self {
        Self {
            used: AtomicU64::new(0),
            limit: AtomicU64::new(u64::MAX),
        }
    }

    /// Takes `bytes` if they fit.
    fn reserve(&self, bytes: u64) -> bool {
        if self.limit.load(Ordering::Relaxed) == u64::MAX {
            // Another thread may decide first: keep whichever is stored.
            let _ = self.limit.compare_exchange(
                u64::MAX,
                default_budget(),
                Ordering::Relaxed,
                Ordering::Relaxed,
            );
        }
        let limit = self.limit.load(Ordering::Relaxed);
        self.used
            .fetch_update(Ordering::Relaxed, Ordering::Relaxed, |used| {
                (used.saturating_add(bytes) <= limit).then_some(used + bytes)
            })
            .is_ok()
    }

    fn release(&self, bytes: u64) {
        self.used.fetch_sub(bytes, Ordering::Relaxed);
    }
}

/// The process's budget.
static BUDGET: PackBudget = PackBudget::undecided();

/// At most `bytes` of packed weights from now on (0: pack nothing more;
/// layers beyond the budget run on their plain weights, with the same
/// results).
pub fn set_pack_budget(bytes: u64) {
    BUDGET
        .limit
        .store(bytes.min(u64::MAX - 1), Ordering::Relaxed);
}

/// Bytes of packed weights alive in this process.
pub fn packed_bytes() -> u64 {
    BUDGET.used.load(Ordering::Relaxed)
}

/// Half of the memory available to this process
/// ([`bridgev2w_io::memory::available_bytes`]: `MemAvailable` in
/// `/proc/meminfo`, or less under a cgroup limit; 0 where it cannot be read).
fn default_budget() -> u64 {
    bridgev2w_io::memory::available_bytes().map_or(0, |b| b / 2)
}

/// A weight packed for oneDNN and what it was packed from.
#[derive(Debug)]
struct Pack {
    /// The weight's data when packed (a detached alias: it keeps that
    /// memory alive, so an equal data pointer means the same data, and it
    /// shares the weight's version counter).
    source: Tensor,
    version: u64,
    /// Packed from the weight widened to f32.
    widened: bool,
    packed: Tensor,
    bytes: u64,
    budget: &'static PackBudget,
}

impl Drop for Pack {
    fn drop(&mut self) {
        self.budget.release(self.bytes);
    }
}

/// A layer's packed weight, made at its first oneDNN call and remade when
/// the weight changes.
#[derive(Debug, Default)]
pub struct PackedWeight(Mutex<Option<Pack>>);

impl PackedWeight {
    /// The packed `weight` (widened to f32 first when `widen`), packing it
    /// now if needed; `None` beyond the budget or if packing failed (the
    /// caller uses the plain weight).
    fn get(&self, weight: &Tensor, widen: bool, budget: &'static PackBudget) -> Option<Tensor> {
        let mut slot = self.0.lock().ok()?;
        let version = onednn::tensor_version(weight);
        if let Some(p) = slot.as_ref() {
            if p.source.data_ptr() == weight.data_ptr()
                && p.version == version
                && p.widened == widen
                && p.source.size() == weight.size()
                && p.source.kind() == weight.kind()
            {
                return Some(p.packed.shallow_clone());
            }
        }
        *slot = None;
        let elt = if widen {
            4
        } else {
            weight.kind().elt_size_in_bytes()
        };
        let bytes = (weight.numel() * elt) as u64;
        if !budget.reserve(bytes) {
            return None;
        }
        let packed = if widen {
            onednn::pack_linear_weight(&weight.to_kind(Kind::Float))
        } else {
            onednn::pack_linear_weight(weight)
        };
        match packed {
            Ok(packed) => {
                let out = packed.shallow_clone();
                *slot = Some(Pack {
                    source: weight.detach(),
                    version,
                    widened: widen,
                    packed,
                    bytes,
                    budget,
                });
                Some(out)
            }
            Err(_) => {
                budget.release(bytes);
                None
            }
        }
    }

    /// Drops the packed copy (when the layer leaves the oneDNN path: a
    /// conversion, training).
    fn clear(&self) {
        if let Ok(mut slot) = self.0.lock() {
            if slot.is_some() {
                *slot = None;
            }
        }
    }
}

/// Where a call goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Route {
    /// oneDNN; `widen`: bf16 operands computed in f32 (a CPU without bf16
    /// arithmetic, [`crate::cpu_bf16`]), the result rounded to bf16.
    OneDnn { widen: bool },
    /// libtorch's `linear` for this call (too few rows, autocast): a packed
    /// weight stays for the next call.
    Aten,
    /// libtorch's `linear`, and a packed weight is dropped: the weight is
    /// not on the path (mode, dtype, device) or autograd records (training,
    /// where the weights change at every step).
    AtenDropPack,
}

/// Where `x W^T + b` runs in `mode`, bf16 being computed as `bf16` says
/// (see the module's conditions).
fn route(
    mode: CpuLinear,
    bf16: Bf16Compute,
    x: &Tensor,
    weight: &Tensor,
    bias: Option<&Tensor>,
) -> Route {
    let kind = weight.kind();
    let same = |t: &Tensor| t.kind() == kind && t.device() == Device::Cpu;
    let weight_on_path =
        mode.resolve().takes(kind) && onednn::available() && same(weight) && weight.dim() == 2;
    if !weight_on_path || onednn::grad_mode_enabled() {
        return Route::AtenDropPack;
    }
    let call_on_path = same(x)
        && bias.is_none_or(same)
        && x.dim() >= 2
        && x.size().last() == weight.size().get(1)
        && x.numel() as i64 / weight.size()[1].max(1) >= MIN_ROWS
        && !autocast::is_enabled(AutocastDevice::Cpu).unwrap_or(true);
    if call_on_path {
        Route::OneDnn {
            widen: kind == Kind::BFloat16 && bf16.resolve() == Bf16Compute::F32,
        }
    } else {
        Route::Aten
    }
}

/// `x W^T + b` then `post_op` (`weight [out, in]`): on oneDNN with the
/// packed weight in `pack` where the module's conditions hold, else
/// libtorch's `linear` (bf16 widened as [`crate::cpu_bf16::linear`] does).
pub fn linear(
    x: &Tensor,
    weight: &Tensor,
    bias: Option<&Tensor>,
    pack: &PackedWeight,
    post_op: PostOp,
) -> Tensor {
    linear_in(
        mode(),
        crate::cpu_bf16::mode(),
        &BUDGET,
        x,
        weight,
        bias,
        pack,
        post_op,
    )
}

/// [`linear`] in `mode` and bf16 mode `bf16`, packing within `budget`.
#[allow(clippy::too_many_arguments)]
fn linear_in(
    mode: CpuLinear,
    bf16: Bf16Compute,
    budget: &'static PackBudget,
    x: &Tensor,
    weight: &Tensor,
    bias: Option<&Tensor>,
    pack: &PackedWeight,
    post_op: PostOp,
) -> Tensor {
    match route(mode, bf16, x, weight, bias) {
        Route::OneDnn { widen: false } => {
            let packed = pack.get(weight, false, budget);
            let w = packed.as_ref().unwrap_or(weight);
            match onednn::linear(x, w, bias, post_op) {
                Ok(y) => return y,
                Err(_) => FALLBACKS.fetch_add(1, Ordering::Relaxed),
            };
        }
        Route::OneDnn { widen: true } => {
            let f32 = |t: &Tensor| t.to_kind(Kind::Float);
            let w = pack
                .get(weight, true, budget)
                .unwrap_or_else(|| f32(weight));
            match onednn::linear(&f32(x), &w, bias.map(f32).as_ref(), post_op) {
                Ok(y) => return y.to_kind(Kind::BFloat16),
                Err(_) => FALLBACKS.fetch_add(1, Ordering::Relaxed),
            };
        }
        Route::Aten => {}
        Route::AtenDropPack => pack.clear(),
    }
    let y = crate::cpu_bf16::linear(x, weight, bias);
    match post_op {
        PostOp::None => y,
        PostOp::GeluTanh => y.gelu("tanh"),
    }
}

/// tch's [`nn::Linear`] (same parameters, `weight` and `bias`) whose
/// forward goes through [`linear`] with its own packed weight.
#[derive(Debug)]
pub struct Linear {
    /// The parameters.
    pub layer: nn::Linear,
    pack: PackedWeight,
}

impl Linear {
    /// Wraps `layer`.
    pub fn new(layer: nn::Linear) -> Self {
        Self {
            layer,
            pack: PackedWeight::default(),
        }
    }

    /// `post_op(x W^T + b)`.
    pub fn forward_then(&self, x: &Tensor, post_op: PostOp) -> Tensor {
        linear(
            x,
            &self.layer.ws,
            self.layer.bs.as_ref(),
            &self.pack,
            post_op,
        )
    }
}

impl nn::Module for Linear {
    fn forward(&self, x: &Tensor) -> Tensor {
        self.forward_then(x, PostOp::None)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn layer(vs: &nn::VarStore, i: i64, o: i64) -> Linear {
        Linear::new(nn::linear(vs.root() / "l", i, o, Default::default()))
    }

    fn max_diff(a: &Tensor, b: &Tensor) -> f64 {
        (a - b).abs().max().double_value(&[])
    }

    /// A budget of its own (the process's is shared with the other tests).
    fn budget(limit: u64) -> &'static PackBudget {
        let b = Box::leak(Box::new(PackBudget::undecided()));
        b.limit.store(limit, Ordering::Relaxed);
        b
    }

    const BYTES: u64 = 48 * 80 * 4;

    #[test]
    fn onednn_path_matches_linear_and_repacks_changed_weights() {
        assert_eq!(
            CpuLinear::Auto.resolve(),
            if mkl_runs_its_own_kernels() {
                CpuLinear::OneDnnBf16
            } else {
                CpuLinear::OneDnn
            },
            "this libtorch has oneDNN"
        );
        let b = budget(u64::MAX - 1);
        let run = |l: &Linear, x: &Tensor, post: PostOp| {
            linear_in(
                CpuLinear::OneDnn,
                Bf16Compute::Native,
                b,
                x,
                &l.layer.ws,
                l.layer.bs.as_ref(),
                &l.pack,
                post,
            )
        };
        tch::manual_seed(1);
        let vs = nn::VarStore::new(Device::Cpu);
        let l = layer(&vs, 48, 80);
        let x = Tensor::randn([2, 40, 48], (Kind::Float, Device::Cpu));
        let reference = x.linear(&l.layer.ws, l.layer.bs.as_ref());

        // Autograd on: libtorch's differentiable linear, exactly.
        let y = run(&l, &x, PostOp::None);
        assert!(y.equal(&reference) && y.requires_grad());
        assert_eq!(b.used.load(Ordering::Relaxed), 0);

        let _guard = tch::no_grad_guard();
        let y = run(&l, &x, PostOp::None);
        assert!(
            max_diff(&y, &reference) < 1e-5,
            "{}",
            max_diff(&y, &reference)
        );
        assert_eq!(b.used.load(Ordering::Relaxed), BYTES, "packed once");
        let g = run(&l, &x, PostOp::GeluTanh);
        assert!(max_diff(&g, &reference.gelu("tanh")) < 1e-5);
        assert_eq!(
            b.used.load(Ordering::Relaxed),
            BYTES,
            "the same pack reused"
        );

        // An in-place change of the weight is seen (its version counter).
        let _ = l.layer.ws.shallow_clone().g_mul_scalar_(2.0);
        let reference2 = x.linear(&l.layer.ws, l.layer.bs.as_ref());
        let y2 = run(&l, &x, PostOp::None);
        assert!(
            max_diff(&y2, &reference2) < 1e-5,
            "{}",
            max_diff(&y2, &reference2)
        );
        assert_eq!(
            b.used.load(Ordering::Relaxed),
            BYTES,
            "the stale pack replaced"
        );

        // Few rows, or the aten mode: libtorch's linear, exactly.
        let row = x.narrow(1, 0, 1);
        assert!(run(&l, &row, PostOp::None).equal(&row.linear(&l.layer.ws, l.layer.bs.as_ref())));
        assert_eq!(
            b.used.load(Ordering::Relaxed),
            BYTES,
            "a few-row call keeps the pack"
        );
        let aten = linear_in(
            CpuLinear::Aten,
            Bf16Compute::Native,
            b,
            &x,
            &l.layer.ws,
            l.layer.bs.as_ref(),
            &l.pack,
            PostOp::None,
        );
        assert!(aten.equal(&reference2));
        assert_eq!(
            b.used.load(Ordering::Relaxed),
            0,
            "leaving the path drops the pack"
        );

        // Training (autograd on) drops it too.
        let _ = run(&l, &x, PostOp::None);
        assert_eq!(b.used.load(Ordering::Relaxed), BYTES);
        let trained = tch::with_grad(|| run(&l, &x, PostOp::None));
        assert!(trained.equal(&reference2));
        assert_eq!(b.used.load(Ordering::Relaxed), 0);

        // f64 leaves the path too; bf16 takes it, widened to f32 on a CPU
        // without bf16 arithmetic (packed in f32 then: twice the bytes).
        let _ = run(&l, &x, PostOp::None);
        assert_eq!(b.used.load(Ordering::Relaxed), BYTES);
        let wd = l.layer.ws.to_kind(Kind::Double);
        let yd = linear_in(
            CpuLinear::OneDnn,
            Bf16Compute::Native,
            b,
            &x.to_kind(Kind::Double),
            &wd,
            None,
            &l.pack,
            PostOp::None,
        );
        assert_eq!(yd.kind(), Kind::Double);
        assert_eq!(b.used.load(Ordering::Relaxed), 0);
        let (xb, wb) = (
            x.to_kind(Kind::BFloat16),
            l.layer.ws.to_kind(Kind::BFloat16),
        );
        let f32_of = |t: &Tensor| t.to_kind(Kind::Float);
        // What a bf16 kernel computes: bf16 products summed in f32, rounded once.
        let yb_ref = f32_of(
            &f32_of(&xb)
                .linear::<Tensor>(&f32_of(&wb), None)
                .to_kind(Kind::BFloat16),
        );
        let scale = yb_ref.abs().max().double_value(&[]);
        // oneDNN packs bf16 weights only on CPUs with bf16 support in its
        // reorder (AVX-512 BW/VL/DQ or AVX-NE-CONVERT: "bf16 path needs the
        // cpu support ..." on an AVX2-only CPU); there the native call runs
        // without a pack, the values the same.
        let native_bytes = if onednn::pack_linear_weight(&wb).is_ok() {
            2
        } else {
            0
        };
        for (bf16, bytes) in [(Bf16Compute::Native, native_bytes), (Bf16Compute::F32, 4)] {
            let yb = linear_in(
                CpuLinear::OneDnn,
                bf16,
                b,
                &xb,
                &wb,
                None,
                &l.pack,
                PostOp::None,
            );
            assert_eq!(yb.kind(), Kind::BFloat16);
            assert_eq!(b.used.load(Ordering::Relaxed), 48 * 80 * bytes, "{bf16}");
            let diff = max_diff(&f32_of(&yb), &yb_ref);
            assert!(diff <= 0.02 * scale, "{bf16}: {diff} of {scale}");
        }

        // A dropped layer gives its bytes back.
        let _ = run(&l, &x, PostOp::None);
        drop(l);
        assert_eq!(b.used.load(Ordering::Relaxed), 0);
    }

    #[test]
    fn beyond_the_budget_the_plain_weight_gives_the_same_values() {
        let _guard = tch::no_grad_guard();
        tch::manual_seed(2);
        let vs = nn::VarStore::new(Device::Cpu);
        let l = layer(&vs, 48, 80);
        let x = Tensor::randn([3, 50, 48], (Kind::Float, Device::Cpu));
        let (roomy, full) = (budget(BYTES), budget(BYTES - 1));
        let packed = linear_in(
            CpuLinear::OneDnn,
            Bf16Compute::Native,
            roomy,
            &x,
            &l.layer.ws,
            l.layer.bs.as_ref(),
            &l.pack,
            PostOp::GeluTanh,
        );
        assert_eq!(roomy.used.load(Ordering::Relaxed), BYTES);
        let other = PackedWeight::default();
        let plain = linear_in(
            CpuLinear::OneDnn,
            Bf16Compute::Native,
            full,
            &x,
            &l.layer.ws,
            l.layer.bs.as_ref(),
            &other,
            PostOp::GeluTanh,
        );
        assert_eq!(full.used.load(Ordering::Relaxed), 0, "nothing packed");
        assert!(plain.equal(&packed), "the same kernel, bit for bit");
    }

    #[test]
    fn onednn_bf16_mode_routes_bf16_layers_to_onednn_and_f32_ones_to_libtorch() {
        let _guard = tch::no_grad_guard();
        let x = Tensor::randn([MIN_ROWS, 16], (Kind::Float, Device::Cpu));
        let w = Tensor::randn([8, 16], (Kind::Float, Device::Cpu));
        let (xb, wb) = (x.to_kind(Kind::BFloat16), w.to_kind(Kind::BFloat16));
        let route_of = |mode, x: &Tensor, w: &Tensor| route(mode, Bf16Compute::Native, x, w, None);
        assert_eq!(
            route_of(CpuLinear::OneDnnBf16, &x, &w),
            Route::AtenDropPack,
            "f32 stays on libtorch"
        );
        assert_eq!(
            route_of(CpuLinear::OneDnnBf16, &xb, &wb),
            Route::OneDnn { widen: false }
        );
        assert_eq!(
            route_of(CpuLinear::OneDnn, &x, &w),
            Route::OneDnn { widen: false }
        );
        assert_eq!(route_of(CpuLinear::Aten, &xb, &wb), Route::AtenDropPack);
        // Whatever the mode, the values are libtorch's up to the order of
        // summation.
        let b = budget(u64::MAX - 1);
        let pack = PackedWeight::default();
        let y = |mode| {
            linear_in(
                mode,
                Bf16Compute::Native,
                b,
                &x,
                &w,
                None,
                &pack,
                PostOp::None,
            )
        };
        let reference = x.linear::<&Tensor>(&w, None);
        for mode in [CpuLinear::OneDnnBf16, CpuLinear::OneDnn, CpuLinear::Aten] {
            assert!(max_diff(&y(mode), &reference) < 1e-4, "{mode}");
        }
    }

    #[test]
    fn modes_parse_and_bad_values_name_the_variable() {
        for &m in CpuLinear::ALL {
            assert_eq!(m.to_string().parse::<CpuLinear>().unwrap(), m);
        }
        let err = "mkl".parse::<CpuLinear>().unwrap_err().to_string();
        assert!(
            err.contains(ENV) && err.contains("\"mkl\"") && err.contains("onednn"),
            "{err}"
        );
        assert_ne!(CpuLinear::Auto.resolve(), CpuLinear::Auto);
    }
}
