//! Weight initialisation for training the VAE: from scratch, or from an autoencoder
//! trained on single frames.

use tch::nn::VarStore;

/// Re-initialises a VAE's convolutions as PyTorch does (`kaiming_uniform_(a=sqrt(5))`
/// for weights and the same bound for biases: uniform in `±1/sqrt(fan_in)`), from the
/// global seed; norm scales and shifts keep 1 and 0. For training from scratch.
pub fn init_like_pytorch(vs: &VarStore) {
    let vars = vs.variables();
    tch::no_grad(|| {
        let mut names: Vec<&String> = vars.keys().collect();
        names.sort();
        for name in names {
            let w = &vars[name];
            if w.dim() < 4 || !name.ends_with(".weight") {
                continue;
            }
            let fan_in: i64 = w.size()[1..].iter().product();
            let bound = 1.0 / (fan_in.max(1) as f64).sqrt();
            let _ = w.shallow_clone().uniform_(-bound, bound);
            if let Some(b) = vars.get(&format!("{}.bias", name.trim_end_matches(".weight"))) {
                let _ = b.shallow_clone().uniform_(-bound, bound);
            }
        }
    });
}

/// Turns an autoencoder trained on single frames into the same autoencoder
/// applied frame by frame: every causal convolution's temporal taps
/// (`[Cout, Cin, kt, kh, kw]`, `kt > 1`, the last tap the current frame) are
/// summed into the current frame's tap and the earlier taps zeroed. A single
/// frame sees all `kt` taps on copies of itself, so its output is unchanged;
/// a clip's frames then no longer mix in the convolutions (only the group
/// norms still pool over time). The start of clip training after image
/// training (3-D "inflation" of 2-D weights). Returns the number of weights changed.
pub fn inflate_image_weights(vs: &VarStore) -> usize {
    let vars = vs.variables();
    let mut changed = 0;
    tch::no_grad(|| {
        for (name, w) in &vars {
            if w.dim() != 5 || !name.ends_with(".weight") || w.size()[2] < 2 {
                continue;
            }
            let kt = w.size()[2];
            // [Cout, Cin, kt, kh, kw] -> [Cout, Cin, 1, kh, kw]
            let summed = w.sum_dim_intlist(2, true, w.kind());
            let mut dst = w.shallow_clone();
            let _ = dst.zero_();
            dst.narrow(2, kt - 1, 1).copy_(&summed);
            changed += 1;
        }
    });
    changed
}
