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
//! [`BatchReplay::Stepwise`] checkpoints inside a batch as well: its decoder
//! units (`conv_in`, each resnet, each upsampler, the output) run once more
//! without autograd keeping only their inputs, then one at a time under
//! autograd from the last, so that one unit's activations are held at a
//! time, for a third decoder pass. Tiled, it also keeps no tile's caches
//! between the decode and the backward: each tile's are computed again (one
//! more pass without autograd over all its batches but the last) just
//! before its replay, so that one tile's caches are held at a time (at 25
//! frames 720x480 all tiles' caches are several GB).

use super::tiling::tiled;
use super::{frame_batches, AutoencoderKLCogVideoX, DecoderCache};
use crate::error::{Result, WorldModelError};
use tch::{Kind, Tensor};

/// How [`AutoencoderKLCogVideoX::decode_backward`] replays one frame batch
/// (of one tile) under autograd; chosen when the decode is recorded
/// ([`AutoencoderKLCogVideoX::decode_recorded`]), since it decides what the
/// record keeps.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum BatchReplay {
    /// The whole decoder at once: every activation of the batch kept until
    /// its backward pass.
    #[default]
    Whole,
    /// Unit by unit (`conv_in`, each resnet, each upsampler, the output):
    /// one more decoder pass keeps only each unit's input, then each unit is
    /// replayed under autograd alone, from the last. Tiled, each tile's conv
    /// caches are computed again just before its replay instead of being
    /// kept for every tile (one more pass without autograd). For the
    /// full-size flow loss, where one batch's activations are themselves too
    /// large.
    Stepwise,
}

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
    /// How the batches are replayed.
    replay: BatchReplay,
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
    /// The cache each batch started from (`None` for the first); `None` when
    /// not kept (computed again by the backward).
    caches: Option<Vec<Option<DecoderCache>>>,
    /// The pixel frames each batch produced.
    frames: Vec<i64>,
}

impl DecodeRecord {
    /// The bytes the record's tensors hold: the recorded latents, the conv
    /// caches each batch started from and, tiled, each tile's decoded output.
    pub fn bytes(&self) -> u64 {
        fn of(t: &Tensor) -> u64 {
            (t.numel() * t.kind().elt_size_in_bytes()) as u64
        }
        fn batches(r: &BatchRecord) -> u64 {
            let caches: u64 = r
                .caches
                .iter()
                .flatten()
                .flatten()
                .flat_map(DecoderCache::tensors)
                .map(of)
                .sum();
            of(&r.z) + caches
        }
        match &self.form {
            Form::Whole(r) => batches(r),
            Form::Tiled { tiles, .. } => tiles
                .iter()
                .map(|t| of(&t.output) + batches(&t.record))
                .sum(),
        }
    }
}

impl AutoencoderKLCogVideoX {
    /// [`Self::decode`] (the whole batch at once; tiled when tiling is on and
    /// the latents exceed a tile) that also returns the record
    /// [`Self::decode_backward`] needs to replay the batches by `replay`.
    pub fn decode_recorded(
        &self,
        latents: &Tensor,
        replay: BatchReplay,
    ) -> Result<(Tensor, DecodeRecord)> {
        self.check_latents(latents)?;
        let z = tch::no_grad(|| self.to_model(&latents.detach()));
        let s = z.size();
        let (video, form) = if self.tiles_latents(s[3], s[4]) {
            let mut tiles = Vec::new();
            // One tile's caches at a time in the stepwise backward.
            let keep_caches = replay == BatchReplay::Whole;
            // Autograd on for the blending only (each tile's decode runs without).
            let video = tch::with_grad(|| {
                tiled(&z, &self.decode_geometry(), |tile, origin| {
                    let (out, record) = self.decode_batches(tile, keep_caches)?;
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
            let (video, record) = self.decode_batches(&z, true)?;
            (video, Form::Whole(record))
        };
        let record = DecodeRecord {
            kind: latents.kind(),
            latent_shape: s,
            video_shape: video.size(),
            form,
            replay,
        };
        Ok((video, record))
    }

    /// The batches of one (untiled) decode, without autograd, recorded (the
    /// caches each batch started from only when `keep_caches`).
    fn decode_batches(&self, z: &Tensor, keep_caches: bool) -> Result<(Tensor, BatchRecord)> {
        let batches = frame_batches(z.size()[2], self.num_latent_frames_batch_size);
        let mut parts = Vec::with_capacity(batches.len());
        let caches = self.batch_caches(z, &batches, Some(&mut |h| parts.push(h)))?;
        let frames = parts.iter().map(|p| p.size()[2]).collect();
        let video = Tensor::f_cat(&parts, 2)?;
        let record = BatchRecord {
            z: z.shallow_clone(),
            batches,
            caches: keep_caches.then_some(caches),
            frames,
        };
        Ok((video, record))
    }

    /// Decodes `z`'s frame `batches` in order without autograd; returns the
    /// cache each batch started from (`None` for the first). With `output`,
    /// each batch's decoded frames are handed to it; without, the last batch
    /// is not decoded (nothing it writes is needed then).
    fn batch_caches(
        &self,
        z: &Tensor,
        batches: &[(i64, i64)],
        mut output: Option<&mut dyn FnMut(Tensor)>,
    ) -> Result<Vec<Option<DecoderCache>>> {
        let _guard = tch::no_grad_guard();
        let (mut cache, mut caches) = (None, Vec::with_capacity(batches.len()));
        for (i, &(start, end)) in batches.iter().enumerate() {
            if output.is_none() && i + 1 == batches.len() {
                caches.push(cache.take());
                break;
            }
            let (h, c) = self.decode_batch(&z.narrow(2, start, end - start), cache.as_ref())?;
            caches.push(cache.replace(c));
            if let Some(out) = output.as_mut() {
                out(h);
            }
        }
        Ok(caches)
    }

    /// The gradient with respect to the recorded latents of
    /// `sum(decode(latents) * grad_video)`, batch by batch from the last, as
    /// the record's [`BatchReplay`] says (see the module docs). `grad_video`
    /// has the decoded video's shape; the result the latents' shape and
    /// dtype. The decoder's own parameters get no gradient.
    pub fn decode_backward(&self, record: &DecodeRecord, grad_video: &Tensor) -> Result<Tensor> {
        let replay = record.replay;
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
            Form::Whole(r) => self.batches_backward(r, grad_video, replay)?,
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
                    let gz = self.batches_backward(&tile.record, &g, replay)?;
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
    fn batches_backward(
        &self,
        record: &BatchRecord,
        grad_video: &Tensor,
        replay: BatchReplay,
    ) -> Result<Tensor> {
        let mut offsets = Vec::with_capacity(record.frames.len());
        let mut at = 0;
        for f in &record.frames {
            offsets.push(at);
            at += f;
        }
        // The caches each batch started from: recorded, or computed again now
        // (and let go batch by batch).
        let mut computed = match &record.caches {
            Some(_) => Vec::new(),
            None => self.batch_caches(&record.z, &record.batches, None)?,
        };
        let n = record.batches.len();
        let mut grads: Vec<Tensor> = Vec::with_capacity(n);
        // d objective / d (the cache batch j + 1 started from), in `tensors()` order.
        let mut grad_cache: Option<Vec<Tensor>> = None;
        for j in (0..n).rev() {
            let (start, end) = record.batches[j];
            let z = record.z.narrow(2, start, end - start);
            let g = grad_video.narrow(2, offsets[j], record.frames[j]);
            let popped;
            let cache_in = match &record.caches {
                Some(c) => c[j].as_ref(),
                None => {
                    popped = computed.pop().flatten();
                    popped.as_ref()
                }
            };
            let (g_z, g_cache) = match replay {
                BatchReplay::Whole => {
                    self.batch_backward_whole(&z, cache_in, &g, grad_cache.as_deref())
                }
                BatchReplay::Stepwise => {
                    self.batch_backward_stepwise(&z, cache_in, &g, grad_cache.as_deref())
                }
            }?;
            grads.push(g_z);
            grad_cache = g_cache;
        }
        grads.reverse();
        Ok(Tensor::f_cat(&grads, 2)?)
    }

    /// One batch under autograd: the gradients of `sum(out * g_out) +
    /// sum(cache_out * g_cache_out)` with respect to the batch's latents and
    /// (when it continued one) its starting cache, in `tensors()` order.
    fn batch_backward_whole(
        &self,
        z: &Tensor,
        cache_in: Option<&DecoderCache>,
        g_out: &Tensor,
        g_cache_out: Option<&[Tensor]>,
    ) -> Result<(Tensor, Option<Vec<Tensor>>)> {
        tch::with_grad(|| {
            let z = z.detach().set_requires_grad(true);
            let cache_in = cache_in.map(|c| c.map(&mut |t| t.detach().set_requires_grad(true)));
            let (out, cache_out) = self.decode_batch(&z, cache_in.as_ref())?;
            let mut objective = (&out * g_out.to_kind(out.kind())).sum(Kind::Float);
            if let Some(gc) = g_cache_out {
                if let Some(c) = cache_objective(&cache_out.tensors(), gc)? {
                    objective += c;
                }
            }
            let mut inputs = vec![z];
            if let Some(c) = &cache_in {
                inputs.extend(c.tensors().into_iter().map(Tensor::shallow_clone));
            }
            let mut all = Tensor::f_run_backward(&[objective], &inputs, false, false)?;
            let g_cache = cache_in.is_some().then(|| all.split_off(1));
            Ok((all.remove(0), g_cache))
        })
    }

    /// [`Self::batch_backward_whole`] checkpointed inside the batch: the
    /// decoder's units (`conv_in`, each resnet, each upsampler, the output)
    /// run once without autograd, keeping only each unit's input; then each
    /// unit is run again under autograd from the last to the first and its
    /// gradient pushed through it alone. The same gradient (up to float
    /// rounding), holding one unit's activations at a time instead of the
    /// whole decoder's, for one more decoder pass.
    fn batch_backward_stepwise(
        &self,
        z: &Tensor,
        cache_in: Option<&DecoderCache>,
        g_out: &Tensor,
        g_cache_out: Option<&[Tensor]>,
    ) -> Result<(Tensor, Option<Vec<Tensor>>)> {
        let decoder = &self.decoder;
        let n = decoder.unit_count();
        // zq: the decoder's input latent (after `post_quant_conv`), which every
        // spatial norm reads; inputs[k]: unit k's input (inputs[0] is zq).
        let (zq, mut inputs) = tch::no_grad(|| -> Result<_> {
            let zq = self.post_quant(z)?;
            let mut inputs = Vec::with_capacity(n);
            let mut h = zq.shallow_clone();
            for k in 0..n {
                let (out, _) =
                    decoder.unit_forward(k, &h, &zq, cache_in.and_then(|c| c.unit(k)))?;
                inputs.push(std::mem::replace(&mut h, out));
            }
            Ok((zq, inputs))
        })?;
        // The written caches' gradients are taken from the end, unit by unit.
        let mut g_cache_end = g_cache_out.map_or(0, <[Tensor]>::len);
        let mut g_h = g_out.shallow_clone();
        let mut g_zq = Tensor::zeros_like(&zq).to_kind(Kind::Float);
        let mut g_cache_units: Vec<Vec<Tensor>> = Vec::with_capacity(n);
        for k in (0..n).rev() {
            // Unit k's input, let go once it is replayed.
            let input = inputs.pop().ok_or_else(|| {
                WorldModelError::input("decode record", format!("unit {k}: no input recorded"))
            })?;
            let (g_input, g_zq_k, g_cache_k) = tch::with_grad(|| -> Result<_> {
                let h = input.detach().set_requires_grad(true);
                let zq_leaf = zq.detach().set_requires_grad(true);
                let unit_in = cache_in
                    .and_then(|c| c.unit(k))
                    .map(|u| u.map(&mut |t| t.detach().set_requires_grad(true)));
                let (out, written) = decoder.unit_forward(k, &h, &zq_leaf, unit_in.as_ref())?;
                let mut objective = (&out * g_h.to_kind(out.kind())).sum(Kind::Float);
                if let Some(gc) = g_cache_out {
                    let written = written.tensors();
                    if written.len() > g_cache_end {
                        return Err(cache_mismatch(written.len(), g_cache_end));
                    }
                    let start = g_cache_end - written.len();
                    if let Some(c) = cache_objective(&written, &gc[start..g_cache_end])? {
                        objective += c;
                    }
                    g_cache_end = start;
                }
                let mut leaves = vec![h, zq_leaf];
                if let Some(u) = &unit_in {
                    leaves.extend(u.tensors().into_iter().map(Tensor::shallow_clone));
                }
                let mut all = Tensor::f_run_backward(&[objective], &leaves, false, false)?;
                let g_cache = all.split_off(2);
                let g_zq_k = all.pop().unwrap_or_default();
                let g_input = all.pop().unwrap_or_default();
                Ok((g_input, g_zq_k, g_cache))
            })?;
            if g_zq_k.defined() {
                g_zq += g_zq_k.to_kind(Kind::Float);
            }
            g_cache_units.push(g_cache_k);
            g_h = g_input;
        }
        if g_cache_end != 0 {
            return Err(cache_mismatch(
                g_cache_out.map_or(0, <[Tensor]>::len) - g_cache_end,
                g_cache_out.map_or(0, <[Tensor]>::len),
            ));
        }
        // Unit 0's input is zq itself.
        if g_h.defined() {
            g_zq += g_h.to_kind(Kind::Float);
        }
        // Through `post_quant_conv` (when there is one) to the latents.
        let g_z = match &self.post_quant_conv {
            None => g_zq.to_kind(z.kind()),
            Some(_) => tch::with_grad(|| -> Result<Tensor> {
                let leaf = z.detach().set_requires_grad(true);
                let out = self.post_quant(&leaf)?;
                let objective = (&out * g_zq.to_kind(out.kind())).sum(Kind::Float);
                Ok(Tensor::f_run_backward(&[objective], &[&leaf], false, false)?.remove(0))
            })?,
        };
        let g_cache = cache_in.is_some().then(|| {
            g_cache_units.reverse();
            g_cache_units.into_iter().flatten().collect()
        });
        Ok((g_z, g_cache))
    }

    /// `post_quant_conv` when the VAE has one.
    fn post_quant(&self, z: &Tensor) -> Result<Tensor> {
        Ok(match &self.post_quant_conv {
            Some(conv) => conv.forward(z)?,
            None => z.shallow_clone(),
        })
    }

    /// `post_quant_conv`, then the decoder on one latent-frame batch.
    pub(super) fn decode_batch(
        &self,
        z: &Tensor,
        cache: Option<&DecoderCache>,
    ) -> Result<(Tensor, DecoderCache)> {
        self.decoder.forward(&self.post_quant(z)?, cache)
    }
}

/// `sum(written_i * g_i)` over a batch's written caches and their gradients
/// (an undefined gradient: the cache was not read); `None` when none is defined.
fn cache_objective(written: &[&Tensor], grads: &[Tensor]) -> Result<Option<Tensor>> {
    if written.len() != grads.len() {
        return Err(cache_mismatch(written.len(), grads.len()));
    }
    let mut sum: Option<Tensor> = None;
    for (t, g) in written.iter().zip(grads) {
        if g.defined() {
            let term = (*t * g.to_kind(t.kind())).sum(Kind::Float);
            sum = Some(match sum {
                Some(s) => s + term,
                None => term,
            });
        }
    }
    Ok(sum)
}

fn cache_mismatch(written: usize, read: usize) -> WorldModelError {
    WorldModelError::input(
        "decode record",
        format!("the batch wrote {written} cache tensors, the next batch read {read}"),
    )
}
