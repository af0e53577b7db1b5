//! AdamW (decoupled weight decay, PyTorch's `torch.optim.AdamW` update) over
//! named trainable tensors, with its state (`m`, `v`, step count) as plain
//! tensors so a checkpoint restores it exactly; and global-norm gradient clipping.

use crate::{Result, TrainError};
use std::collections::BTreeMap;
use tch::{Kind, Tensor};

/// AdamW hyper-parameters (the learning rate is passed per step).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdamWConfig {
    /// First-moment decay.
    pub beta1: f64,
    /// Second-moment decay.
    pub beta2: f64,
    /// Denominator epsilon.
    pub eps: f64,
    /// Decoupled weight decay.
    pub weight_decay: f64,
}

/// AdamW over a fixed set of named parameters.
#[derive(Debug)]
pub struct AdamW {
    cfg: AdamWConfig,
    params: Vec<(String, Tensor)>,
    m: Vec<Tensor>,
    v: Vec<Tensor>,
    steps: i64,
}

impl AdamW {
    /// An optimizer over `params` (sorted by name for a stable order), zero state.
    pub fn new(mut params: Vec<(String, Tensor)>, cfg: AdamWConfig) -> Self {
        params.sort_by(|a, b| a.0.cmp(&b.0));
        let zeros = |p: &Tensor| Tensor::zeros_like(p).to_kind(Kind::Float);
        let m = params.iter().map(|(_, p)| zeros(p)).collect();
        let v = params.iter().map(|(_, p)| zeros(p)).collect();
        Self {
            cfg,
            params,
            m,
            v,
            steps: 0,
        }
    }

    /// The parameters, by name.
    pub fn params(&self) -> &[(String, Tensor)] {
        &self.params
    }

    /// Optimizer steps taken.
    pub fn steps(&self) -> i64 {
        self.steps
    }

    /// Sets every parameter's gradient to zero.
    pub fn zero_grad(&mut self) {
        for (_, p) in &mut self.params {
            p.zero_grad();
        }
    }

    /// The global L2 norm of the gradients (missing gradients count as zero).
    pub fn grad_norm(&self) -> f64 {
        let mut sq = 0.0;
        for (_, p) in &self.params {
            let g = p.grad();
            if g.defined() {
                sq += g
                    .to_kind(Kind::Double)
                    .square()
                    .sum(Kind::Double)
                    .double_value(&[]);
            }
        }
        sq.sqrt()
    }

    /// Scales the gradients so their global norm is at most `max_norm`
    /// (`torch.nn.utils.clip_grad_norm_`: factor `max / (norm + 1e-6)` when
    /// below 1). Returns the norm before clipping.
    pub fn clip_grad_norm(&mut self, max_norm: f64) -> f64 {
        let norm = self.grad_norm();
        let coef = max_norm / (norm + 1e-6);
        if max_norm > 0.0 && coef < 1.0 {
            tch::no_grad(|| {
                for (_, p) in &self.params {
                    let mut g = p.grad();
                    if g.defined() {
                        let _ = g.g_mul_scalar_(coef);
                    }
                }
            });
        }
        norm
    }

    /// One AdamW update with learning rate `lr`:
    /// `p *= 1 - lr wd; m = b1 m + (1 - b1) g; v = b2 v + (1 - b2) g^2;
    ///  p -= lr / (1 - b1^t) * m / (sqrt(v) / sqrt(1 - b2^t) + eps)`.
    /// Parameters without a gradient get only the decay.
    pub fn step(&mut self, lr: f64) {
        self.steps += 1;
        let AdamWConfig {
            beta1,
            beta2,
            eps,
            weight_decay,
        } = self.cfg;
        let t = self.steps as i32;
        let bc1 = 1.0 - beta1.powi(t);
        let bc2 = 1.0 - beta2.powi(t);
        tch::no_grad(|| {
            for (i, (_, p)) in self.params.iter().enumerate() {
                let mut p = p.shallow_clone();
                let g = p.grad();
                let g = if g.defined() {
                    g.to_kind(Kind::Float)
                } else {
                    Tensor::zeros_like(&self.m[i])
                };
                let _ = p.g_mul_scalar_(1.0 - lr * weight_decay);
                self.m[i] = &self.m[i] * beta1 + &g * (1.0 - beta1);
                self.v[i] = &self.v[i] * beta2 + g.square() * (1.0 - beta2);
                let denom = self.v[i].sqrt() / bc2.sqrt() + eps;
                let update = (&self.m[i] / denom) * (lr / bc1);
                let _ = p.g_sub_(&update.to_kind(p.kind()));
            }
        });
    }

    /// The state as named tensors: `m.NAME`, `v.NAME`, and `steps` (a scalar int64).
    pub fn state(&self) -> Vec<(String, Tensor)> {
        let mut out = Vec::with_capacity(2 * self.params.len() + 1);
        for (i, (name, _)) in self.params.iter().enumerate() {
            out.push((format!("m.{name}"), self.m[i].shallow_clone()));
            out.push((format!("v.{name}"), self.v[i].shallow_clone()));
        }
        out.push(("steps".into(), Tensor::from_slice(&[self.steps])));
        out
    }

    /// Restores a state written by [`Self::state`] (strict: every buffer, right shapes).
    pub fn load_state(&mut self, state: Vec<(String, Tensor)>) -> Result<()> {
        let mut map: BTreeMap<String, Tensor> = state.into_iter().collect();
        let err = |m: String| TrainError::input("optimizer state", m);
        let steps = map
            .remove("steps")
            .ok_or_else(|| err("no `steps` entry".into()))?;
        let device = self.m.first().map(|t| t.device());
        for (i, (name, p)) in self.params.iter().enumerate() {
            for (prefix, buf) in [("m", &mut self.m[i]), ("v", &mut self.v[i])] {
                let key = format!("{prefix}.{name}");
                let t = map
                    .remove(&key)
                    .ok_or_else(|| err(format!("no `{key}` entry")))?;
                if t.size() != p.size() {
                    return Err(err(format!(
                        "`{key}` {:?} but the parameter is {:?}",
                        t.size(),
                        p.size()
                    )));
                }
                *buf = t
                    .to_kind(Kind::Float)
                    .to_device(device.unwrap_or(p.device()));
            }
        }
        if let Some(k) = map.keys().next() {
            return Err(err(format!("unexpected entry `{k}` (another model?)")));
        }
        self.steps = steps.int64_value(&[0]);
        Ok(())
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn cfg() -> AdamWConfig {
        AdamWConfig {
            beta1: 0.9,
            beta2: 0.95,
            eps: 1e-8,
            weight_decay: 1e-4,
        }
    }

    #[test]
    fn first_step_matches_the_closed_form() {
        // After one step m_hat = g and v_hat = g^2: p1 = p0 (1 - lr wd) - lr g / (|g| + eps).
        let p = Tensor::from_slice(&[1.0f32, -2.0, 0.5]).set_requires_grad(true);
        let mut opt = AdamW::new(vec![("p".into(), p.shallow_clone())], cfg());
        let loss = (&p * Tensor::from_slice(&[3.0f32, -0.25, 0.0])).sum(Kind::Float);
        loss.backward(); // g = [3, -0.25, 0]
        let lr = 0.1;
        opt.step(lr);
        let got = Vec::<f32>::try_from(&p.detach()).unwrap();
        let g = [3.0f64, -0.25, 0.0];
        let p0 = [1.0f64, -2.0, 0.5];
        for i in 0..3 {
            let expected = p0[i] * (1.0 - lr * 1e-4) - lr * g[i] / (g[i].abs() + 1e-8);
            assert!(
                (got[i] as f64 - expected).abs() < 1e-6,
                "[{i}] {} vs {expected}",
                got[i]
            );
        }
        assert_eq!(opt.steps(), 1);
    }

    #[test]
    fn second_step_matches_the_recurrence() {
        let p = Tensor::from_slice(&[1.0f32]).set_requires_grad(true);
        let mut opt = AdamW::new(vec![("p".into(), p.shallow_clone())], cfg());
        let (g1, g2, lr) = (2.0f64, -1.0f64, 0.01);
        for g in [g1, g2] {
            opt.zero_grad();
            (&p * g).sum(Kind::Float).backward();
            opt.step(lr);
        }
        let mut w = 1.0f64;
        let (mut m, mut v) = (0.0, 0.0);
        for (t, g) in [(1, g1), (2, g2)] {
            w *= 1.0 - lr * 1e-4;
            m = 0.9 * m + 0.1 * g;
            v = 0.95 * v + 0.05 * g * g;
            let (bc1, bc2) = (1.0 - 0.9f64.powi(t), 1.0 - 0.95f64.powi(t));
            w -= lr / bc1 * m / (v.sqrt() / bc2.sqrt() + 1e-8);
        }
        let got = p.double_value(&[0]);
        assert!((got - w).abs() < 1e-6, "{got} vs {w}");
    }

    #[test]
    fn clipping_scales_to_the_max_norm_and_state_round_trips() {
        let a = Tensor::zeros([2], (Kind::Float, tch::Device::Cpu)).set_requires_grad(true);
        let b = Tensor::zeros([1], (Kind::Float, tch::Device::Cpu)).set_requires_grad(true);
        let mut opt = AdamW::new(
            vec![
                ("a".into(), a.shallow_clone()),
                ("b".into(), b.shallow_clone()),
            ],
            cfg(),
        );
        let loss = (&a * Tensor::from_slice(&[3.0f32, 0.0])).sum(Kind::Float)
            + (&b * 4.0).sum(Kind::Float);
        loss.backward(); // norm 5
        let n = opt.clip_grad_norm(1.0);
        assert!((n - 5.0).abs() < 1e-6);
        assert!((opt.grad_norm() - 1.0).abs() < 1e-5);
        opt.step(0.1);
        let state = opt.state();
        let mut other = AdamW::new(
            vec![
                ("a".into(), a.shallow_clone()),
                ("b".into(), b.shallow_clone()),
            ],
            cfg(),
        );
        other.load_state(state).unwrap();
        assert_eq!(other.steps(), 1);
        for (x, y) in opt.state().iter().zip(other.state().iter()) {
            assert_eq!(x.0, y.0);
            assert!(x.1.equal(&y.1));
        }
        let mut bad = opt.state();
        bad.pop();
        assert!(other.load_state(bad).is_err());
    }
}
