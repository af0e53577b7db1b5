//! Drawing clips: the epoch's slots, each step's episodes and clip starts
//! (deterministic in `(seed, step)`), and the batch tensors.

use super::*;

impl ClipDataset {
    /// Steps per epoch at `batch_size`: `clips_per_video` clips of every video.
    pub fn steps_per_epoch(&self, batch_size: usize) -> usize {
        (self.episodes.len() * self.clips_per_video)
            .div_ceil(batch_size.max(1))
            .max(1)
    }

    /// The episode of every clip slot of `epoch`. One source: each episode
    /// `clips_per_video` times, shuffled. Several: each slot draws a source
    /// by weight, then the next episode of that source's own shuffled cycle
    /// (so every source is covered evenly within its share).
    pub fn epoch_slots(&self, seed: u64, epoch: u64, slots: usize) -> Vec<usize> {
        let mut rng = rng_for(seed, epoch, 1);
        let mut cycles: Vec<Vec<usize>> = vec![Vec::new(); self.sources.len()];
        for (i, e) in self.episodes.iter().enumerate() {
            for _ in 0..self.clips_per_video {
                cycles[e.source].push(i);
            }
        }
        for c in &mut cycles {
            c.shuffle(&mut rng);
        }
        if self.sources.len() == 1 {
            let c = &cycles[0];
            return (0..slots).map(|k| c[k % c.len()]).collect();
        }
        let total: f64 = self.sources.iter().map(|s| s.1).sum();
        let mut next = vec![0usize; cycles.len()];
        (0..slots)
            .map(|_| {
                let mut u = rng.gen::<f64>() * total;
                let mut s = 0;
                while s + 1 < self.sources.len() && (u >= self.sources[s].1 || cycles[s].is_empty())
                {
                    u -= self.sources[s].1;
                    s += 1;
                }
                let c = &cycles[s];
                let e = c[next[s] % c.len()];
                next[s] += 1;
                e
            })
            .collect()
    }

    /// The episodes of step `step`: a permutation per epoch from `(seed, epoch)`,
    /// consecutive `batch_size` slices of it (wrapping).
    pub fn batch_episodes(&self, seed: u64, step: usize, batch_size: usize) -> Vec<usize> {
        let spe = self.steps_per_epoch(batch_size);
        let (epoch, within) = (step / spe, step % spe);
        let order = self.epoch_slots(seed, epoch as u64, spe * batch_size);
        (0..batch_size)
            .map(|j| order[within * batch_size + j])
            .collect()
    }

    /// The batch of step `step` on `device`: episodes from [`Self::batch_episodes`],
    /// clip starts from `(seed, step)`.
    pub fn batch(
        &self,
        seed: u64,
        step: usize,
        batch_size: usize,
        device: Device,
    ) -> Result<Batch> {
        self.clips(&self.batch_clips(seed, step, batch_size), device)
    }

    /// The clips `(episode, start frame)` of step `step`'s batch.
    pub fn batch_clips(&self, seed: u64, step: usize, batch_size: usize) -> Vec<(usize, usize)> {
        let eps = self.batch_episodes(seed, step, batch_size);
        let mut rng = rng_for(seed, step as u64, 2);
        eps.iter()
            .map(|&i| {
                (
                    i,
                    rng.gen_range(0..=self.episodes[i].frames - self.clip_frames),
                )
            })
            .collect()
    }

    /// A batch of the clips `(episode, start frame)` on `device`.
    pub fn clips(&self, clips: &[(usize, usize)], device: Device) -> Result<Batch> {
        let (tf, h, w) = (
            self.clip_frames as i64,
            self.height as i64,
            self.width as i64,
        );
        let mut videos = Vec::new();
        let mut masks = Vec::new();
        let mut actions = Vec::new();
        for &(i, start) in clips {
            let e = self.episodes.get(i).ok_or_else(|| {
                TrainError::input("clip", format!("episode {i} of {}", self.episodes.len()))
            })?;
            if start + self.clip_frames > e.frames {
                return Err(TrainError::input(
                    format!("episode {} clip", e.index),
                    format!(
                        "start {start} + {} frames past its {} frames",
                        self.clip_frames, e.frames
                    ),
                ));
            }
            let (eh, ew) = (e.height as i64, e.width as i64);
            let px = eh * ew;
            let rgb =
                &e.rgb[start * (px as usize) * 3..(start + self.clip_frames) * (px as usize) * 3];
            let v = Tensor::from_slice(rgb)
                .reshape([tf, eh, ew, 3])
                .permute([0, 3, 1, 2]) // [T, 3, H, W]
                .to_kind(Kind::Float)
                / 127.5
                - 1.0;
            let v = if (eh, ew) != (h, w) {
                v.upsample_bilinear2d([h, w], false, None, None)
            } else {
                v
            };
            videos.push(v.permute([1, 0, 2, 3])); // [3, T, H, W]
            let m = match &e.masks {
                Some(data) => {
                    let m = Tensor::from_slice(
                        &data[start * px as usize..(start + self.clip_frames) * px as usize],
                    )
                    .reshape([tf, 1, eh, ew])
                    .to_kind(Kind::Float);
                    let m = if (eh, ew) != (h, w) {
                        m.upsample_nearest2d([h, w], None, None)
                    } else {
                        m
                    };
                    // labels [T, 1, H, W] -> coded channels [T, 3, H, W] -> [3, T, H, W]
                    self.mask_coding
                        .code(&m, 1)
                        .permute([1, 0, 2, 3])
                        .contiguous()
                }
                None => Tensor::zeros([3, tf, h, w], (Kind::Float, Device::Cpu)),
            };
            masks.push(m);
            let a = self.action_dim;
            actions.push(
                Tensor::from_slice(&e.actions[start * a..(start + self.clip_frames) * a])
                    .reshape([tf, a as i64]),
            );
        }
        let video = Tensor::stack(&videos, 0).to_device(device); // [B, 3, T, H, W]
        Ok(Batch {
            first_frames: video.select(2, 0),
            video,
            masks: Tensor::stack(&masks, 0).to_device(device),
            actions: Tensor::stack(&actions, 0).to_device(device),
            episodes: clips.iter().map(|&(i, _)| self.episodes[i].index).collect(),
        })
    }
}
