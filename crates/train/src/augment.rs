//! Colour augmentation of the `vae` stage: each clip's RGB channels are
//! permuted and, half of the time, inverted (`x -> -x` on `[-1, 1]` data)
//! before it is encoded and reconstructed. An autoencoder trained on the few
//! palettes of one scene family then meets every hue and brightness order,
//! as a VAE trained on internet video does, so that it reconstructs scenes
//! of colours it never saw (the synthetic `unseen_scene` split) as well as
//! the familiar ones. The reconstruction target is the augmented clip.

use crate::Result;
use rand::Rng;
use tch::Tensor;

/// The six orders of three channels.
const PERMUTATIONS: [[i64; 3]; 6] = [
    [0, 1, 2],
    [0, 2, 1],
    [1, 0, 2],
    [1, 2, 0],
    [2, 0, 1],
    [2, 1, 0],
];

/// One clip's draw: a channel order and whether to invert.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ColorDraw {
    /// Output channel `c` is input channel `order[c]`.
    pub order: [i64; 3],
    /// Negate the values (in `[-1, 1]`: 1 - x in `[0, 1]`).
    pub invert: bool,
}

impl ColorDraw {
    /// A uniform draw: one of the six orders, inversion with probability 1/2.
    pub fn sample(rng: &mut impl Rng) -> Self {
        Self {
            order: PERMUTATIONS[rng.gen_range(0..PERMUTATIONS.len())],
            invert: rng.gen_bool(0.5),
        }
    }
}

/// `[B, 3, T, H, W]` -> the same shape, clip `b` recoloured by `draws[b]`.
pub fn recolor(video: &Tensor, draws: &[ColorDraw]) -> Result<Tensor> {
    let b = video.size()[0];
    if draws.len() as i64 != b || video.size().get(1) != Some(&3) {
        return Err(crate::TrainError::input(
            "colour augmentation",
            format!(
                "{} draws for a batch of shape {:?}: expected one per clip of 3 channels",
                draws.len(),
                video.size()
            ),
        ));
    }
    let clips = draws
        .iter()
        .enumerate()
        .map(|(i, d)| {
            let order = Tensor::from_slice(&d.order).to_device(video.device());
            // [3, T, H, W] with its channels reordered
            let c = video.get(i as i64).index_select(0, &order);
            if d.invert {
                -c
            } else {
                c
            }
        })
        .collect::<Vec<_>>();
    Ok(Tensor::stack(&clips, 0))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use tch::{Device, Kind};

    #[test]
    fn recolor_permutes_and_inverts_each_clip() {
        // Clip 0 has channels (0.1, 0.2, 0.3), clip 1 (0.4, 0.5, 0.6).
        let v = Tensor::from_slice(&[0.1f32, 0.2, 0.3, 0.4, 0.5, 0.6])
            .view([2, 3, 1, 1, 1])
            .expand([2, 3, 2, 2, 2], false)
            .contiguous();
        let draws = [
            ColorDraw {
                order: [2, 0, 1],
                invert: false,
            },
            ColorDraw {
                order: [0, 1, 2],
                invert: true,
            },
        ];
        let out = recolor(&v, &draws).unwrap();
        assert_eq!(out.size(), v.size());
        let at = |b: i64, c: i64| out.get(b).get(c).mean(Kind::Float).double_value(&[]);
        let want = [[0.3, 0.1, 0.2], [-0.4, -0.5, -0.6]];
        for b in 0..2 {
            for c in 0..3 {
                assert!((at(b, c) - want[b as usize][c as usize]).abs() < 1e-6);
            }
        }
        assert!(recolor(&v, &draws[..1]).is_err());
        let gray = Tensor::zeros([2, 1, 2, 2, 2], (Kind::Float, Device::Cpu));
        assert!(recolor(&gray, &draws).is_err());
    }

    #[test]
    fn draws_cover_every_order_and_both_signs() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let draws: Vec<ColorDraw> = (0..400).map(|_| ColorDraw::sample(&mut rng)).collect();
        for p in PERMUTATIONS {
            let n = draws.iter().filter(|d| d.order == p).count();
            assert!((40..=100).contains(&n), "{p:?}: {n}");
        }
        let inv = draws.iter().filter(|d| d.invert).count();
        assert!((160..=240).contains(&inv), "{inv}");
    }
}
