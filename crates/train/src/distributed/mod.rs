//! Data-parallel training: one process per device, started torchrun-style.
//!
//! Environment ([`DistEnv::from_env`]): `WORLD_SIZE` (processes), `RANK`
//! (this one, `0..WORLD_SIZE`), `MASTER_ADDR` / `MASTER_PORT` (where rank 0
//! listens; default `127.0.0.1:29500` as torchrun's), optional `LOCAL_RANK`
//! (the CUDA device index on its machine; default `RANK`), and
//! `BRIDGEV2W_DIST_TIMEOUT` (seconds to wait for the rendezvous; default 300).
//!
//! Every rank draws the same global batch of a step from `(seed, step)` and
//! takes the items `rank, rank + world, ...`; gradients are summed over the
//! ranks with weight `1 / world` each (every rank holds `batch / world`
//! items, so this is the gradient of the global batch's mean loss) before
//! clipping and AdamW, so all ranks keep identical parameters.
//!
//! Backends ([`Collective`]): [`TcpCollective`] (pure Rust: rank 0 receives
//! every rank's flattened f32 gradient, sums them in rank order and sends the
//! sum back; works anywhere, used on the CPU and by the tests) and
//! [`NcclCollective`] (CUDA devices: NCCL loaded at run time, the unique id
//! sent over the same TCP rendezvous, an in-place sum all-reduce on the
//! gradient buffer on libtorch's current stream; untested here, no GPU).

use crate::{Result, TrainError};
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream, ToSocketAddrs};
use std::time::{Duration, Instant};
use tch::{Device, Kind, Tensor};

/// Wire protocol version of the TCP rendezvous and all-reduce.
const PROTOCOL: u32 = 1;
const MAGIC: &[u8; 4] = b"BV2W";

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
    /// How long to wait for the other ranks (`BRIDGEV2W_DIST_TIMEOUT`).
    pub timeout: Duration,
}

fn env_err(var: &str, message: impl Into<String>) -> TrainError {
    TrainError::input(format!("environment {var}"), message)
}

impl DistEnv {
    /// From the process environment: `None` without `WORLD_SIZE` (a single
    /// process) or with `WORLD_SIZE=1`.
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
        if world == 1 {
            return Ok(None);
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
            None => Duration::from_secs(300),
        };
        Ok(Some(Self {
            rank,
            world,
            master_addr,
            master_port,
            local_rank,
            timeout,
        }))
    }

    /// `MASTER_ADDR:MASTER_PORT` as written.
    pub fn master(&self) -> String {
        format!("{}:{}", self.master_addr, self.master_port)
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
    /// Sums the contiguous f32 tensor `buf` over all ranks, in place; every
    /// rank gets the same values.
    fn all_reduce_sum(&mut self, buf: &mut Tensor) -> Result<()>;
}

fn io_error(what: String, e: std::io::Error) -> TrainError {
    TrainError::input(what, e.to_string())
}

/// The pure-Rust backend: a star of TCP connections to rank 0.
#[derive(Debug)]
pub struct TcpCollective {
    rank: usize,
    world: usize,
    /// Rank 0: the stream of rank `i` at `i - 1`; others: the stream to rank 0.
    peers: Vec<TcpStream>,
}

fn write_u32(s: &mut TcpStream, v: u32) -> std::io::Result<()> {
    s.write_all(&v.to_le_bytes())
}

fn read_u32(s: &mut TcpStream) -> std::io::Result<u32> {
    let mut b = [0u8; 4];
    s.read_exact(&mut b)?;
    Ok(u32::from_le_bytes(b))
}

fn write_u64(s: &mut TcpStream, v: u64) -> std::io::Result<()> {
    s.write_all(&v.to_le_bytes())
}

fn read_u64(s: &mut TcpStream) -> std::io::Result<u64> {
    let mut b = [0u8; 8];
    s.read_exact(&mut b)?;
    Ok(u64::from_le_bytes(b))
}

fn write_bytes(s: &mut TcpStream, bytes: &[u8]) -> std::io::Result<()> {
    write_u64(s, bytes.len() as u64)?;
    s.write_all(bytes)
}

fn read_bytes(s: &mut TcpStream, max: u64) -> std::io::Result<Vec<u8>> {
    let n = read_u64(s)?;
    if n > max {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("message of {n} bytes, expected at most {max}"),
        ));
    }
    let mut v = vec![0u8; n as usize];
    s.read_exact(&mut v)?;
    Ok(v)
}

fn f32_to_bytes(v: &[f32]) -> Vec<u8> {
    let mut out = Vec::with_capacity(4 * v.len());
    for x in v {
        out.extend_from_slice(&x.to_le_bytes());
    }
    out
}

fn add_bytes_into(acc: &mut [f32], bytes: &[u8]) {
    for (a, c) in acc.iter_mut().zip(bytes.chunks_exact(4)) {
        *a += f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
    }
}

fn bytes_to_f32(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

impl TcpCollective {
    /// The rendezvous: rank 0 listens on `MASTER_PORT` (all interfaces) and
    /// waits for the other `WORLD_SIZE - 1` ranks; the others connect to
    /// `MASTER_ADDR:MASTER_PORT`, retrying until `timeout`. `fingerprint`
    /// (e.g. a hash of the configuration) must be equal on every rank.
    pub fn connect(env: &DistEnv, fingerprint: u64) -> Result<Self> {
        if env.rank == 0 {
            Self::serve(env, fingerprint)
        } else {
            Self::join(env, fingerprint)
        }
    }

    fn serve(env: &DistEnv, fingerprint: u64) -> Result<Self> {
        let what = || {
            format!(
                "rank 0 listening on MASTER_PORT={} (WORLD_SIZE={})",
                env.master_port, env.world
            )
        };
        let listener =
            TcpListener::bind(("0.0.0.0", env.master_port)).map_err(|e| io_error(what(), e))?;
        listener
            .set_nonblocking(true)
            .map_err(|e| io_error(what(), e))?;
        let deadline = Instant::now() + env.timeout;
        let mut peers: Vec<Option<TcpStream>> = (1..env.world).map(|_| None).collect();
        let mut joined = 0;
        while joined < env.world - 1 {
            match listener.accept() {
                Ok((mut s, from)) => {
                    s.set_nonblocking(false).map_err(|e| io_error(what(), e))?;
                    s.set_nodelay(true).map_err(|e| io_error(what(), e))?;
                    // A stray connection must not stall the rendezvous.
                    s.set_read_timeout(Some(Duration::from_secs(10)))
                        .map_err(|e| io_error(what(), e))?;
                    let hello = (|| -> std::io::Result<(Vec<u8>, u32, u32, u32, u64)> {
                        let mut magic = vec![0u8; 4];
                        s.read_exact(&mut magic)?;
                        Ok((
                            magic,
                            read_u32(&mut s)?,
                            read_u32(&mut s)?,
                            read_u32(&mut s)?,
                            read_u64(&mut s)?,
                        ))
                    })();
                    let Ok((magic, version, rank, world, fp)) = hello else {
                        continue; // not one of ours
                    };
                    let problem = if magic != MAGIC || version != PROTOCOL {
                        Some(format!(
                            "a connection from {from} that is not bridgev2w protocol {PROTOCOL}"
                        ))
                    } else if world as usize != env.world {
                        Some(format!(
                            "rank {rank} has WORLD_SIZE={world}, rank 0 has WORLD_SIZE={}",
                            env.world
                        ))
                    } else if rank == 0 || rank as usize >= env.world {
                        Some(format!("a second rank claims RANK={rank}"))
                    } else if peers[rank as usize - 1].is_some() {
                        Some(format!("RANK={rank} joined twice"))
                    } else if fp != fingerprint {
                        Some(format!(
                            "rank {rank}'s configuration differs from rank 0's (every rank must train the same config)"
                        ))
                    } else {
                        None
                    };
                    let reply = problem.clone().unwrap_or_default();
                    let _ = write_bytes(&mut s, reply.as_bytes());
                    if let Some(p) = problem {
                        if magic == MAGIC {
                            return Err(TrainError::input("data-parallel rendezvous", p));
                        }
                        continue;
                    }
                    s.set_read_timeout(None).map_err(|e| io_error(what(), e))?;
                    peers[rank as usize - 1] = Some(s);
                    joined += 1;
                }
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                    if Instant::now() >= deadline {
                        return Err(TrainError::input(
                            "data-parallel rendezvous",
                            format!(
                                "rank 0: only {joined} of the {} other rank(s) connected to MASTER_PORT={} within {:.0} s (BRIDGEV2W_DIST_TIMEOUT)",
                                env.world - 1,
                                env.master_port,
                                env.timeout.as_secs_f64()
                            ),
                        ));
                    }
                    std::thread::sleep(Duration::from_millis(20));
                }
                Err(e) => return Err(io_error(what(), e)),
            }
        }
        Ok(Self {
            rank: 0,
            world: env.world,
            peers: peers.into_iter().flatten().collect(),
        })
    }

    fn join(env: &DistEnv, fingerprint: u64) -> Result<Self> {
        let master = env.master();
        let unreachable = |last: String| {
            TrainError::input(
                "environment MASTER_ADDR/MASTER_PORT",
                format!(
                    "rank {} cannot reach rank 0 at MASTER_ADDR={} MASTER_PORT={} within {:.0} s (BRIDGEV2W_DIST_TIMEOUT): {last}",
                    env.rank,
                    env.master_addr,
                    env.master_port,
                    env.timeout.as_secs_f64()
                ),
            )
        };
        let deadline = Instant::now() + env.timeout;
        let mut last = String::from("no attempt");
        let mut stream = loop {
            let addrs: Vec<SocketAddr> = match master.to_socket_addrs() {
                Ok(a) => a.collect(),
                Err(e) => {
                    last = format!("cannot resolve {master}: {e}");
                    Vec::new()
                }
            };
            let mut connected = None;
            for a in &addrs {
                let left = deadline.saturating_duration_since(Instant::now());
                let attempt = left
                    .min(Duration::from_secs(2))
                    .max(Duration::from_millis(10));
                match TcpStream::connect_timeout(a, attempt) {
                    Ok(s) => {
                        connected = Some(s);
                        break;
                    }
                    Err(e) => last = format!("{a}: {e}"),
                }
            }
            if let Some(s) = connected {
                break s;
            }
            if Instant::now() >= deadline {
                return Err(unreachable(last));
            }
            std::thread::sleep(Duration::from_millis(100));
        };
        let what = || format!("rank {} talking to rank 0 at {master}", env.rank);
        stream.set_nodelay(true).map_err(|e| io_error(what(), e))?;
        (|| -> std::io::Result<()> {
            stream.write_all(MAGIC)?;
            write_u32(&mut stream, PROTOCOL)?;
            write_u32(&mut stream, env.rank as u32)?;
            write_u32(&mut stream, env.world as u32)?;
            write_u64(&mut stream, fingerprint)
        })()
        .map_err(|e| io_error(what(), e))?;
        let reply = read_bytes(&mut stream, 1 << 16).map_err(|e| io_error(what(), e))?;
        if !reply.is_empty() {
            return Err(TrainError::input(
                "data-parallel rendezvous",
                format!(
                    "rank 0 refused rank {}: {}",
                    env.rank,
                    String::from_utf8_lossy(&reply)
                ),
            ));
        }
        Ok(Self {
            rank: env.rank,
            world: env.world,
            peers: vec![stream],
        })
    }

    /// Sends `bytes` from rank 0 to every rank (the argument of the others is
    /// ignored); returns rank 0's bytes on every rank.
    pub fn broadcast_bytes(&mut self, bytes: &[u8]) -> Result<Vec<u8>> {
        if self.rank == 0 {
            for (i, s) in self.peers.iter_mut().enumerate() {
                write_bytes(s, bytes)
                    .map_err(|e| io_error(format!("broadcast to rank {}", i + 1), e))?;
            }
            Ok(bytes.to_vec())
        } else {
            read_bytes(&mut self.peers[0], 1 << 20)
                .map_err(|e| io_error(format!("rank {}: broadcast from rank 0", self.rank), e))
        }
    }

    /// Checks that every rank holds `len` values, before a collective that
    /// cannot check it itself (NCCL would sum mismatched buffers into
    /// garbage or wait forever). Every rank learns the outcome, so all stop
    /// together: rank 0 sends its length, each rank compares, and the
    /// mismatches are summed over all ranks.
    pub fn agree_on_len(&mut self, len: usize, what: &str) -> Result<()> {
        let theirs = self.broadcast_bytes(&(len as u64).to_le_bytes())?;
        let rank0 = <[u8; 8]>::try_from(theirs.as_slice())
            .map(u64::from_le_bytes)
            .map_err(|_| {
                TrainError::input(
                    what,
                    format!("rank 0 sent {} bytes, expected a length", theirs.len()),
                )
            })?;
        let mut mismatched = [f32::from(u8::from(rank0 != len as u64))];
        self.all_reduce_host(&mut mismatched)?;
        if mismatched[0] > 0.0 {
            return Err(TrainError::input(
                what,
                format!(
                    "{} rank(s) hold a different number of values than rank 0's {rank0} \
                     (rank {} holds {len}): different models or gradients?",
                    mismatched[0], self.rank
                ),
            ));
        }
        Ok(())
    }

    /// Sums `buf` over all ranks in place (rank 0 adds the ranks' buffers in
    /// rank order, so every rank gets the same values).
    pub fn all_reduce_host(&mut self, buf: &mut [f32]) -> Result<()> {
        let max = 4 * buf.len() as u64;
        if self.rank == 0 {
            for (i, s) in self.peers.iter_mut().enumerate() {
                let r = i + 1;
                let bytes = read_bytes(s, u64::MAX).map_err(|e| {
                    io_error(
                        format!("all-reduce: receiving from rank {r} (did it stop?)"),
                        e,
                    )
                })?;
                if bytes.len() as u64 != max {
                    return Err(TrainError::input(
                        "all-reduce",
                        format!(
                            "rank {r} sent {} values, rank 0 has {} (different models or gradients?)",
                            bytes.len() / 4,
                            buf.len()
                        ),
                    ));
                }
                add_bytes_into(buf, &bytes);
            }
            let out = f32_to_bytes(buf);
            for (i, s) in self.peers.iter_mut().enumerate() {
                write_bytes(s, &out).map_err(|e| {
                    io_error(
                        format!("all-reduce: sending to rank {} (did it stop?)", i + 1),
                        e,
                    )
                })?;
            }
        } else {
            let s = &mut self.peers[0];
            let rank = self.rank;
            write_bytes(s, &f32_to_bytes(buf)).map_err(|e| {
                io_error(
                    format!("rank {rank} all-reduce: sending to rank 0 (did it stop?)"),
                    e,
                )
            })?;
            let bytes = read_bytes(s, max).map_err(|e| {
                io_error(
                    format!("rank {rank} all-reduce: receiving from rank 0 (did it stop?)"),
                    e,
                )
            })?;
            if bytes.len() != buf.len() * 4 {
                return Err(TrainError::input(
                    "all-reduce",
                    format!(
                        "rank 0 sent {} values, rank {rank} has {} (different models or gradients?)",
                        bytes.len() / 4,
                        buf.len()
                    ),
                ));
            }
            buf.copy_from_slice(&bytes_to_f32(&bytes));
        }
        Ok(())
    }
}

impl Collective for TcpCollective {
    fn rank(&self) -> usize {
        self.rank
    }
    fn world(&self) -> usize {
        self.world
    }
    fn name(&self) -> &'static str {
        "tcp"
    }
    fn all_reduce_sum(&mut self, buf: &mut Tensor) -> Result<()> {
        let host = buf.to_device(Device::Cpu).to_kind(Kind::Float).contiguous();
        let mut v = Vec::<f32>::try_from(&host.reshape(-1))?;
        self.all_reduce_host(&mut v)?;
        let summed = Tensor::from_slice(&v)
            .view(buf.size().as_slice())
            .to_device(buf.device())
            .to_kind(buf.kind());
        tch::no_grad(|| buf.copy_(&summed));
        Ok(())
    }
}

/// The CUDA backend: NCCL (loaded at run time), bootstrapped over the TCP
/// rendezvous. The all-reduce runs on libtorch's current stream of the
/// device (the legacy default stream: tch never switches streams), so it is
/// ordered after the backward's kernels and before the optimizer's.
#[derive(Debug)]
pub struct NcclCollective {
    tcp: TcpCollective,
    comm: bridgev2w_torch_ext::nccl::NcclComm,
    /// The buffer length all ranks were found to share (checked over TCP on
    /// the first all-reduce and whenever this rank's length changes).
    agreed_len: Option<usize>,
}

impl NcclCollective {
    /// Loads NCCL, makes rank 0's unique id and sends it to the others over
    /// `tcp`, and creates this rank's communicator on CUDA device `device`.
    pub fn new(mut tcp: TcpCollective, device: usize) -> Result<Self> {
        use bridgev2w_torch_ext::nccl::{Nccl, UNIQUE_ID_BYTES};
        // Every rank must learn whether rank 0 could load NCCL (else the
        // others would wait for an id forever): rank 0 sends the id or an
        // empty message.
        let loaded = Nccl::load();
        let id = if tcp.rank() == 0 {
            let id = loaded.as_ref().ok().map(|n| n.unique_id()).transpose();
            let bytes = match &id {
                Ok(Some(id)) => id.to_vec(),
                _ => Vec::new(),
            };
            tcp.broadcast_bytes(&bytes)?;
            bytes
        } else {
            tcp.broadcast_bytes(&[])?
        };
        // ncclCommInitRank waits for every rank: all must be ready first, or
        // a rank that failed would leave the others waiting forever.
        let id: Option<[u8; UNIQUE_ID_BYTES]> = id.as_slice().try_into().ok();
        let mut failed = [f32::from(u8::from(loaded.is_err() || id.is_none()))];
        tcp.all_reduce_host(&mut failed)?;
        let nccl = loaded?;
        let id = id.ok_or_else(|| {
            TrainError::input(
                "data-parallel NCCL",
                "rank 0 could not create an NCCL unique id (see rank 0's error)",
            )
        })?;
        if failed[0] > 0.0 {
            return Err(TrainError::input(
                "data-parallel NCCL",
                format!(
                    "{} rank(s) could not load NCCL (see their errors); rank {} stops too",
                    failed[0],
                    tcp.rank()
                ),
            ));
        }
        let comm = nccl.init_rank(&id, tcp.world(), tcp.rank(), device)?;
        Ok(Self {
            tcp,
            comm,
            agreed_len: None,
        })
    }
}

impl Collective for NcclCollective {
    fn rank(&self) -> usize {
        self.tcp.rank()
    }
    fn world(&self) -> usize {
        self.tcp.world()
    }
    fn name(&self) -> &'static str {
        "nccl"
    }
    fn all_reduce_sum(&mut self, buf: &mut Tensor) -> Result<()> {
        let len = buf.numel();
        if self.agreed_len != Some(len) {
            self.tcp.agree_on_len(len, "NCCL all-reduce")?;
            self.agreed_len = Some(len);
        }
        Ok(self.comm.all_reduce_sum(buf)?)
    }
}

/// The backend for `device`: NCCL for CUDA, TCP for the CPU. `device` is the
/// CUDA device index of this rank (its `LOCAL_RANK`) when on CUDA.
pub fn connect(env: &DistEnv, device: Device, fingerprint: u64) -> Result<Box<dyn Collective>> {
    let tcp = TcpCollective::connect(env, fingerprint)?;
    match device {
        Device::Cuda(i) => Ok(Box::new(NcclCollective::new(tcp, i)?)),
        _ => Ok(Box::new(tcp)),
    }
}

#[cfg(test)]
mod tests;
