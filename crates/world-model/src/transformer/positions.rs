//! Positional information of the video tokens: CogVideoX's 3D sin-cos
//! embedding (added to the tokens; 2B models, and the 5B-I2V model at frame
//! counts other than its training length) and the 3D rotary embedding of the
//! attention (5B models), computed as diffusers and its image-to-video
//! pipeline do.

use super::config::TransformerConfig;
use crate::error::{Result, WorldModelError};
use tch::{Device, Kind, Tensor};

/// 1-D sin-cos embedding of positions `pos` (`[M]`) in f64: `[M, dim]`,
/// `[sin(p w_i)..., cos(p w_i)...]` with `w_i = 10000^(-2i / dim)`.
fn sincos_1d(dim: usize, pos: &[f64]) -> Vec<Vec<f64>> {
    let half = dim / 2;
    let omega: Vec<f64> = (0..half)
        .map(|i| 1.0 / 10000f64.powf(i as f64 / (dim as f64 / 2.0)))
        .collect();
    pos.iter()
        .map(|&p| {
            let mut row: Vec<f64> = omega.iter().map(|w| (p * w).sin()).collect();
            row.extend(omega.iter().map(|w| (p * w).cos()));
            row
        })
        .collect()
}

/// The patch embedding's joint (text + video) sin-cos positions
/// `[1, max_text_seq_length + F * h * w, D]` (zeros over the text tokens) for
/// `frames` latent frames of `h x w` patches.
pub fn joint_sincos(
    cfg: &TransformerConfig,
    frames: i64,
    h: i64,
    w: i64,
    device: Device,
) -> Tensor {
    let d = cfg.inner_dim();
    let (spatial_dim, temporal_dim) = (3 * d / 4, d / 4);
    // Positions are f32 in diffusers (arange / scale), promoted to f64.
    let positions = |n: i64, scale: f64| -> Vec<f64> {
        (0..n).map(|i| f64::from(i as f32 / scale as f32)).collect()
    };
    // The per-axis tables are small ([n, dim] in f64, rounded to f32 once as
    // diffusers' result is); the [N, D] embedding is broadcast from them on
    // `device` (built on the host it cost a third of a 5B forward).
    let table = |dim: i64, pos: Vec<f64>| -> Tensor {
        let n = pos.len() as i64;
        let rows = sincos_1d(dim as usize, &pos);
        let flat: Vec<f32> = rows.iter().flatten().map(|&v| v as f32).collect();
        Tensor::from_slice(&flat).view([n, dim]).to_device(device) // [n, dim]
    };
    let et = table(
        temporal_dim,
        positions(frames, cfg.temporal_interpolation_scale),
    );
    let ex = table(
        spatial_dim / 2,
        positions(w, cfg.spatial_interpolation_scale),
    );
    let ey = table(
        spatial_dim / 2,
        positions(h, cfg.spatial_interpolation_scale),
    );
    // [T, dt], [W, dx], [H, dy] -> [T, H, W, dt + dx + dy]: time, then x, then y.
    let video = Tensor::cat(
        &[
            et.view([frames, 1, 1, temporal_dim])
                .expand([frames, h, w, temporal_dim], false),
            ex.view([1, 1, w, spatial_dim / 2])
                .expand([frames, h, w, spatial_dim / 2], false),
            ey.view([1, h, 1, spatial_dim / 2])
                .expand([frames, h, w, spatial_dim / 2], false),
        ],
        -1,
    )
    .view([frames * h * w, d]); // [N, D]
    let text = Tensor::zeros([cfg.max_text_seq_length, d], (Kind::Float, device));
    Tensor::cat(&[text, video], 0).unsqueeze(0) // [1, L + N, D]
}

/// The rotary embedding of the video tokens: `cos`, `sin` `[N, head_dim]`.
#[derive(Debug)]
pub struct Rotary {
    /// `[N, head_dim]`.
    pub cos: Tensor,
    /// `[N, head_dim]`.
    pub sin: Tensor,
}

impl Rotary {
    /// From precomputed tables (e.g. a parity fixture's).
    pub fn new(cos: Tensor, sin: Tensor) -> Result<Self> {
        if cos.size() != sin.size() || cos.dim() != 2 {
            return Err(WorldModelError::input(
                "rotary embedding",
                format!(
                    "cos {:?} / sin {:?}: expected two [N, head_dim] tables",
                    cos.size(),
                    sin.size()
                ),
            ));
        }
        Ok(Self { cos, sin })
    }

    /// Tokens covered.
    pub fn tokens(&self) -> i64 {
        self.cos.size()[0]
    }

    /// The same tables (shared storage).
    pub fn shallow_clone(&self) -> Self {
        Self {
            cos: self.cos.shallow_clone(),
            sin: self.sin.shallow_clone(),
        }
    }

    /// On another device / dtype.
    pub fn to(&self, device: Device, kind: Kind) -> Self {
        Self {
            cos: self.cos.to_device(device).to_kind(kind),
            sin: self.sin.to_device(device).to_kind(kind),
        }
    }
}

/// diffusers' `get_resize_crop_region_for_grid`: the region of the base grid
/// (`base_w x base_h`) that a `grid_h x grid_w` grid covers after an
/// aspect-preserving resize and centre crop: `((top, left), (bottom, right))`.
pub fn resize_crop_region(
    grid_h: i64,
    grid_w: i64,
    base_w: i64,
    base_h: i64,
) -> ((i64, i64), (i64, i64)) {
    let (tw, th) = (base_w as f64, base_h as f64);
    let (h, w) = (grid_h as f64, grid_w as f64);
    let (rh, rw) = if h / w > th / tw {
        (base_h, (th / h * w).round_ties_even() as i64)
    } else {
        ((tw / w * h).round_ties_even() as i64, base_w)
    };
    let top = ((th - rh as f64) / 2.0).round_ties_even() as i64;
    let left = ((tw - rw as f64) / 2.0).round_ties_even() as i64;
    ((top, left), (top + rh, left + rw))
}

/// 1-D rotary table `[len(pos), dim]` (f32, each frequency repeated twice).
fn rope_1d(dim: i64, pos: &Tensor, theta: f64) -> (Tensor, Tensor) {
    let device = pos.device();
    let exponents = Tensor::arange_start_step(0, dim, 2, (Kind::Float, device)) / dim as f64;
    let freqs = Tensor::pow_scalar(theta, &exponents).reciprocal(); // [dim / 2]
    let angles = pos.outer(&freqs); // [S, dim / 2]
    (
        angles.cos().repeat_interleave_self_int(2, 1, None::<i64>),
        angles.sin().repeat_interleave_self_int(2, 1, None::<i64>),
    )
}

/// The rotary embedding the CogVideoX image-to-video pipeline computes for
/// `frames` latent frames of `latent_h x latent_w` latents (CogVideoX 1.0:
/// `linspace` grids over the resize-crop region of the base grid; 1.5: the
/// `slice` grids), or `None` for models without RoPE.
pub fn rotary_for_latents(
    cfg: &TransformerConfig,
    frames: i64,
    latent_h: i64,
    latent_w: i64,
    device: Device,
) -> Result<Option<Rotary>> {
    if !cfg.use_rotary_positional_embeddings {
        return Ok(None);
    }
    let p = cfg.patch_size;
    if latent_h % p != 0 || latent_w % p != 0 {
        return Err(WorldModelError::input(
            "latents",
            format!(
                "{latent_h}x{latent_w}: height and width must be multiples of the patch size {p}"
            ),
        ));
    }
    let (gh, gw) = (latent_h / p, latent_w / p);
    let (base_w, base_h) = (cfg.sample_width / p, cfg.sample_height / p);
    let f32s = (Kind::Float, device);
    let (grid_t, grid_h, grid_w) = match cfg.patch_size_t {
        None => {
            let ((top, left), (bottom, right)) = resize_crop_region(gh, gw, base_w, base_h);
            let lin = |start: i64, stop: i64, n: i64| {
                let end = (stop * (n - 1)) as f64 / n as f64;
                Tensor::linspace(start as f64, end, n, f32s)
            };
            let t_end = (frames * (frames - 1)) as f64 / frames as f64;
            (
                Tensor::linspace(0.0, t_end, frames, f32s),
                lin(top, bottom, gh),
                lin(left, right, gw),
            )
        }
        Some(pt) => {
            let base_frames = (frames + pt - 1) / pt;
            (
                Tensor::arange(base_frames, f32s),
                Tensor::arange(base_h, f32s).narrow(0, 0, gh.min(base_h)),
                Tensor::arange(base_w, f32s).narrow(0, 0, gw.min(base_w)),
            )
        }
    };
    let hd = cfg.attention_head_dim;
    let (dim_t, dim_h) = (hd / 4, hd / 8 * 3);
    let (tc, ts) = rope_1d(dim_t, &grid_t, 10000.0);
    let (hc, hs) = rope_1d(dim_h, &grid_h, 10000.0);
    let (wc, ws) = rope_1d(dim_h, &grid_w, 10000.0);
    let (nt, nh, nw) = (tc.size()[0], hc.size()[0], wc.size()[0]);
    let combine = |t: &Tensor, h: &Tensor, w: &Tensor| {
        let t = t.view([nt, 1, 1, dim_t]).expand([nt, nh, nw, dim_t], false);
        let h = h.view([1, nh, 1, dim_h]).expand([nt, nh, nw, dim_h], false);
        let w = w.view([1, 1, nw, dim_h]).expand([nt, nh, nw, dim_h], false);
        Tensor::cat(&[t, h, w], -1).reshape([nt * nh * nw, -1]) // [T*h*w, head_dim]
    };
    Ok(Some(Rotary {
        cos: combine(&tc, &hc, &wc),
        sin: combine(&ts, &hs, &ws),
    }))
}

/// Applies the rotary embedding to `x` `[B, heads, N, head_dim]` (channel
/// pairs `(2i, 2i + 1)` rotate together).
pub fn apply_rotary(x: &Tensor, rot: &Rotary) -> Tensor {
    let size = x.size();
    let d = size[3];
    // [B, H, N, D] -> [B, H, N, D/2, 2]
    let pairs = x.reshape([size[0], size[1], size[2], d / 2, 2]);
    let (re, im) = (pairs.select(-1, 0), pairs.select(-1, 1));
    let rotated = Tensor::stack(&[-im, re], -1).reshape(size.as_slice()); // [B, H, N, D]
    let kind = x.kind();
    (x.to_kind(Kind::Float) * &rot.cos + rotated.to_kind(Kind::Float) * &rot.sin).to_kind(kind)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn crop_region_matches_hand_computation() {
        // Same aspect as the base: the whole grid.
        assert_eq!(resize_crop_region(30, 45, 45, 30), ((0, 0), (30, 45)));
        // Slightly taller than the base: height-limited, width round(30 / 15 * 22) = 44,
        // left offset round(0.5) = 0 (ties to even, as Python).
        assert_eq!(resize_crop_region(15, 22, 45, 30), ((0, 0), (30, 44)));
        // Square grid into 45x30: height-limited, width 30 centred (left 7.5 -> 8).
        assert_eq!(resize_crop_region(10, 10, 45, 30), ((0, 8), (30, 38)));
    }

    /// Reference: the 3D sin-cos embedding `[T * H * W, dim]` (tokens frame-major, then
    /// rows, then columns): a quarter of the channels for time, then three
    /// quarters for space (half from x, half from y), as diffusers'
    /// `get_3d_sincos_pos_embed` (positions in f32, embedding in f64).
    fn sincos_3d(
        dim: usize,
        grid_w: usize,
        grid_h: usize,
        frames: usize,
        spatial_scale: f64,
        temporal_scale: f64,
    ) -> Vec<Vec<f64>> {
        let spatial_dim = 3 * dim / 4;
        let temporal_dim = dim / 4;
        // Positions are f32 in diffusers (arange / scale), promoted to f64.
        let xs: Vec<f64> = (0..grid_w)
            .map(|x| f64::from(x as f32 / spatial_scale as f32))
            .collect();
        let ys: Vec<f64> = (0..grid_h)
            .map(|y| f64::from(y as f32 / spatial_scale as f32))
            .collect();
        let ts: Vec<f64> = (0..frames)
            .map(|t| f64::from(t as f32 / temporal_scale as f32))
            .collect();
        let ex = sincos_1d(spatial_dim / 2, &xs);
        let ey = sincos_1d(spatial_dim / 2, &ys);
        let et = sincos_1d(temporal_dim, &ts);
        let mut out = Vec::with_capacity(frames * grid_h * grid_w);
        for t in &et {
            for y in &ey {
                for x in &ex {
                    let mut row = Vec::with_capacity(dim);
                    row.extend_from_slice(t);
                    row.extend_from_slice(x);
                    row.extend_from_slice(y);
                    out.push(row);
                }
            }
        }
        out
    }

    #[test]
    fn joint_sincos_is_the_reference_embedding_after_the_text_zeros() {
        let mut cfg = TransformerConfig::cogvideox_2b();
        cfg.num_attention_heads = 2;
        cfg.attention_head_dim = 8; // inner dim 16
        cfg.max_text_seq_length = 3;
        cfg.spatial_interpolation_scale = 1.875;
        cfg.temporal_interpolation_scale = 1.0;
        let got = joint_sincos(&cfg, 2, 3, 4, Device::Cpu);
        assert_eq!(got.size(), [1, 3 + 2 * 3 * 4, 16]);
        let want = sincos_3d(16, 4, 3, 2, 1.875, 1.0);
        let text = got.narrow(1, 0, 3);
        assert_eq!(text.abs().max().double_value(&[]), 0.0);
        for (i, row) in want.iter().enumerate() {
            let row32: Vec<f32> = row.iter().map(|&v| v as f32).collect();
            let got_row = Vec::<f32>::try_from(got.get(0).get(3 + i as i64)).unwrap();
            assert_eq!(got_row, row32, "token {i}");
        }
    }

    #[test]
    fn sincos_layout() {
        let e = sincos_3d(16, 3, 2, 2, 1.0, 1.0);
        assert_eq!(e.len(), 12);
        // Token 0: t = x = y = 0: sin parts 0, cos parts 1.
        // Temporal block (4 channels): [sin, sin, cos, cos].
        assert_eq!(&e[0][..4], &[0.0, 0.0, 1.0, 1.0]);
        // Token 1 is x = 1 (columns vary fastest): the x block changes.
        let x_block = 4..10;
        assert_ne!(&e[1][x_block.clone()], &e[0][x_block]);
        assert_eq!(&e[1][10..16], &e[0][10..16]);
        // Token 6 is t = 1: only the temporal block differs from token 0.
        assert_ne!(&e[6][..4], &e[0][..4]);
        assert_eq!(&e[6][4..], &e[0][4..]);
    }
}
