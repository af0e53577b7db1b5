//! Data-parallel runs: this rank's items of every step's global batch, its rows of
//! the batch's random draws (so the ranks together compute what one process computes
//! on the whole batch), and the average of the gradients over the ranks.

use super::Trainer;
use crate::data::Batch;
use crate::Result;
use tch::Tensor;

/// The items `rank, rank + world, ...` of a global batch's per-item list
/// (`(0, 1)`: all of them).
pub(super) fn rank_items<T>(items: Vec<T>, (rank, world): (usize, usize)) -> Vec<T> {
    items.into_iter().skip(rank).step_by(world).collect()
}

impl Trainer {
    /// `(rank, world size)` of a data-parallel run; `(0, 1)` for one process.
    pub fn rank_and_world(&self) -> (usize, usize) {
        self.collective
            .as_ref()
            .map_or((0, 1), |c| (c.rank(), c.world()))
    }

    /// The data-parallel backend's name (`None`: one process).
    pub fn collective_name(&self) -> Option<&'static str> {
        self.collective.as_ref().map(|c| c.name())
    }

    /// Whether this process writes metrics and checkpoints (rank 0).
    pub fn is_primary(&self) -> bool {
        self.rank_and_world().0 == 0
    }

    /// This rank's items of a global batch (`rank, rank + world, ...`) as an
    /// index tensor; `None` for one process.
    fn shard_index(&self, global: i64, device: tch::Device) -> Option<Tensor> {
        let (rank, world) = self.rank_and_world();
        (world > 1).then(|| {
            let idx = rank_items((0..global).collect(), (rank, world));
            Tensor::from_slice(&idx).to_device(device)
        })
    }

    /// Standard normal noise for this rank's rows `local` `[b, ...]`: the
    /// rows of the global batch's draw (`[b * world, ...]` from libtorch's
    /// generator), so the ranks together use the single process's noise.
    pub(super) fn shard_randn(&self, local: &Tensor) -> Tensor {
        let mut size = local.size();
        let (_, world) = self.rank_and_world();
        size[0] *= world as i64;
        match self.shard_index(size[0], local.device()) {
            None => local.randn_like(),
            Some(idx) => {
                // `randn_like` is `empty_like` (which keeps the strides of a
                // permuted tensor such as the latents) then `normal_`, whose
                // CPU kernel differs for contiguous and strided tensors: make
                // the global tensor with the same layout and fill it the same way.
                let strides = local.stride();
                let mut order: Vec<usize> = (0..size.len()).collect();
                order.sort_by(|&a, &b| strides[b].cmp(&strides[a]));
                let mem_size: Vec<i64> = order.iter().map(|&d| size[d]).collect();
                let mut inverse = vec![0i64; order.len()];
                for (pos, &d) in order.iter().enumerate() {
                    inverse[d] = pos as i64;
                }
                let mut global = Tensor::empty(mem_size.as_slice(), (local.kind(), local.device()))
                    .permute(inverse.as_slice());
                let _ = global.normal_(0.0, 1.0);
                global.index_select(0, &idx)
            }
        }
    }

    /// `post.sample(seed)` for this rank's rows of the global batch.
    pub(super) fn shard_sample(
        &self,
        post: &bridgev2w_world_model::vae::Posterior,
        seed: u64,
    ) -> Result<Tensor> {
        let mean = post.mean();
        let mut size = mean.size();
        let (_, world) = self.rank_and_world();
        size[0] *= world as i64;
        match self.shard_index(size[0], tch::Device::Cpu) {
            None => Ok(post.sample(seed)?),
            Some(idx) => {
                // As `sample`: the generators seeded with `seed`, CPU noise.
                tch::manual_seed(seed as i64);
                let noise = Tensor::f_randn(size.as_slice(), (mean.kind(), tch::Device::Cpu))?
                    .index_select(0, &idx);
                Ok(post.sample_with_noise(&noise)?)
            }
        }
    }

    /// `model.encode_latents(video, Some(seed))` with this rank's rows of
    /// the global batch's posterior noise.
    pub(super) fn encode_sampled(&self, video: &Tensor, seed: u64) -> Result<Tensor> {
        let model = &self.model;
        if self.collective.is_none() {
            return Ok(model.encode_latents(video, Some(seed))?);
        }
        let post = model.vae.encode(video)?;
        let z = self.shard_sample(&post, seed)?;
        Ok(model
            .vae
            .scale_latents(&z)
            .permute([0, 2, 1, 3, 4])
            .to_device(model.device())
            .to_kind(model.kind()))
    }

    /// `model.image_latents(first, Some(seed))` with this rank's noise rows.
    pub(super) fn image_latents_sampled(
        &self,
        first: &Tensor,
        seed: u64,
        frames: i64,
    ) -> Result<Tensor> {
        let model = &self.model;
        if self.collective.is_none() {
            return Ok(model.image_latents(first, Some(seed))?);
        }
        let z = self.encode_sampled(&first.unsqueeze(2), seed)?; // [B, 1, C, h, w]
        Ok(model.config().image_conditioning.expand(&z, frames)) // [B, t, C, h, w]
    }

    /// This process's batch of step `step`: the whole batch, or in a
    /// data-parallel run this rank's items (`rank, rank + world, ...`).
    pub fn batch(&self, step: usize) -> Result<Batch> {
        let clips = self
            .data
            .batch_clips(self.cfg.train.seed, step, self.cfg.train.batch_size);
        let mine = rank_items(clips, self.rank_and_world());
        self.data.clips(&mine, self.model.device())
    }

    /// The whole batch of step `step` (every rank's items).
    pub fn global_batch(&self, step: usize) -> Result<Batch> {
        self.data.batch(
            self.cfg.train.seed,
            step,
            self.cfg.train.batch_size,
            self.model.device(),
        )
    }

    /// Data-parallel runs: replaces every gradient (and the loss values in
    /// `scalars`) by its mean over the ranks ([`crate::distributed::average_gradients`]:
    /// in buckets, after a check that the ranks' gradients agree). A no-op
    /// for one process.
    pub(super) fn average_gradients(&mut self, scalars: &mut [f64]) -> Result<()> {
        let Some(collective) = self.collective.as_mut() else {
            return Ok(());
        };
        let grads: Vec<Tensor> = self
            .opt
            .params()
            .iter()
            .map(|(_, p)| p.grad())
            .filter(|g| g.defined())
            .collect();
        crate::distributed::average_gradients(collective.as_mut(), &grads, scalars)
    }
}
