//! LoRA adapters (Hu et al. 2021) in PEFT's layout: `W x + (alpha / r) B A x` with
//! `lora_A.weight` `[r, in]` (Kaiming-uniform init, as PEFT) and `lora_B.weight`
//! `[out, r]` (zero init, so a fresh adapter leaves the layer unchanged).
//! BridgeV2W puts them on `to_q`, `to_k`, `to_v` and `to_out.0` of every attention
//! (rank 64, alpha 64).

use crate::error::{Result, WorldModelError};
use tch::nn::{self, Init};
use tch::Tensor;

/// Which linear layers of an attention get adapters (diffusers key suffixes).
pub const LORA_TARGETS: [&str; 4] = ["to_q", "to_k", "to_v", "to_out.0"];

/// LoRA hyper-parameters.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LoraConfig {
    /// Rank r.
    pub rank: i64,
    /// Alpha; the update is scaled by alpha / r.
    pub alpha: f64,
}

impl LoraConfig {
    /// The paper's setting: rank 64, alpha 64.
    pub fn paper() -> Self {
        Self {
            rank: 64,
            alpha: 64.0,
        }
    }

    /// alpha / r.
    pub fn scale(&self) -> f64 {
        self.alpha / self.rank as f64
    }
}

/// One adapter: `lora_A` and `lora_B` under the adapted layer's path.
#[derive(Debug)]
pub struct LoraAdapter {
    /// `[r, in]`.
    pub a: Tensor,
    /// `[out, r]`.
    pub b: Tensor,
    /// alpha / r.
    pub scale: f64,
}

impl LoraAdapter {
    /// Creates `p/lora_A/weight` and `p/lora_B/weight` for a linear `in -> out`.
    pub fn new(p: nn::Path, in_dim: i64, out_dim: i64, cfg: LoraConfig) -> Result<Self> {
        if cfg.rank <= 0 || cfg.rank > in_dim.min(out_dim) {
            return Err(WorldModelError::input(
                "lora rank",
                format!(
                    "{}: expected 1..={} for a {in_dim}->{out_dim} layer",
                    cfg.rank,
                    in_dim.min(out_dim)
                ),
            ));
        }
        if !(cfg.alpha.is_finite() && cfg.alpha > 0.0) {
            return Err(WorldModelError::input(
                "lora alpha",
                format!("{}: expected a positive number", cfg.alpha),
            ));
        }
        // PEFT: kaiming_uniform_(A, a=sqrt(5)) => U(-1/sqrt(in), 1/sqrt(in)).
        let bound = 1.0 / (in_dim as f64).sqrt();
        let a = (&p / "lora_A").var(
            "weight",
            &[cfg.rank, in_dim],
            Init::Uniform {
                lo: -bound,
                up: bound,
            },
        );
        let b = (&p / "lora_B").var("weight", &[out_dim, cfg.rank], Init::Const(0.0));
        Ok(Self {
            a,
            b,
            scale: cfg.scale(),
        })
    }

    /// The low-rank update of `x [..., in]`: `scale * x A^T B^T` `[..., out]`.
    pub fn delta(&self, x: &Tensor) -> Tensor {
        x.matmul(&self.a.tr()).matmul(&self.b.tr()) * self.scale
    }

    /// The dense update `scale * B A` `[out, in]`.
    pub fn dense_update(&self) -> Tensor {
        self.b.matmul(&self.a) * self.scale
    }
}

/// A linear layer in diffusers' layout (`weight` `[out, in]`, optional `bias`) with an
/// optional LoRA adapter that can be merged into the weight and unmerged again.
#[derive(Debug)]
pub struct LoraLinear {
    /// `[out, in]`.
    pub weight: Tensor,
    /// `[out]`.
    pub bias: Option<Tensor>,
    adapter: Option<LoraAdapter>,
    merged: bool,
    /// `weight` packed for oneDNN (inference on the CPU, [`crate::cpu_linear`]).
    pack: crate::cpu_linear::PackedWeight,
}

impl LoraLinear {
    /// Creates `p/weight` (and `p/bias`) with PyTorch's default init.
    pub fn new(p: nn::Path, in_dim: i64, out_dim: i64, bias: bool) -> Self {
        let bound = 1.0 / (in_dim as f64).sqrt();
        let weight = p.var(
            "weight",
            &[out_dim, in_dim],
            Init::Uniform {
                lo: -bound,
                up: bound,
            },
        );
        let bias = bias.then(|| {
            p.var(
                "bias",
                &[out_dim],
                Init::Uniform {
                    lo: -bound,
                    up: bound,
                },
            )
        });
        Self {
            weight,
            bias,
            adapter: None,
            merged: false,
            pack: Default::default(),
        }
    }

    /// `(in, out)` features.
    pub fn dims(&self) -> (i64, i64) {
        let s = self.weight.size();
        (s[1], s[0])
    }

    /// Attaches an adapter under `p` (the same path as the layer, e.g.
    /// `transformer_blocks.0.attn1.to_q`, gives PEFT key names).
    pub fn attach_lora(&mut self, p: nn::Path, cfg: LoraConfig) -> Result<()> {
        let (i, o) = self.dims();
        self.adapter = Some(LoraAdapter::new(p, i, o, cfg)?);
        self.merged = false;
        Ok(())
    }

    /// The adapter, if any.
    pub fn lora(&self) -> Option<&LoraAdapter> {
        self.adapter.as_ref()
    }

    /// Whether the adapter is merged into the weight.
    pub fn is_merged(&self) -> bool {
        self.merged
    }

    /// Adds the adapter's update into the weight (inference without the extra matmuls).
    pub fn merge(&mut self) {
        if let (Some(a), false) = (&self.adapter, self.merged) {
            tch::no_grad(|| {
                let update = a.dense_update().to_kind(self.weight.kind());
                let _ = self.weight.g_add_(&update);
            });
            self.merged = true;
        }
    }

    /// Subtracts a merged adapter's update from the weight again.
    pub fn unmerge(&mut self) {
        if let (Some(a), true) = (&self.adapter, self.merged) {
            tch::no_grad(|| {
                let update = a.dense_update().to_kind(self.weight.kind());
                let _ = self.weight.g_sub_(&update);
            });
            self.merged = false;
        }
    }

    /// `x W^T + b (+ scale x A^T B^T)` for `x [..., in]`.
    pub fn forward(&self, x: &Tensor) -> Tensor {
        let y = crate::cpu_linear::linear(
            x,
            &self.weight,
            self.bias.as_ref(),
            &self.pack,
            bridgev2w_torch_ext::onednn::PostOp::None,
        );
        match (&self.adapter, self.merged) {
            (Some(a), false) => y + a.delta(x),
            _ => y,
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use tch::{Device, Kind};

    fn layer(vs: &nn::VarStore, cfg: LoraConfig) -> LoraLinear {
        let p = vs.root() / "to_q";
        let mut l = LoraLinear::new(p.clone(), 12, 10, true);
        l.attach_lora(p, cfg).unwrap();
        l
    }

    #[test]
    fn fresh_adapter_is_exactly_the_base_layer() {
        tch::manual_seed(0);
        let vs = nn::VarStore::new(Device::Cpu);
        let l = layer(
            &vs,
            LoraConfig {
                rank: 4,
                alpha: 8.0,
            },
        );
        let x = Tensor::randn([3, 5, 12], (Kind::Float, Device::Cpu));
        let base = x.linear(&l.weight, l.bias.as_ref());
        assert!(
            l.forward(&x).equal(&base),
            "B = 0 must give the base output bit for bit"
        );
        let keys: Vec<String> = {
            let mut k: Vec<String> = vs.variables().into_keys().collect();
            k.sort();
            k
        };
        assert_eq!(
            keys,
            [
                "to_q.bias",
                "to_q.lora_A.weight",
                "to_q.lora_B.weight",
                "to_q.weight"
            ]
        );
    }

    #[test]
    fn merge_matches_adapter_path_and_unmerge_restores() {
        tch::manual_seed(1);
        let vs = nn::VarStore::new(Device::Cpu);
        let mut l = layer(
            &vs,
            LoraConfig {
                rank: 3,
                alpha: 6.0,
            },
        );
        tch::no_grad(|| {
            let b = l.lora().unwrap().b.shallow_clone();
            b.shallow_clone()
                .copy_(&Tensor::randn(b.size(), (Kind::Float, Device::Cpu)));
        });
        let x = Tensor::randn([4, 12], (Kind::Float, Device::Cpu));
        let w0 = l.weight.copy();
        let unmerged = l.forward(&x);
        // closed form: x W^T + b + (alpha/r) x A^T B^T
        let a = l.lora().unwrap();
        let expect = x.linear(&w0, l.bias.as_ref()) + x.matmul(&a.a.tr()).matmul(&a.b.tr()) * 2.0;
        assert!(unmerged.allclose(&expect, 1e-5, 1e-6, false));
        assert!(!unmerged.allclose(&x.linear(&w0, l.bias.as_ref()), 1e-3, 1e-3, false));
        l.merge();
        assert!(l.is_merged());
        assert!(l.forward(&x).allclose(&unmerged, 1e-5, 1e-5, false));
        l.merge(); // idempotent
        l.unmerge();
        assert!(l.weight.allclose(&w0, 1e-6, 1e-6, false));
        assert!(l.forward(&x).allclose(&unmerged, 1e-5, 1e-5, false));
    }

    #[test]
    fn gradients_reach_both_factors() {
        tch::manual_seed(2);
        let vs = nn::VarStore::new(Device::Cpu);
        let l = layer(&vs, LoraConfig::paper_scaled_for_test());
        let x = Tensor::randn([2, 12], (Kind::Float, Device::Cpu));
        l.forward(&x)
            .pow_tensor_scalar(2)
            .sum(Kind::Float)
            .backward();
        let a = l.lora().unwrap();
        // B = 0: dL/dA = 0 at init, dL/dB != 0 (the usual LoRA start).
        assert!(a.b.grad().abs().sum(Kind::Float).double_value(&[]) > 0.0);
        assert_eq!(a.a.grad().abs().sum(Kind::Float).double_value(&[]), 0.0);
    }

    #[test]
    fn bad_rank_and_alpha_are_errors() {
        let vs = nn::VarStore::new(Device::Cpu);
        let mut l = LoraLinear::new(vs.root() / "x", 8, 8, false);
        assert!(l
            .attach_lora(
                vs.root() / "x",
                LoraConfig {
                    rank: 0,
                    alpha: 1.0
                }
            )
            .is_err());
        assert!(l
            .attach_lora(
                vs.root() / "x",
                LoraConfig {
                    rank: 9,
                    alpha: 1.0
                }
            )
            .is_err());
        let err = l
            .attach_lora(
                vs.root() / "x",
                LoraConfig {
                    rank: 2,
                    alpha: f64::NAN,
                },
            )
            .unwrap_err()
            .to_string();
        assert!(err.contains("lora alpha"), "{err}");
    }

    impl LoraConfig {
        fn paper_scaled_for_test() -> Self {
            Self {
                rank: 4,
                alpha: 4.0,
            }
        }
    }
}
