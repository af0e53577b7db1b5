//! Data-parallel training: one process per device, launched by torchrun
//! (`torchrun --no-python --nproc-per-node N bridgev2w train cfg.toml`), a
//! Slurm/Kubernetes launcher that sets the same variables, or by hand.
//!
//! Environment ([`DistEnv::from_env`]): `WORLD_SIZE` (processes), `RANK`
//! (this one, `0..WORLD_SIZE`), `MASTER_ADDR` / `MASTER_PORT` (the c10d
//! TCPStore; default `127.0.0.1:29500` as torchrun's), optional `LOCAL_RANK`
//! (the CUDA device index on its machine; default `RANK`),
//! `TORCHELASTIC_USE_AGENT_STORE=True` (torchrun's agent already hosts the
//! store on `MASTER_PORT`: every rank is a client), `TORCHELASTIC_RESTART_COUNT`
//! (keys of a restarted attempt are kept apart), `BRIDGEV2W_DIST_TIMEOUT`
//! (seconds; default c10d's 1800) and `BRIDGEV2W_BUCKET_MB` (gradient bucket
//! size; default DDP's 25).
//!
//! Every rank draws the same global batch of a step from `(seed, step)` and
//! takes the items `rank, rank + world, ...`; gradients are summed over the
//! ranks with weight `1 / world` each (every rank holds `batch / world`
//! items, so this is the gradient of the global batch's mean loss) before
//! clipping and AdamW, so all ranks keep identical parameters.
//!
//! The engine is PyTorch's own ([`C10dCollective`], through
//! `bridgev2w_torch_ext::c10d`): a TCPStore for the rendezvous and the
//! consistency checks, the Gloo process group on the CPU and NCCL on CUDA
//! for the collectives, gradients all-reduced in buckets ([`buckets`]).

mod buckets;
mod c10d;

pub use buckets::{average_gradients, bucket_ranges};
pub use c10d::C10dCollective;

use crate::{Result, TrainError};
use std::time::Duration;
use tch::{Device, Tensor};

/// This process's place in a data-parallel run, from torchrun's variables.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DistEnv {
    /// `RANK`.
    pub rank: usize,
    /// `WORLD_SIZE`.
    pub world: usize,
    /// `MASTER_ADDR`.
    pub master_addr: String,
    /// `MASTER_PORT`.
    pub master_port: u16,
    /// `LOCAL_RANK` (CUDA device index), when set.
    pub local_rank: Option<usize>,
    /// How long to wait for the other ranks and for a collective
    /// (`BRIDGEV2W_DIST_TIMEOUT`).
    pub timeout: Duration,
    /// torchrun's agent hosts the store (`TORCHELASTIC_USE_AGENT_STORE=True`).
    pub use_agent_store: bool,
    /// `TORCHELASTIC_RESTART_COUNT` (0 outside torchrun).
    pub restart_count: u64,
    /// Gradient bucket size in bytes (`BRIDGEV2W_BUCKET_MB`).
    pub bucket_bytes: usize,
}

/// c10d's default timeout (`kBackendDefaultTimeout`, 30 minutes).
pub const DEFAULT_TIMEOUT: Duration = Duration::from_secs(1800);

/// DDP's default gradient bucket size (`bucket_cap_mb = 25`).
pub const DEFAULT_BUCKET_MB: f64 = 25.0;

fn env_err(var: &str, message: impl Into<String>) -> TrainError {
    TrainError::input(format!("environment {var}"), message)
}

impl DistEnv {
    /// From the process environment: `None` without `WORLD_SIZE` (a single
    /// process). `WORLD_SIZE=1` is a group of one rank (as under
    /// `torchrun --nproc-per-node 1`): the same engine with nothing to sum.
    pub fn from_env() -> Result<Option<Self>> {
        Self::from_vars(|k| std::env::var(k).ok())
    }

    /// From a variable lookup (testable form of [`Self::from_env`]).
    pub fn from_vars(get: impl Fn(&str) -> Option<String>) -> Result<Option<Self>> {
        let parse = |var: &str, v: &str| -> Result<usize> {
            v.trim()
                .parse::<usize>()
                .map_err(|_| env_err(var, format!("{var}={v:?}: expected a non-negative integer")))
        };
        let world = match get("WORLD_SIZE") {
            Some(w) => parse("WORLD_SIZE", &w)?,
            None => {
                if let Some(r) = get("RANK") {
                    return Err(env_err(
                        "WORLD_SIZE",
                        format!("RANK={r} is set but WORLD_SIZE is not: set both (torchrun-style)"),
                    ));
                }
                return Ok(None);
            }
        };
        if world == 0 {
            return Err(env_err("WORLD_SIZE", "WORLD_SIZE=0: expected at least 1"));
        }
        let rank = match get("RANK") {
            Some(r) => parse("RANK", &r)?,
            None => {
                return Err(env_err(
                    "RANK",
                    format!("WORLD_SIZE={world} is set but RANK is not: set RANK in 0..{world}"),
                ))
            }
        };
        if rank >= world {
            return Err(env_err(
                "RANK",
                format!("RANK={rank} but WORLD_SIZE={world}: expected RANK in 0..{world}"),
            ));
        }
        let master_addr = get("MASTER_ADDR").unwrap_or_else(|| "127.0.0.1".into());
        if master_addr.trim().is_empty() {
            return Err(env_err(
                "MASTER_ADDR",
                "empty: expected a host name or address",
            ));
        }
        let master_port = match get("MASTER_PORT") {
            Some(p) => p
                .trim()
                .parse::<u16>()
                .ok()
                .filter(|&p| p > 0)
                .ok_or_else(|| {
                    env_err(
                        "MASTER_PORT",
                        format!("MASTER_PORT={p:?}: expected a port 1..65535"),
                    )
                })?,
            None => 29500,
        };
        let local_rank = get("LOCAL_RANK")
            .map(|v| parse("LOCAL_RANK", &v))
            .transpose()?;
        let timeout = match get("BRIDGEV2W_DIST_TIMEOUT") {
            Some(t) => {
                let secs = t
                    .trim()
                    .parse::<f64>()
                    .ok()
                    .filter(|s| *s > 0.0 && s.is_finite());
                Duration::from_secs_f64(secs.ok_or_else(|| {
                    env_err(
                        "BRIDGEV2W_DIST_TIMEOUT",
                        format!("BRIDGEV2W_DIST_TIMEOUT={t:?}: expected seconds > 0"),
                    )
                })?)
            }
            None => DEFAULT_TIMEOUT,
        };
        let use_agent_store = match get("TORCHELASTIC_USE_AGENT_STORE") {
            None => false,
            Some(v) => match v.trim() {
                "True" | "true" | "1" => true,
                "False" | "false" | "0" | "" => false,
                other => {
                    return Err(env_err(
                        "TORCHELASTIC_USE_AGENT_STORE",
                        format!("TORCHELASTIC_USE_AGENT_STORE={other:?}: expected True or False"),
                    ))
                }
            },
        };
        let restart_count = match get("TORCHELASTIC_RESTART_COUNT") {
            None => 0,
            Some(v) => v.trim().parse::<u64>().map_err(|_| {
                env_err(
                    "TORCHELASTIC_RESTART_COUNT",
                    format!("TORCHELASTIC_RESTART_COUNT={v:?}: expected a non-negative integer"),
                )
            })?,
        };
        let bucket_mb = match get("BRIDGEV2W_BUCKET_MB") {
            None => DEFAULT_BUCKET_MB,
            Some(v) => v
                .trim()
                .parse::<f64>()
                .ok()
                .filter(|m| *m > 0.0 && m.is_finite() && *m <= 1e6)
                .ok_or_else(|| {
                    env_err(
                        "BRIDGEV2W_BUCKET_MB",
                        format!("BRIDGEV2W_BUCKET_MB={v:?}: expected megabytes > 0"),
                    )
                })?,
        };
        Ok(Some(Self {
            rank,
            world,
            master_addr,
            master_port,
            local_rank,
            timeout,
            use_agent_store,
            restart_count,
            bucket_bytes: (bucket_mb * 1024.0 * 1024.0) as usize,
        }))
    }

    /// `MASTER_ADDR:MASTER_PORT` as written.
    pub fn master(&self) -> String {
        format!("{}:{}", self.master_addr, self.master_port)
    }

    /// One line for the log: rank, world size and who hosts the store.
    pub fn describe(&self) -> String {
        let host = if self.use_agent_store {
            "torchrun's agent"
        } else {
            "rank 0"
        };
        format!(
            "data-parallel: rank {} of {}, c10d store at {} (hosted by {host})",
            self.rank,
            self.world,
            self.master()
        )
    }
}

/// The collective operations data-parallel training needs.
pub trait Collective: std::fmt::Debug + Send {
    /// This process's rank.
    fn rank(&self) -> usize;
    /// The number of processes.
    fn world(&self) -> usize;
    /// The backend's name (for logs).
    fn name(&self) -> &'static str;
    /// Sums the contiguous tensor `buf` over all ranks, in place; every
    /// rank gets the same values.
    fn all_reduce_sum(&mut self, buf: &mut Tensor) -> Result<()>;
    /// Every rank's `row` (the same length on every rank), in rank order.
    fn all_gather_f64(&mut self, row: &[f64]) -> Result<Vec<Vec<f64>>>;
    /// The gradient bucket size in bytes.
    fn bucket_bytes(&self) -> usize {
        (DEFAULT_BUCKET_MB * 1024.0 * 1024.0) as usize
    }
    /// Sum-all-reduces `n` buffers made one at a time by `make(i)`, handing
    /// each summed buffer to `done(i, buf)`. A backend may overlap buffer
    /// `i`'s reduction with making buffer `i + 1` (this default does them
    /// one after the other), but keeps few of them alive at once.
    fn all_reduce_buckets(
        &mut self,
        n: usize,
        make: &mut dyn FnMut(usize) -> Result<Tensor>,
        done: &mut dyn FnMut(usize, Tensor) -> Result<()>,
    ) -> Result<()> {
        for i in 0..n {
            let mut buf = make(i)?;
            self.all_reduce_sum(&mut buf)?;
            done(i, buf)?;
        }
        Ok(())
    }
    /// Waits until every rank calls it.
    fn barrier(&mut self) -> Result<()>;
}

/// Joins the data-parallel group of `env`: the store, then the consistency
/// checks (`fingerprint`, e.g. a hash of the configuration, must be equal on
/// every rank), then the process group: NCCL on `Device::Cuda(i)` (this
/// rank's `LOCAL_RANK`), Gloo on the CPU.
pub fn connect(env: &DistEnv, device: Device, fingerprint: u64) -> Result<Box<dyn Collective>> {
    Ok(Box::new(C10dCollective::connect(env, device, fingerprint)?))
}

#[cfg(test)]
mod tests;
