//! A decode whose gradient is pushed back one frame batch at a time, for the
//! flow loss at full size: autograd through a whole 25-frame 720x480 decode
//! keeps every activation of the decoder (it did not fit a 140 GB GPU next to
//! the 5B transformer), while the decoder already runs over latent-frame
//! batches of 2 linked only by its causal conv caches.
//!
//! [`AutoencoderKLCogVideoX::decode_recorded`] decodes without autograd and
//! keeps the cache each batch started from; [`AutoencoderKLCogVideoX::decode_backward`]
//! then replays the batches from the last to the first, each with autograd,
//! and carries the caches' gradients back to the batch that wrote them. The
//! result is the exact gradient of `sum(decode(z) * grad_video)` with respect
//! to `z` (the same as autograd through [`AutoencoderKLCogVideoX::decode_with_grad`],
//! up to float rounding), holding one batch's activations at a time, at the
//! price of a second decoder pass. With tiling enabled (as `predict` runs the
//! VAE above 256x256), each spatial tile keeps its own record and the
//! blending's gradient comes from autograd: then one tile's batch at a time.

use super::tiling::tiled;
use super::{frame_batches, AutoencoderKLCogVideoX, DecoderCache};
use crate::error::{Result, WorldModelError};
use tch::{Kind, Tensor};

/// What [`AutoencoderKLCogVideoX::decode_recorded`] keeps for
/// [`AutoencoderKLCogVideoX::decode_backward`].
#[derive(Debug)]
pub struct DecodeRecord {
    /// The dtype of the caller's latents (the gradient's).
    kind: Kind,
    /// The latents' shape.
    latent_shape: Vec<i64>,
    /// The decoded video's shape.
    video_shape: Vec<i64>,
    /// Untiled or tiled.
    form: Form,
}

#[derive(Debug)]
enum Form {
    /// The whole frame at once.
    Whole(BatchRecord),
    /// Spatial tiles: the blended video (with autograd back to each tile's
    /// output, a leaf) and each tile's record.
    Tiled {
        video: Tensor,
        tiles: Vec<TileRecord>,
    },
}

/// One spatial tile: its latent origin, its output leaf and its record.
#[derive(Debug)]
struct TileRecord {
    origin: (i64, i64),
    output: Tensor,
    record: BatchRecord,
}

/// One decode over latent-frame batches.
#[derive(Debug)]
struct BatchRecord {
    /// The latents in the model's dtype, `[B, C, t, h, w]`.
    z: Tensor,
    /// The latent-frame batches, `(start, end)`.
    batches: Vec<(i64, i64)>,
    /// The cache each batch started from (`None` for the first).
    caches: Vec<Option<DecoderCache>>,
    /// The pixel frames each batch produced.
    frames: Vec<i64>,
}

impl AutoencoderKLCogVideoX {
    /// [`Self::decode`] (the whole batch at once; tiled when tiling is on and
    /// the latents exceed a tile) that also returns the record
    /// [`Self::decode_backward`] needs.
    pub fn decode_recorded(&self, latents: &Tensor) -> Result<(Tensor, DecodeRecord)> {
        self.check_latents(latents)?;
        let z = tch::no_grad(|| self.to_model(&latents.detach()));
        let s = z.size();
        let (video, form) = if self.tiles_latents(s[3], s[4]) {
            let mut tiles = Vec::new();
            // Autograd on for the blending only (each tile's decode runs without).
            let video = tch::with_grad(|| {
                tiled(&z, &self.decode_geometry(), |tile, origin| {
                    let (out, record) = self.decode_batches(tile)?;
                    let output = out.set_requires_grad(true);
                    tiles.push(TileRecord {
                        origin,
                        output: output.shallow_clone(),
                        record,
                    });
                    Ok(output)
                })
            })?;
            (video.detach(), Form::Tiled { video, tiles })
        } else {
            let (video, record) = self.decode_batches(&z)?;
            (video, Form::Whole(record))
        };
        let record = DecodeRecord {
            kind: latents.kind(),
            latent_shape: s,
            video_shape: video.size(),
            form,
        };
        Ok((video, record))
    }

    /// The batches of one (untiled) decode, without autograd, recorded.
    fn decode_batches(&self, z: &Tensor) -> Result<(Tensor, BatchRecord)> {
        let _guard = tch::no_grad_guard();
        let batches = frame_batches(z.size()[2], self.num_latent_frames_batch_size);
        let (mut cache, mut caches, mut parts) = (None, Vec::new(), Vec::new());
        for &(start, end) in &batches {
            let (h, c) = self.decode_batch(&z.narrow(2, start, end - start), cache.as_ref())?;
            caches.push(cache.replace(c));
            parts.push(h);
        }
        let frames = parts.iter().map(|p| p.size()[2]).collect();
        let video = Tensor::f_cat(&parts, 2)?;
        let record = BatchRecord {
            z: z.shallow_clone(),
            batches,
            caches,
            frames,
        };
        Ok((video, record))
    }

    /// The gradient with respect to the recorded latents of
    /// `sum(decode(latents) * grad_video)`, batch by batch from the last
    /// (see the module docs). `grad_video` has the decoded video's shape; the
    /// result the latents' shape and dtype. The decoder's own parameters get
    /// no gradient.
    pub fn decode_backward(&self, record: &DecodeRecord, grad_video: &Tensor) -> Result<Tensor> {
        if grad_video.size() != record.video_shape {
            return Err(WorldModelError::input(
                "grad_video",
                format!(
                    "shape {:?}: expected the decoded video's {:?}",
                    grad_video.size(),
                    record.video_shape
                ),
            ));
        }
        let grad = match &record.form {
            Form::Whole(r) => self.batches_backward(r, grad_video)?,
            Form::Tiled { video, tiles } => {
                let outputs: Vec<&Tensor> = tiles.iter().map(|t| &t.output).collect();
                let objective = (video * grad_video.to_kind(video.kind())).sum(Kind::Float);
                // The blending's adjoint: each tile output's share of the gradient.
                let tile_grads =
                    tch::with_grad(|| Tensor::f_run_backward(&[objective], &outputs, true, false))?;
                let grad = Tensor::zeros(
                    record.latent_shape.as_slice(),
                    (Kind::Float, grad_video.device()),
                );
                for (tile, g) in tiles.iter().zip(tile_grads) {
                    if !g.defined() {
                        continue; // a tile the crop dropped entirely
                    }
                    let gz = self.batches_backward(&tile.record, &g)?;
                    let s = gz.size();
                    let (i, j) = tile.origin;
                    let mut view = grad.narrow(3, i, s[3]).narrow(4, j, s[4]);
                    view += gz.to_kind(Kind::Float);
                }
                grad
            }
        };
        Ok(grad.to_kind(record.kind))
    }

    /// [`Self::decode_backward`] of one untiled decode: the gradient with
    /// respect to its latents (model dtype).
    fn batches_backward(&self, record: &BatchRecord, grad_video: &Tensor) -> Result<Tensor> {
        let mut offsets = Vec::with_capacity(record.frames.len());
        let mut at = 0;
        for f in &record.frames {
            offsets.push(at);
            at += f;
        }
        let n = record.batches.len();
        let mut grads: Vec<Tensor> = Vec::with_capacity(n);
        // d objective / d (the cache batch j + 1 started from), in `tensors()` order.
        let mut grad_cache: Option<Vec<Tensor>> = None;
        for j in (0..n).rev() {
            let (start, end) = record.batches[j];
            let (g_z, g_cache) = tch::with_grad(|| -> Result<(Tensor, Option<Vec<Tensor>>)> {
                let z = record
                    .z
                    .narrow(2, start, end - start)
                    .detach()
                    .set_requires_grad(true);
                let cache_in = record.caches[j]
                    .as_ref()
                    .map(|c| c.map(&mut |t| t.detach().set_requires_grad(true)));
                let (out, cache_out) = self.decode_batch(&z, cache_in.as_ref())?;
                let g = grad_video.narrow(2, offsets[j], record.frames[j]);
                let mut objective = (&out * g.to_kind(out.kind())).sum(Kind::Float);
                if let Some(gc) = &grad_cache {
                    let written = cache_out.tensors();
                    if written.len() != gc.len() {
                        return Err(WorldModelError::input(
                            "decode record",
                            format!(
                                "batch {j} wrote {} cache tensors, the next batch read {}",
                                written.len(),
                                gc.len()
                            ),
                        ));
                    }
                    for (t, g) in written.into_iter().zip(gc) {
                        if g.defined() {
                            objective += (t * g.to_kind(t.kind())).sum(Kind::Float);
                        }
                    }
                }
                let mut inputs = vec![z];
                if let Some(c) = &cache_in {
                    inputs.extend(c.tensors().into_iter().map(Tensor::shallow_clone));
                }
                let mut all = Tensor::f_run_backward(&[objective], &inputs, false, false)?;
                let g_cache = cache_in.is_some().then(|| all.split_off(1));
                Ok((all.remove(0), g_cache))
            })?;
            grads.push(g_z);
            grad_cache = g_cache;
        }
        grads.reverse();
        Ok(Tensor::f_cat(&grads, 2)?)
    }

    /// `post_quant_conv`, then the decoder on one latent-frame batch.
    pub(super) fn decode_batch(
        &self,
        z: &Tensor,
        cache: Option<&DecoderCache>,
    ) -> Result<(Tensor, DecoderCache)> {
        let z = match &self.post_quant_conv {
            Some(conv) => conv.forward(z)?,
            None => z.shallow_clone(),
        };
        self.decoder.forward(&z, cache)
    }
}
