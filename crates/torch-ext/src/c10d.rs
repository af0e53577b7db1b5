//! PyTorch's distributed engine, c10d, as libtorch ships it (through the C
//! shim in `csrc/c10d.cpp` and `csrc/c10d_nccl.cpp`): the [`Store`] every
//! rank meets at (`TCPStore`, server or client, under an optional key
//! prefix) and the [`ProcessGroup`] that runs collectives on tch tensors:
//! Gloo on the CPU (ring/tree all-reduce in background threads), NCCL on
//! CUDA. The same engine `torch.distributed` and DDP use, so its timeouts,
//! algorithms and error reports are PyTorch's own.
//!
//! Every call that can fail returns the C++ exception's message; a collective
//! that a peer never joins fails after the group's timeout instead of hanging.

use crate::{Result, TorchExtError};
use std::ffi::{c_char, c_int, c_void, CStr, CString};
use std::ptr::NonNull;
use std::time::Duration;
use tch::Tensor;

const ERR_LEN: usize = 4096;

extern "C" {
    fn bv2w_c10d_has_gloo() -> c_int;
    fn bv2w_c10d_has_nccl() -> c_int;
    fn bv2w_c10d_store_new(
        host: *const c_char,
        port: c_int,
        is_server: c_int,
        world: c_int,
        timeout_ms: i64,
        prefix: *const c_char,
        err: *mut c_char,
        err_len: usize,
    ) -> *mut c_void;
    fn bv2w_c10d_store_free(store: *mut c_void);
    fn bv2w_c10d_store_set(
        store: *mut c_void,
        key: *const c_char,
        data: *const u8,
        len: usize,
        err: *mut c_char,
        err_len: usize,
    ) -> c_int;
    fn bv2w_c10d_store_get(
        store: *mut c_void,
        key: *const c_char,
        out: *mut *mut u8,
        len: *mut usize,
        err: *mut c_char,
        err_len: usize,
    ) -> c_int;
    fn bv2w_c10d_store_add(
        store: *mut c_void,
        key: *const c_char,
        delta: i64,
        out: *mut i64,
        err: *mut c_char,
        err_len: usize,
    ) -> c_int;
    fn bv2w_c10d_store_check(
        store: *mut c_void,
        key: *const c_char,
        err: *mut c_char,
        err_len: usize,
    ) -> c_int;
    fn bv2w_c10d_free(p: *mut c_void);
    fn bv2w_c10d_gloo_new(
        store: *mut c_void,
        rank: c_int,
        world: c_int,
        timeout_ms: i64,
        err: *mut c_char,
        err_len: usize,
    ) -> *mut c_void;
    fn bv2w_c10d_nccl_new(
        store: *mut c_void,
        rank: c_int,
        world: c_int,
        device: c_int,
        timeout_ms: i64,
        err: *mut c_char,
        err_len: usize,
    ) -> *mut c_void;
    fn bv2w_c10d_group_free(group: *mut c_void);
    fn bv2w_c10d_all_reduce(
        group: *mut c_void,
        tensor: *mut c_void,
        err: *mut c_char,
        err_len: usize,
    ) -> *mut c_void;
    fn bv2w_c10d_work_wait(work: *mut c_void, err: *mut c_char, err_len: usize) -> c_int;
    fn bv2w_c10d_work_free(work: *mut c_void);
    fn bv2w_c10d_broadcast(
        group: *mut c_void,
        tensor: *mut c_void,
        root: c_int,
        err: *mut c_char,
        err_len: usize,
    ) -> c_int;
    fn bv2w_c10d_all_gather(
        group: *mut c_void,
        input: *mut c_void,
        outputs: *const *mut c_void,
        world: c_int,
        err: *mut c_char,
        err_len: usize,
    ) -> c_int;
    fn bv2w_c10d_barrier(group: *mut c_void, err: *mut c_char, err_len: usize) -> c_int;
}

/// Whether this build has the Gloo backend (the gloo headers were found when
/// it was compiled).
pub fn has_gloo() -> bool {
    // SAFETY: no arguments, no state.
    unsafe { bv2w_c10d_has_gloo() == 1 }
}

/// Whether this build has the NCCL backend (libtorch with CUDA, and the CUDA
/// and NCCL headers found when it was compiled).
pub fn has_nccl() -> bool {
    // SAFETY: no arguments, no state.
    unsafe { bv2w_c10d_has_nccl() == 1 }
}

/// A buffer for the shim's error message.
struct ErrBuf([c_char; ERR_LEN]);

impl ErrBuf {
    fn new() -> Self {
        Self([0; ERR_LEN])
    }
    fn ptr(&mut self) -> *mut c_char {
        self.0.as_mut_ptr()
    }
    fn into_error(self, what: &str) -> TorchExtError {
        // SAFETY: the buffer is zero-initialised and the shim writes at most
        // ERR_LEN - 1 bytes plus a NUL, so it is always NUL-terminated.
        let msg = unsafe { CStr::from_ptr(self.0.as_ptr()) }.to_string_lossy();
        let msg = if msg.is_empty() {
            "no message".into()
        } else {
            msg
        };
        TorchExtError::C10d(format!("{what}: {}", msg.trim_end()))
    }
}

fn cstring(what: &str, s: &str) -> Result<CString> {
    CString::new(s).map_err(|_| TorchExtError::C10d(format!("{what}: {s:?} contains a NUL byte")))
}

fn millis(timeout: Duration) -> i64 {
    i64::try_from(timeout.as_millis()).unwrap_or(i64::MAX)
}

/// A c10d key-value store: `TCPStore`, possibly under a key prefix. Every
/// operation waits at most the timeout it was created with.
#[derive(Debug)]
pub struct Store {
    ptr: NonNull<c_void>,
    host: String,
    port: u16,
}

// SAFETY: c10d stores are safe to use from any thread (TCPStore serialises
// its client socket with a mutex); the handle is freed once, in Drop.
unsafe impl Send for Store {}
// SAFETY: as above.
unsafe impl Sync for Store {}

impl Store {
    /// A `TCPStore` at `host:port`: the server (hosting the store in this
    /// process, as rank 0 does without torchrun's agent) when `is_server`,
    /// else a client, which retries connecting until `timeout`. `world` is
    /// the number of processes that will use it. Keys are prefixed with
    /// `prefix` when it is not empty.
    pub fn tcp(
        host: &str,
        port: u16,
        is_server: bool,
        world: usize,
        timeout: Duration,
        prefix: &str,
    ) -> Result<Self> {
        let h = cstring("TCPStore host", host)?;
        let p = cstring("TCPStore prefix", prefix)?;
        let mut err = ErrBuf::new();
        // SAFETY: valid NUL-terminated strings and an error buffer of ERR_LEN.
        let ptr = unsafe {
            bv2w_c10d_store_new(
                h.as_ptr(),
                c_int::from(port),
                c_int::from(is_server),
                c_int::try_from(world).unwrap_or(c_int::MAX),
                millis(timeout),
                p.as_ptr(),
                err.ptr(),
                ERR_LEN,
            )
        };
        let role = if is_server {
            "hosting"
        } else {
            "connecting to"
        };
        NonNull::new(ptr)
            .map(|ptr| Self {
                ptr,
                host: host.into(),
                port,
            })
            .ok_or_else(|| err.into_error(&format!("TCPStore {role} {host}:{port}")))
    }

    fn what(&self, op: &str, key: &str) -> String {
        format!("TCPStore {}:{} {op} {key:?}", self.host, self.port)
    }

    /// Sets `key` to `value`.
    pub fn set(&self, key: &str, value: &[u8]) -> Result<()> {
        let k = cstring("store key", key)?;
        let mut err = ErrBuf::new();
        // SAFETY: live handle, NUL-terminated key, `value` valid for its length.
        let rc = unsafe {
            bv2w_c10d_store_set(
                self.ptr.as_ptr(),
                k.as_ptr(),
                value.as_ptr(),
                value.len(),
                err.ptr(),
                ERR_LEN,
            )
        };
        if rc == 0 {
            Ok(())
        } else {
            Err(err.into_error(&self.what("set", key)))
        }
    }

    /// The value of `key`, waiting for it up to the store's timeout.
    pub fn get(&self, key: &str) -> Result<Vec<u8>> {
        let k = cstring("store key", key)?;
        let mut err = ErrBuf::new();
        let mut out: *mut u8 = std::ptr::null_mut();
        let mut len = 0usize;
        // SAFETY: live handle, NUL-terminated key, valid out-pointers.
        let rc = unsafe {
            bv2w_c10d_store_get(
                self.ptr.as_ptr(),
                k.as_ptr(),
                &mut out,
                &mut len,
                err.ptr(),
                ERR_LEN,
            )
        };
        if rc != 0 {
            return Err(err.into_error(&self.what("get", key)));
        }
        // SAFETY: on success `out` is a malloc'd buffer of `len` bytes, copied
        // here and then freed once with the shim's free.
        unsafe {
            let v = std::slice::from_raw_parts(out, len).to_vec();
            bv2w_c10d_free(out.cast());
            Ok(v)
        }
    }

    /// Adds `delta` to the counter at `key` (0 when absent); the new value.
    pub fn add(&self, key: &str, delta: i64) -> Result<i64> {
        let k = cstring("store key", key)?;
        let mut err = ErrBuf::new();
        let mut out = 0i64;
        // SAFETY: live handle, NUL-terminated key, valid out-pointer.
        let rc = unsafe {
            bv2w_c10d_store_add(
                self.ptr.as_ptr(),
                k.as_ptr(),
                delta,
                &mut out,
                err.ptr(),
                ERR_LEN,
            )
        };
        if rc == 0 {
            Ok(out)
        } else {
            Err(err.into_error(&self.what("add", key)))
        }
    }

    /// Whether `key` exists, without waiting.
    pub fn check(&self, key: &str) -> Result<bool> {
        let k = cstring("store key", key)?;
        let mut err = ErrBuf::new();
        // SAFETY: live handle, NUL-terminated key.
        let rc =
            unsafe { bv2w_c10d_store_check(self.ptr.as_ptr(), k.as_ptr(), err.ptr(), ERR_LEN) };
        match rc {
            0 => Ok(false),
            1 => Ok(true),
            _ => Err(err.into_error(&self.what("check", key))),
        }
    }
}

impl Drop for Store {
    fn drop(&mut self) {
        // SAFETY: the handle came from bv2w_c10d_store_new and is freed once.
        unsafe { bv2w_c10d_store_free(self.ptr.as_ptr()) }
    }
}

/// Which c10d backend a [`ProcessGroup`] runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Backend {
    /// Gloo: CPU tensors.
    Gloo,
    /// NCCL: CUDA tensors on device `device` (this rank's `LOCAL_RANK`).
    Nccl {
        /// The CUDA device index.
        device: usize,
    },
}

impl Backend {
    /// Its name in PyTorch (`gloo`, `nccl`).
    pub fn name(self) -> &'static str {
        match self {
            Self::Gloo => "gloo",
            Self::Nccl { .. } => "nccl",
        }
    }
}

/// How [`ProcessGroup::all_reduce`] combines the ranks' tensors.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ReduceOp {
    /// The sum over the ranks.
    Sum,
    /// The mean over the ranks (the sum divided by the world size, on every
    /// backend: Gloo has no native average).
    Avg,
}

/// A c10d process group of `world` ranks; collectives must be called in the
/// same order on every rank.
#[derive(Debug)]
pub struct ProcessGroup {
    ptr: NonNull<c_void>,
    rank: usize,
    world: usize,
    backend: Backend,
}

// SAFETY: c10d backends are driven from one thread at a time here (the
// owner's), and their own worker threads are internal; freed once in Drop.
unsafe impl Send for ProcessGroup {}

impl ProcessGroup {
    /// Joins the group over `store` (every rank must call this with the same
    /// `world` and backend); collectives fail after `timeout`.
    pub fn new(
        store: &Store,
        rank: usize,
        world: usize,
        backend: Backend,
        timeout: Duration,
    ) -> Result<Self> {
        let mut err = ErrBuf::new();
        let r = c_int::try_from(rank).unwrap_or(c_int::MAX);
        let w = c_int::try_from(world).unwrap_or(c_int::MAX);
        // SAFETY: a live store handle and an error buffer of ERR_LEN.
        let ptr = unsafe {
            match backend {
                Backend::Gloo => bv2w_c10d_gloo_new(
                    store.ptr.as_ptr(),
                    r,
                    w,
                    millis(timeout),
                    err.ptr(),
                    ERR_LEN,
                ),
                Backend::Nccl { device } => bv2w_c10d_nccl_new(
                    store.ptr.as_ptr(),
                    r,
                    w,
                    c_int::try_from(device).unwrap_or(c_int::MAX),
                    millis(timeout),
                    err.ptr(),
                    ERR_LEN,
                ),
            }
        };
        NonNull::new(ptr)
            .map(|ptr| Self {
                ptr,
                rank,
                world,
                backend,
            })
            .ok_or_else(|| {
                err.into_error(&format!(
                    "creating the {} process group (rank {rank} of {world})",
                    backend.name()
                ))
            })
    }

    /// This process's rank.
    pub fn rank(&self) -> usize {
        self.rank
    }

    /// The number of ranks.
    pub fn world(&self) -> usize {
        self.world
    }

    /// The backend.
    pub fn backend(&self) -> Backend {
        self.backend
    }

    fn check_dense(&self, t: &Tensor, op: &str) -> Result<()> {
        if !t.is_contiguous() {
            return Err(TorchExtError::C10d(format!(
                "{op}: the tensor must be contiguous (shape {:?})",
                t.size()
            )));
        }
        Ok(())
    }

    /// Starts summing the contiguous tensor `t` over all ranks, in place;
    /// [`Work::wait`] for the result.
    pub fn start_all_reduce_sum(&self, t: &Tensor) -> Result<Work> {
        self.check_dense(t, "all-reduce")?;
        let mut err = ErrBuf::new();
        // SAFETY: a live group; `as_ptr` is the `at::Tensor*` the shim copies
        // (a reference-counted handle, so the storage lives with the work).
        let ptr = unsafe {
            bv2w_c10d_all_reduce(
                self.ptr.as_ptr(),
                t.as_ptr() as *mut c_void,
                err.ptr(),
                ERR_LEN,
            )
        };
        NonNull::new(ptr)
            .map(|ptr| Work { ptr })
            .ok_or_else(|| err.into_error(&format!("{} all-reduce", self.backend.name())))
    }

    /// Sums the contiguous tensor `t` over all ranks, in place.
    pub fn all_reduce_sum(&self, t: &mut Tensor) -> Result<()> {
        self.start_all_reduce_sum(t)?.wait()
    }

    /// Combines the contiguous tensor `t` over all ranks by `op`, in place.
    pub fn all_reduce(&self, t: &mut Tensor, op: ReduceOp) -> Result<()> {
        self.all_reduce_sum(t)?;
        if op == ReduceOp::Avg {
            let _ = t.g_div_scalar_(self.world as f64);
        }
        Ok(())
    }

    /// Replaces `t` on every rank by rank `root`'s `t`.
    pub fn broadcast(&self, t: &mut Tensor, root: usize) -> Result<()> {
        self.check_dense(t, "broadcast")?;
        let mut err = ErrBuf::new();
        // SAFETY: a live group and a live tensor handle.
        let rc = unsafe {
            bv2w_c10d_broadcast(
                self.ptr.as_ptr(),
                t.as_ptr() as *mut c_void,
                c_int::try_from(root).unwrap_or(c_int::MAX),
                err.ptr(),
                ERR_LEN,
            )
        };
        if rc == 0 {
            Ok(())
        } else {
            Err(err.into_error(&format!(
                "{} broadcast from rank {root}",
                self.backend.name()
            )))
        }
    }

    /// Every rank's `t` (same shape and dtype everywhere), in rank order.
    pub fn all_gather(&self, t: &Tensor) -> Result<Vec<Tensor>> {
        self.check_dense(t, "all-gather")?;
        let outs: Vec<Tensor> = (0..self.world).map(|_| t.empty_like()).collect();
        let ptrs: Vec<*mut c_void> = outs.iter().map(|o| o.as_ptr() as *mut c_void).collect();
        let mut err = ErrBuf::new();
        // SAFETY: a live group, live tensor handles, `ptrs` holds `world` of them.
        let rc = unsafe {
            bv2w_c10d_all_gather(
                self.ptr.as_ptr(),
                t.as_ptr() as *mut c_void,
                ptrs.as_ptr(),
                c_int::try_from(self.world).unwrap_or(c_int::MAX),
                err.ptr(),
                ERR_LEN,
            )
        };
        if rc == 0 {
            Ok(outs)
        } else {
            Err(err.into_error(&format!("{} all-gather", self.backend.name())))
        }
    }

    /// Waits until every rank has called it.
    pub fn barrier(&self) -> Result<()> {
        let mut err = ErrBuf::new();
        // SAFETY: a live group.
        let rc = unsafe { bv2w_c10d_barrier(self.ptr.as_ptr(), err.ptr(), ERR_LEN) };
        if rc == 0 {
            Ok(())
        } else {
            Err(err.into_error(&format!("{} barrier", self.backend.name())))
        }
    }
}

impl Drop for ProcessGroup {
    fn drop(&mut self) {
        // SAFETY: the handle came from a constructor above and is freed once
        // (the shim shuts the backend down first: NCCL destroys its
        // communicators, Gloo joins its threads).
        unsafe { bv2w_c10d_group_free(self.ptr.as_ptr()) }
    }
}

/// A collective in flight; [`Self::wait`] for it (dropping it unwaited lets
/// it finish in the background).
#[derive(Debug)]
pub struct Work {
    ptr: NonNull<c_void>,
}

// SAFETY: a c10d Work may be waited on from any thread; freed once in Drop.
unsafe impl Send for Work {}

impl Work {
    /// Waits for the collective (up to the group's timeout).
    pub fn wait(self) -> Result<()> {
        let mut err = ErrBuf::new();
        // SAFETY: a live work handle.
        let rc = unsafe { bv2w_c10d_work_wait(self.ptr.as_ptr(), err.ptr(), ERR_LEN) };
        if rc == 0 {
            Ok(())
        } else {
            Err(err.into_error("waiting for a collective"))
        }
    }
}

impl Drop for Work {
    fn drop(&mut self) {
        // SAFETY: the handle came from bv2w_c10d_all_reduce and is freed once.
        unsafe { bv2w_c10d_work_free(self.ptr.as_ptr()) }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn free_port() -> u16 {
        std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port()
    }

    #[test]
    fn store_and_gloo_collectives_across_three_ranks() {
        assert!(has_gloo(), "this build has no Gloo backend");
        let port = free_port();
        let world = 3;
        let timeout = Duration::from_secs(30);
        let handles: Vec<_> = (0..world)
            .map(|rank| {
                std::thread::spawn(move || {
                    let store =
                        Store::tcp("127.0.0.1", port, rank == 0, world, timeout, "t/").unwrap();
                    store.set(&format!("r{rank}"), &[rank as u8; 3]).unwrap();
                    assert_eq!(store.get("r0").unwrap(), vec![0u8; 3]);
                    assert_eq!(store.get("r2").unwrap(), vec![2u8; 3]);
                    assert!(store.check("r1").unwrap() || rank != 1);
                    assert!(!store.check("never").unwrap());
                    let added = store.add("count", 1).unwrap();
                    assert!((1..=3).contains(&added));
                    let pg =
                        ProcessGroup::new(&store, rank, world, Backend::Gloo, timeout).unwrap();
                    let mut t = Tensor::from_slice(&[1.0f32, 2.0, 3.0]) * (rank as f64 + 1.0);
                    pg.all_reduce_sum(&mut t).unwrap();
                    // (1 + 2 + 3) * [1, 2, 3]
                    assert_eq!(Vec::<f32>::try_from(&t).unwrap(), vec![6.0, 12.0, 18.0]);
                    let mut a = Tensor::from_slice(&[rank as f64, 3.0]);
                    pg.all_reduce(&mut a, ReduceOp::Avg).unwrap();
                    assert_eq!(Vec::<f64>::try_from(&a).unwrap(), vec![1.0, 3.0]);
                    let mut b = Tensor::from_slice(&[rank as f64; 2]);
                    pg.broadcast(&mut b, 2).unwrap();
                    assert_eq!(Vec::<f64>::try_from(&b).unwrap(), vec![2.0, 2.0]);
                    let g = pg.all_gather(&Tensor::from_slice(&[rank as i64])).unwrap();
                    let got: Vec<i64> = g.iter().map(|t| t.int64_value(&[0])).collect();
                    assert_eq!(got, vec![0, 1, 2]);
                    pg.barrier().unwrap();
                    let err =
                        pg.all_reduce_sum(&mut Tensor::ones([2, 2], tch::kind::FLOAT_CPU).tr());
                    assert!(err.unwrap_err().to_string().contains("contiguous"));
                })
            })
            .collect();
        for h in handles {
            h.join().unwrap();
        }
    }

    #[test]
    fn a_missing_peer_is_a_timeout_error_not_a_hang() {
        let port = free_port();
        let store = Store::tcp("127.0.0.1", port, true, 2, Duration::from_millis(500), "").unwrap();
        let e = store.get("never-set").unwrap_err().to_string();
        assert!(e.contains("never-set") && e.contains("127.0.0.1"), "{e}");
        let e = Store::tcp(
            "127.0.0.1",
            free_port(),
            false,
            2,
            Duration::from_millis(300),
            "",
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("connecting to 127.0.0.1"), "{e}");
    }
}
