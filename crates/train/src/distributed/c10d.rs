//! [`C10dCollective`]: data-parallel collectives on PyTorch's c10d engine.
//!
//! The rendezvous is a c10d `TCPStore` at `MASTER_ADDR:MASTER_PORT`: hosted
//! by rank 0, or under torchrun by its agent (`TORCHELASTIC_USE_AGENT_STORE`),
//! every rank then being a client; keys live under
//! `bridgev2w/attempt_<TORCHELASTIC_RESTART_COUNT>/`. On it every rank
//! checks in (so a missing or doubled `RANK` is named, not waited for
//! forever) and publishes its configuration fingerprint (so a rank with a
//! different config stops every rank). Then the Gloo (CPU) or NCCL (CUDA)
//! process group runs the collectives, with `BRIDGEV2W_DIST_TIMEOUT`.

use super::{Collective, DistEnv};
use crate::{Result, TrainError};
use bridgev2w_torch_ext::c10d::{Backend, ProcessGroup, Store};
use std::collections::VecDeque;
use std::time::{Duration, Instant};
use tch::{Device, Kind, Tensor};

/// Buckets reduced at once by [`C10dCollective::all_reduce_buckets`].
const BUCKETS_IN_FLIGHT: usize = 2;

/// Collectives over a c10d process group (Gloo or NCCL).
#[derive(Debug)]
pub struct C10dCollective {
    group: ProcessGroup,
    // Kept alive for the group's lifetime (the group holds it too).
    _store: Store,
    device: Device,
    bucket_bytes: usize,
}

fn rendezvous_err(message: String) -> TrainError {
    TrainError::input("data-parallel rendezvous", message)
}

/// Every rank checks in; waits until all `world` have (or the timeout),
/// then checks that each `RANK` was claimed exactly once.
fn check_in(store: &Store, env: &DistEnv) -> Result<()> {
    let c10d = |e: bridgev2w_torch_ext::TorchExtError| rendezvous_err(e.to_string());
    store.add(&format!("rank/{}", env.rank), 1).map_err(c10d)?;
    store.add("joined", 1).map_err(c10d)?;
    let deadline = Instant::now() + env.timeout;
    loop {
        let joined = store.add("joined", 0).map_err(c10d)?;
        if joined >= env.world as i64 {
            break;
        }
        if Instant::now() >= deadline {
            let mut missing = Vec::new();
            for r in 0..env.world {
                if !store.check(&format!("rank/{r}")).map_err(c10d)? {
                    missing.push(r.to_string());
                }
            }
            return Err(rendezvous_err(format!(
                "rank {}: only {joined} of WORLD_SIZE={} ranks joined at MASTER_ADDR={} MASTER_PORT={} \
                 within {:.0} s (BRIDGEV2W_DIST_TIMEOUT); missing: rank(s) {}",
                env.rank,
                env.world,
                env.master_addr,
                env.master_port,
                env.timeout.as_secs_f64(),
                missing.join(", ")
            )));
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let mut wrong = Vec::new();
    for r in 0..env.world {
        let n = store.add(&format!("rank/{r}"), 0).map_err(c10d)?;
        if n != 1 {
            wrong.push(format!("RANK={r} by {n}"));
        }
    }
    if !wrong.is_empty() {
        return Err(rendezvous_err(format!(
            "rank {}: each RANK in 0..{} must be claimed by exactly one process, but {} \
             (WORLD_SIZE or RANK set wrongly?)",
            env.rank,
            env.world,
            wrong.join(", ")
        )));
    }
    Ok(())
}

/// Every rank publishes `WORLD_SIZE` and the configuration's fingerprint and
/// compares everyone's with rank 0's: all ranks reach the same verdict.
fn check_fingerprints(store: &Store, env: &DistEnv, fingerprint: u64, hosting: bool) -> Result<()> {
    let c10d = |e: bridgev2w_torch_ext::TorchExtError| {
        rendezvous_err(format!(
            "rank {}: {e}{}",
            env.rank,
            if hosting {
                ""
            } else {
                " (the store's host stopped? its own error says why)"
            }
        ))
    };
    let mine = format!("WORLD_SIZE={} config {fingerprint:016x}", env.world);
    store
        .set(&format!("fingerprint/{}", env.rank), mine.as_bytes())
        .map_err(c10d)?;
    let all: Vec<String> = (0..env.world)
        .map(|r| {
            store
                .get(&format!("fingerprint/{r}"))
                .map(|v| String::from_utf8_lossy(&v).into_owned())
                .map_err(c10d)
        })
        .collect::<Result<_>>()?;
    // The host keeps the store up until every rank has read the fingerprints,
    // so a verdict that stops it does not cut the others off mid-read.
    store.add("fingerprints_read", 1).map_err(c10d)?;
    if hosting {
        let deadline = Instant::now() + env.timeout;
        while store.add("fingerprints_read", 0).map_err(c10d)? < env.world as i64
            && Instant::now() < deadline
        {
            std::thread::sleep(Duration::from_millis(20));
        }
    }
    let differ: Vec<String> = all
        .iter()
        .enumerate()
        .filter(|(_, v)| *v != &all[0])
        .map(|(r, v)| format!("rank {r} has {v}"))
        .collect();
    if !differ.is_empty() {
        return Err(rendezvous_err(format!(
            "the configuration differs between ranks (every rank must train the same config): \
             rank 0 has {}, {}; rank {} stops",
            all[0],
            differ.join(", "),
            env.rank
        )));
    }
    Ok(())
}

impl C10dCollective {
    /// Meets the other ranks (see the module doc) and creates the process
    /// group: NCCL on `Device::Cuda(i)`, Gloo otherwise.
    pub fn connect(env: &DistEnv, device: Device, fingerprint: u64) -> Result<Self> {
        let is_server = env.rank == 0 && !env.use_agent_store;
        let prefix = format!("bridgev2w/attempt_{}", env.restart_count); // keys: PREFIX/key
        let store = Store::tcp(
            &env.master_addr,
            env.master_port,
            is_server,
            env.world,
            env.timeout,
            &prefix,
        )
        .map_err(|e| {
            let role = if is_server {
                "cannot host the store".to_string()
            } else {
                format!(
                    "cannot reach the store within {:.0} s (BRIDGEV2W_DIST_TIMEOUT)",
                    env.timeout.as_secs_f64()
                )
            };
            TrainError::input(
                "environment MASTER_ADDR/MASTER_PORT",
                format!(
                    "rank {} {role} at MASTER_ADDR={} MASTER_PORT={}{}: {e}",
                    env.rank,
                    env.master_addr,
                    env.master_port,
                    if env.use_agent_store {
                        ", hosted by torchrun's agent (TORCHELASTIC_USE_AGENT_STORE=True)"
                    } else {
                        ""
                    }
                ),
            )
        })?;
        check_in(&store, env)?;
        check_fingerprints(&store, env, fingerprint, is_server)?;
        let backend = match device {
            Device::Cuda(i) => Backend::Nccl { device: i },
            _ => Backend::Gloo,
        };
        let group = ProcessGroup::new(&store, env.rank, env.world, backend, env.timeout)
            .map_err(|e| rendezvous_err(format!("rank {}: {e}", env.rank)))?;
        Ok(Self {
            group,
            _store: store,
            device,
            bucket_bytes: env.bucket_bytes,
        })
    }

    fn collective_err(&self, e: bridgev2w_torch_ext::TorchExtError) -> TrainError {
        TrainError::input(
            "data-parallel collective",
            format!(
                "rank {} of {}: {e} (did another rank stop? its own error says why)",
                self.group.rank(),
                self.group.world()
            ),
        )
    }
}

impl Collective for C10dCollective {
    fn rank(&self) -> usize {
        self.group.rank()
    }
    fn world(&self) -> usize {
        self.group.world()
    }
    fn name(&self) -> &'static str {
        self.group.backend().name()
    }
    fn all_reduce_sum(&mut self, buf: &mut Tensor) -> Result<()> {
        self.group
            .all_reduce_sum(buf)
            .map_err(|e| self.collective_err(e))
    }
    fn all_gather_f64(&mut self, row: &[f64]) -> Result<Vec<Vec<f64>>> {
        let t = Tensor::from_slice(row).to_device(self.device);
        let rows = self
            .group
            .all_gather(&t)
            .map_err(|e| self.collective_err(e))?;
        rows.iter()
            .map(|r| {
                Ok(Vec::<f64>::try_from(
                    &r.to_device(Device::Cpu).to_kind(Kind::Double),
                )?)
            })
            .collect()
    }
    fn bucket_bytes(&self) -> usize {
        self.bucket_bytes
    }
    fn all_reduce_buckets(
        &mut self,
        n: usize,
        make: &mut dyn FnMut(usize) -> Result<Tensor>,
        done: &mut dyn FnMut(usize, Tensor) -> Result<()>,
    ) -> Result<()> {
        let mut in_flight = VecDeque::new();
        for i in 0..n {
            let buf = make(i)?;
            let work = self
                .group
                .start_all_reduce_sum(&buf)
                .map_err(|e| self.collective_err(e))?;
            in_flight.push_back((i, buf, work));
            if in_flight.len() >= BUCKETS_IN_FLIGHT {
                if let Some((j, buf, work)) = in_flight.pop_front() {
                    work.wait().map_err(|e| self.collective_err(e))?;
                    done(j, buf)?;
                }
            }
        }
        while let Some((j, buf, work)) = in_flight.pop_front() {
            work.wait().map_err(|e| self.collective_err(e))?;
            done(j, buf)?;
        }
        Ok(())
    }
    fn barrier(&mut self) -> Result<()> {
        self.group.barrier().map_err(|e| self.collective_err(e))
    }
}
