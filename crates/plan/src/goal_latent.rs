//! The latent in which planners and policy evaluation measure the distance
//! of a predicted frame to a goal image.
//!
//! The paper scores candidates by the mean L1 distance of VAE latents
//! ([`GoalLatent::Model`]: a diffusion model's VAE posterior mean). A
//! latent that keeps the image's resolution (this project's small VAEs
//! compress space 2x, CogVideoX's 8x) makes that distance flat once the arm
//! no longer overlaps its goal pose: every far candidate costs the same.
//! [`GoalLatent::Pyramid`] measures it on a Gaussian pyramid of the image
//! instead ([`pyramid_latent`], the perfect model's own latent), whose
//! coarse levels grow with the displacement (beyond the paper).

use crate::PlanError;
use bridgev2w_io::frame::RgbFrame;

/// The latent of goal distances.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum GoalLatent {
    /// The model's own encoder: a diffusion model's VAE posterior mean (the
    /// paper), the perfect model's pyramid.
    #[default]
    Model,
    /// A Gaussian pyramid of the RGB image ([`pyramid_latent`]) for every
    /// model.
    Pyramid,
}
bridgev2w_world_model::named_enum!(GoalLatent, PlanError, PlanError::input, "goal latent", {
    Model => "model",
    Pyramid => "pyramid",
});

/// Blur scales of [`pyramid_latent`], as fractions of the image width
/// (1, 2, 4, 8, 16 and 32 pixels at 96 wide; the two coarsest widen the
/// basin for a gripper far from its goal pose).
pub const PYRAMID_SIGMAS: [f64; 6] = [
    1.0 / 96.0,
    2.0 / 96.0,
    4.0 / 96.0,
    8.0 / 96.0,
    16.0 / 96.0,
    32.0 / 96.0,
];

/// The perfect model's latent: a Gaussian pyramid of the image. Level `l`
/// is the image blurred with `sigma_l = PYRAMID_SIGMAS[l] * width` pixels
/// and subsampled with stride `max(1, floor(sigma_l))`; each level's values
/// are scaled so that every level weighs the same in the mean L1 distance.
/// Coarse levels widen the basin of the goal distance (a pixel-exact
/// distance is flat until the arm overlaps its goal pose), fine levels
/// make it precise near the goal.
pub fn pyramid_latent(image: &RgbFrame) -> Vec<f32> {
    let (h, w) = (image.height, image.width);
    let levels: Vec<Vec<f32>> = PYRAMID_SIGMAS
        .iter()
        .map(|frac| {
            let sigma = (frac * w as f64).max(0.5);
            let blurred = gaussian_blur(&image.rgb, h, w, sigma);
            let stride = (sigma.floor() as usize).max(1);
            let mut out = Vec::with_capacity((h / stride + 1) * (w / stride + 1) * 3);
            for y in (0..h).step_by(stride) {
                for x in (0..w).step_by(stride) {
                    out.extend_from_slice(&blurred[(y * w + x) * 3..(y * w + x) * 3 + 3]);
                }
            }
            out
        })
        .collect();
    let total: usize = levels.iter().map(Vec::len).sum();
    let n_levels = levels.len() as f32;
    levels
        .into_iter()
        .flat_map(|l| {
            let scale = total as f32 / (n_levels * l.len() as f32);
            l.into_iter().map(move |v| v * scale)
        })
        .collect()
}

/// Separable Gaussian blur of an interleaved RGB image (`sigma` pixels,
/// truncated at 3 sigma, renormalised at the borders).
pub fn gaussian_blur(data: &[f32], h: usize, w: usize, sigma: f64) -> Vec<f32> {
    let r = (3.0 * sigma).ceil() as isize;
    let kernel: Vec<f32> = (-r..=r)
        .map(|i| (-((i * i) as f64) / (2.0 * sigma * sigma)).exp() as f32)
        .collect();
    let pass = |src: &[f32], horizontal: bool| {
        let mut out = vec![0.0f32; src.len()];
        for y in 0..h {
            for x in 0..w {
                let mut acc = [0.0f32; 3];
                let mut norm = 0.0f32;
                for (j, k) in kernel.iter().enumerate() {
                    let o = j as isize - r;
                    let (xx, yy) = if horizontal {
                        (x as isize + o, y as isize)
                    } else {
                        (x as isize, y as isize + o)
                    };
                    if xx < 0 || yy < 0 || xx >= w as isize || yy >= h as isize {
                        continue;
                    }
                    let at = (yy as usize * w + xx as usize) * 3;
                    for c in 0..3 {
                        acc[c] += k * src[at + c];
                    }
                    norm += k;
                }
                for c in 0..3 {
                    out[(y * w + x) * 3 + c] = acc[c] / norm;
                }
            }
        }
        out
    };
    pass(&pass(data, true), false)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn square(h: usize, w: usize, x0: usize, y0: usize, side: usize) -> RgbFrame {
        let mut data = vec![0.0f32; h * w * 3];
        for y in y0..(y0 + side).min(h) {
            for x in x0..(x0 + side).min(w) {
                data[(y * w + x) * 3..(y * w + x) * 3 + 3].fill(1.0);
            }
        }
        RgbFrame {
            height: h,
            width: w,
            rgb: data,
        }
    }

    #[test]
    fn gaussian_blur_keeps_constants_and_mass() {
        let (h, w) = (12, 20);
        let flat = vec![0.25f32; h * w * 3];
        for v in gaussian_blur(&flat, h, w, 2.0) {
            assert!((v - 0.25).abs() < 1e-6);
        }
        // A point far from the borders keeps its mass and spreads symmetrically.
        let mut dot = vec![0.0f32; 41 * 41 * 3];
        dot[(20 * 41 + 20) * 3] = 1.0;
        let b = gaussian_blur(&dot, 41, 41, 2.0);
        let mass: f32 = b.iter().sum();
        assert!((mass - 1.0).abs() < 1e-4, "{mass}");
        let at = |y: usize, x: usize| b[(y * 41 + x) * 3];
        assert!((at(20, 23) - at(20, 17)).abs() < 1e-7);
        assert!((at(23, 20) - at(20, 23)).abs() < 1e-7);
        // exp(-9 / 8) relative to the centre, per axis.
        let ratio = at(20, 23) / at(20, 20);
        assert!((ratio - (-9.0f32 / 8.0).exp()).abs() < 1e-4, "{ratio}");
    }

    #[test]
    fn the_pyramid_distance_grows_with_displacement_beyond_overlap() {
        // A 4-pixel square displaced by 6..30 pixels never overlaps its goal:
        // a pixel-exact distance is flat there, the pyramid distance grows.
        let (h, w) = (64, 96);
        let goal = pyramid_latent(&square(h, w, 10, 30, 4));
        let d = |dx: usize| {
            crate::model::latent_l1(&pyramid_latent(&square(h, w, 10 + dx, 30, 4)), &goal).unwrap()
        };
        let pixel = |dx: usize| {
            crate::model::latent_l1(
                &square(h, w, 10 + dx, 30, 4).rgb,
                &square(h, w, 10, 30, 4).rgb,
            )
            .unwrap()
        };
        assert_eq!(d(0), 0.0);
        assert_eq!(pixel(6), pixel(30));
        let ds: Vec<f64> = [1, 3, 6, 12, 20, 30].iter().map(|&dx| d(dx)).collect();
        assert!(ds.windows(2).all(|p| p[1] > p[0]), "{ds:?}");
    }

    #[test]
    fn goal_latents_by_name() {
        for name in GoalLatent::NAMES {
            let g: GoalLatent = name.parse().unwrap();
            assert_eq!(g.to_string(), *name);
        }
        let e = "vae".parse::<GoalLatent>().unwrap_err().to_string();
        assert!(
            e.contains("goal latent") && e.contains("model, pyramid"),
            "{e}"
        );
    }
}
