//! Several VAE encodes or decodes in one process, at `bridgev2w bench
//! model`'s default shapes (the 2B VAE, 9 frames at 128x192, its 3 latent
//! frames at 16x24), each timed: the first is the warm-up, the others the
//! steady state; a process for `perf record` / `perf stat` on the VAE alone.
//! libtorch's threads as the environment sets them; this crate's caching
//! CPU allocator installed as the `bridgev2w` binary installs it.
//!
//!     cargo run --release -p bridgev2w-world-model --example vae_timing -- [RUNS=3] [encode|decode]
//!
//! Weights are the constructor's constants and inputs random: the time of
//! the convolutions does not depend on the values.

use bridgev2w_torch_ext::cpu_cache;
use bridgev2w_world_model::vae::{AutoencoderKLCogVideoX, VaeConfig};
use std::error::Error;
use std::time::Instant;
use tch::{nn::VarStore, Device, Kind, Tensor};

fn main() -> Result<(), Box<dyn Error>> {
    cpu_cache::install(cpu_cache::limit_from_env()?);
    let mut args = std::env::args().skip(1);
    let runs: usize = args.next().map_or(Ok(3), |s| s.parse())?;
    let part = args.next().unwrap_or_else(|| "encode".into());
    if part != "encode" && part != "decode" {
        return Err(format!("{part}: expected encode or decode").into());
    }
    let _guard = tch::no_grad_guard();
    let vs = VarStore::new(Device::Cpu);
    let vae = AutoencoderKLCogVideoX::new(&VaeConfig::cogvideox_2b(), vs.root())?;
    let opts = (Kind::Float, Device::Cpu);
    let video = Tensor::rand([1, 3, 9, 128, 192], opts) * 2.0 - 1.0;
    let latents = Tensor::randn([1, 16, 3, 16, 24], opts);
    for i in 0..runs {
        let t0 = Instant::now();
        if part == "encode" {
            let _posterior = vae.encode(&video)?;
        } else {
            let _video = vae.decode(&latents)?;
        }
        println!("{part} {i}: {:.3} s", t0.elapsed().as_secs_f64());
    }
    Ok(())
}
