//! The VAE's diagonal Gaussian posterior.

use crate::error::{Result, WorldModelError};
use tch::Tensor;

/// The diagonal Gaussian posterior of an encoded video (diffusers'
/// `DiagonalGaussianDistribution`): `mean` and `logvar` (clamped to `[-30, 20]`),
/// each `[B, latent_channels, t, h, w]`, unscaled.
#[derive(Debug)]
pub struct Posterior {
    mean: Tensor,
    logvar: Tensor,
}

impl Posterior {
    /// Splits the encoder's moments `[B, 2C, t, h, w]` into mean and log-variance.
    pub fn from_moments(moments: &Tensor) -> Result<Self> {
        let parts = moments.f_chunk(2, 1)?;
        let [mean, logvar] = <[Tensor; 2]>::try_from(parts).map_err(|p| {
            WorldModelError::input(
                "moments",
                format!("expected 2 chunks along channels, got {}", p.len()),
            )
        })?;
        Ok(Self {
            mean,
            logvar: logvar.clamp(-30.0, 20.0),
        })
    }

    /// The posterior of `batch` copies of a single element's (the mean and
    /// log-variance expanded, not copied): encoding a frame once stands for
    /// encoding it `batch` times.
    pub fn repeat_batch(&self, batch: i64) -> Result<Self> {
        let size = self.mean.size();
        match size.split_first() {
            Some((1, rest)) if batch >= 1 => {
                let shape: Vec<i64> = std::iter::once(batch).chain(rest.iter().copied()).collect();
                Ok(Self {
                    mean: self.mean.expand(shape.as_slice(), false),
                    logvar: self.logvar.expand(shape.as_slice(), false),
                })
            }
            _ => Err(WorldModelError::input(
                "posterior",
                format!("shape {size:?} to repeat {batch} times: expected a batch of one"),
            )),
        }
    }

    /// The mean `[B, C, t, h, w]` (diffusers' `latent_dist.mean`, also the mode).
    pub fn mean(&self) -> &Tensor {
        &self.mean
    }

    /// The clamped log-variance.
    pub fn logvar(&self) -> &Tensor {
        &self.logvar
    }

    /// `exp(0.5 * logvar)`.
    pub fn std(&self) -> Tensor {
        (&self.logvar * 0.5).exp()
    }

    /// The mode (== mean).
    pub fn mode(&self) -> Tensor {
        self.mean.shallow_clone()
    }

    /// `mean + std * noise` for a caller-supplied standard normal `noise` of the
    /// mean's shape.
    pub fn sample_with_noise(&self, noise: &Tensor) -> Result<Tensor> {
        if noise.size() != self.mean.size() {
            return Err(WorldModelError::input(
                "noise",
                format!(
                    "shape {:?}, the posterior's is {:?}",
                    noise.size(),
                    self.mean.size()
                ),
            ));
        }
        let noise = noise
            .to_device(self.mean.device())
            .to_kind(self.mean.kind());
        Ok(&self.mean + self.std() * noise)
    }

    /// A sample with the noise of diffusers'
    /// `sample(generator=torch.Generator().manual_seed(seed))`: standard normal noise
    /// drawn on the CPU after seeding libtorch's global generators with `seed` (which
    /// they keep afterwards).
    pub fn sample(&self, seed: u64) -> Result<Tensor> {
        self.sample_batch(seed, crate::pipeline::BatchNoise::Independent)
    }

    /// [`Self::sample`] with the batch's noise drawn as `batch_noise` says:
    /// shared, every element gets the noise of element 0.
    pub fn sample_batch(
        &self,
        seed: u64,
        batch_noise: crate::pipeline::BatchNoise,
    ) -> Result<Tensor> {
        tch::manual_seed(seed as i64);
        let noise = batch_noise.randn(&self.mean.size(), self.mean.kind(), tch::Device::Cpu);
        self.sample_with_noise(&noise)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::pipeline::BatchNoise;
    use tch::{Device, Kind};

    #[test]
    fn a_repeated_posterior_samples_as_its_copies() {
        tch::manual_seed(0);
        let one = Tensor::randn([1, 4, 1, 2, 3], (Kind::Float, Device::Cpu)); // [1, 2C, t, h, w]
        let post = Posterior::from_moments(&one).unwrap();
        let copies = Posterior::from_moments(&Tensor::cat(&[&one, &one, &one], 0)).unwrap();
        let repeated = post.repeat_batch(3).unwrap();
        assert_eq!(repeated.mean().size(), [3, 2, 1, 2, 3]);
        for noise in [BatchNoise::Independent, BatchNoise::Shared] {
            let a = repeated.sample_batch(5, noise).unwrap();
            let b = copies.sample_batch(5, noise).unwrap();
            assert!(a.equal(&b), "{noise:?}");
        }
        let e = copies.repeat_batch(2).unwrap_err().to_string();
        assert!(e.contains("batch of one"), "{e}");
        assert!(post.repeat_batch(0).is_err());
    }
}
