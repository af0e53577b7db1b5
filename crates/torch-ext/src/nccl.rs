//! NCCL, loaded at run time with `dlopen("libnccl.so.2")`: on a CUDA machine
//! libtorch_cuda has already loaded it (the PyPI wheel depends on it), and
//! `dlopen` returns that copy; on a CPU-only machine nothing links against
//! NCCL and [`Nccl::load`] reports that it is missing.
//!
//! Only what data-parallel training needs: a unique id (made by rank 0 and
//! sent to the others by the caller), a communicator per process, an
//! in-place sum all-reduce of a float32 CUDA tensor on libtorch's current
//! stream of that device (the legacy default stream, as tch never changes
//! it), and destruction.
//!
//! Untested here: the machine that develops this crate has no GPU.

use crate::{Result, TorchExtError};
use std::ffi::{c_char, c_int, c_void, CStr};
use std::sync::Arc;

/// `ncclUniqueId`: 128 opaque bytes that every rank must pass to
/// [`Nccl::init_rank`].
pub const UNIQUE_ID_BYTES: usize = 128;

#[repr(C)]
#[derive(Clone, Copy)]
struct RawUniqueId {
    internal: [c_char; UNIQUE_ID_BYTES],
}

type NcclResult = c_int;
type GetUniqueIdFn = unsafe extern "C" fn(*mut RawUniqueId) -> NcclResult;
type CommInitRankFn =
    unsafe extern "C" fn(*mut *mut c_void, c_int, RawUniqueId, c_int) -> NcclResult;
type AllReduceFn = unsafe extern "C" fn(
    *const c_void,
    *mut c_void,
    usize,
    c_int,
    c_int,
    *mut c_void,
    *mut c_void,
) -> NcclResult;
type CommDestroyFn = unsafe extern "C" fn(*mut c_void) -> NcclResult;
type GetErrorStringFn = unsafe extern "C" fn(NcclResult) -> *const c_char;

const NCCL_FLOAT32: c_int = 7;
const NCCL_SUM: c_int = 0;

extern "C" {
    fn bv2w_cuda_set_device(index: c_int) -> c_int;
    fn bv2w_cuda_current_stream(index: c_int, out: *mut *mut c_void) -> c_int;
}

struct Lib {
    handle: *mut c_void,
    get_unique_id: GetUniqueIdFn,
    comm_init_rank: CommInitRankFn,
    all_reduce: AllReduceFn,
    comm_destroy: CommDestroyFn,
    get_error_string: GetErrorStringFn,
}

// SAFETY: the handle and function pointers are immutable after loading and
// NCCL's entry points may be called from any thread.
unsafe impl Send for Lib {}
// SAFETY: as above.
unsafe impl Sync for Lib {}

impl Drop for Lib {
    fn drop(&mut self) {
        // SAFETY: `handle` came from a successful dlopen and is closed once.
        unsafe {
            libc::dlclose(self.handle);
        }
    }
}

fn dlerror_text() -> String {
    // SAFETY: dlerror returns null or a NUL-terminated string valid until the
    // next dl* call on this thread; it is copied at once.
    unsafe {
        let e = libc::dlerror();
        if e.is_null() {
            "unknown error".into()
        } else {
            CStr::from_ptr(e).to_string_lossy().into_owned()
        }
    }
}

/// The symbol `name` of the library `handle` as a function pointer `F`.
///
/// # Safety
/// `handle` must be a live `dlopen` handle and `F` the function-pointer type
/// of the symbol's C declaration.
unsafe fn symbol<F: Copy>(handle: *mut c_void, name: &CStr) -> Result<F> {
    debug_assert_eq!(std::mem::size_of::<F>(), std::mem::size_of::<*mut c_void>());
    // SAFETY: the caller's contract; `name` is NUL-terminated.
    let p = unsafe { libc::dlsym(handle, name.as_ptr()) };
    if p.is_null() {
        return Err(TorchExtError::Nccl(format!(
            "libnccl.so.2 has no {} ({})",
            name.to_string_lossy(),
            dlerror_text()
        )));
    }
    // SAFETY: a non-null symbol address reinterpreted as the function pointer
    // type the caller vouches for (same size, checked above in debug builds).
    Ok(unsafe { std::mem::transmute_copy::<*mut c_void, F>(&p) })
}

/// The loaded NCCL library.
#[derive(Clone)]
pub struct Nccl {
    lib: Arc<Lib>,
}

impl std::fmt::Debug for Nccl {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Nccl(libnccl.so.2)")
    }
}

impl Nccl {
    /// Loads `libnccl.so.2` (the copy libtorch_cuda loaded, else the dynamic
    /// loader's search path: `LD_LIBRARY_PATH`, ...).
    pub fn load() -> Result<Self> {
        let name = c"libnccl.so.2";
        // SAFETY: a NUL-terminated name; dlopen has no other preconditions.
        let handle = unsafe { libc::dlopen(name.as_ptr(), libc::RTLD_NOW | libc::RTLD_LOCAL) };
        if handle.is_null() {
            return Err(TorchExtError::Nccl(format!(
                "cannot load libnccl.so.2 ({}): data-parallel training on CUDA needs NCCL \
                 (the PyPI torch wheel brings it as nvidia-nccl; or set LD_LIBRARY_PATH)",
                dlerror_text()
            )));
        }
        let load = || -> Result<Lib> {
            // SAFETY: `handle` is a live dlopen handle, and the type is the
            // signature nccl.h (NCCL 2.x) declares for the symbol.
            let get_unique_id = unsafe { symbol::<GetUniqueIdFn>(handle, c"ncclGetUniqueId")? };
            // SAFETY: as above.
            let comm_init_rank = unsafe { symbol::<CommInitRankFn>(handle, c"ncclCommInitRank")? };
            // SAFETY: as above.
            let all_reduce = unsafe { symbol::<AllReduceFn>(handle, c"ncclAllReduce")? };
            // SAFETY: as above.
            let comm_destroy = unsafe { symbol::<CommDestroyFn>(handle, c"ncclCommDestroy")? };
            // SAFETY: as above.
            let get_error_string =
                unsafe { symbol::<GetErrorStringFn>(handle, c"ncclGetErrorString")? };
            Ok(Lib {
                handle,
                get_unique_id,
                comm_init_rank,
                all_reduce,
                comm_destroy,
                get_error_string,
            })
        };
        match load() {
            Ok(lib) => Ok(Self { lib: Arc::new(lib) }),
            Err(e) => {
                // SAFETY: the handle is not used after this.
                unsafe {
                    libc::dlclose(handle);
                }
                Err(e)
            }
        }
    }

    fn check(&self, call: &str, rc: NcclResult) -> Result<()> {
        if rc == 0 {
            return Ok(());
        }
        // SAFETY: ncclGetErrorString returns a static NUL-terminated string.
        let text = unsafe {
            let p = (self.lib.get_error_string)(rc);
            if p.is_null() {
                String::new()
            } else {
                CStr::from_ptr(p).to_string_lossy().into_owned()
            }
        };
        Err(TorchExtError::Nccl(format!(
            "{call} failed: {text} (code {rc})"
        )))
    }

    /// A new unique id (rank 0 makes it; every rank passes it to [`Self::init_rank`]).
    pub fn unique_id(&self) -> Result<[u8; UNIQUE_ID_BYTES]> {
        let mut id = RawUniqueId {
            internal: [0; UNIQUE_ID_BYTES],
        };
        // SAFETY: `id` is a valid, writable ncclUniqueId.
        let rc = unsafe { (self.lib.get_unique_id)(&mut id) };
        self.check("ncclGetUniqueId", rc)?;
        Ok(id.internal.map(|c| c as u8))
    }

    /// This process's communicator: rank `rank` of `world`, on CUDA device
    /// `device` (made the current device first, as NCCL requires).
    /// Blocks until every rank has called it.
    pub fn init_rank(
        &self,
        id: &[u8; UNIQUE_ID_BYTES],
        world: usize,
        rank: usize,
        device: usize,
    ) -> Result<NcclComm> {
        let dev = c_int::try_from(device)
            .map_err(|_| TorchExtError::Nccl(format!("cuda device {device} out of range")))?;
        // SAFETY: a plain C function taking an int; exceptions are caught.
        if unsafe { bv2w_cuda_set_device(dev) } != 0 {
            return Err(TorchExtError::Nccl(format!(
                "cannot make cuda:{device} the current device (is CUDA available to libtorch?)"
            )));
        }
        let (world_c, rank_c) = match (c_int::try_from(world), c_int::try_from(rank)) {
            (Ok(w), Ok(r)) => (w, r),
            _ => {
                return Err(TorchExtError::Nccl(format!(
                    "world size {world} / rank {rank} out of range"
                )))
            }
        };
        let raw = RawUniqueId {
            internal: id.map(|b| b as c_char),
        };
        let mut comm: *mut c_void = std::ptr::null_mut();
        // SAFETY: `comm` is a writable pointer slot; the id is passed by
        // value as nccl.h declares; rank < world is the caller's contract,
        // checked by NCCL too.
        let rc = unsafe { (self.lib.comm_init_rank)(&mut comm, world_c, raw, rank_c) };
        self.check("ncclCommInitRank", rc)?;
        Ok(NcclComm {
            nccl: self.clone(),
            comm,
            device: dev,
        })
    }
}

/// One process's NCCL communicator; destroyed when dropped.
pub struct NcclComm {
    nccl: Nccl,
    comm: *mut c_void,
    device: c_int,
}

// SAFETY: an NCCL communicator may be used from any thread as long as calls
// on it do not overlap; `NcclComm` is not `Sync` and its methods take `&self`
// only through one owner at a time, so moving it to another thread is sound.
unsafe impl Send for NcclComm {}

impl std::fmt::Debug for NcclComm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "NcclComm(cuda:{})", self.device)
    }
}

impl NcclComm {
    /// Sums `t` over all ranks, in place: `t` must be a contiguous float32
    /// tensor on this communicator's CUDA device. Enqueued on libtorch's
    /// current stream of the device, so later torch ops see the result.
    pub fn all_reduce_sum(&self, t: &mut tch::Tensor) -> Result<()> {
        if t.device() != tch::Device::Cuda(self.device as usize) {
            return Err(TorchExtError::Nccl(format!(
                "all-reduce of a tensor on {:?}, the communicator is on cuda:{}",
                t.device(),
                self.device
            )));
        }
        if t.kind() != tch::Kind::Float || !t.is_contiguous() {
            return Err(TorchExtError::Nccl(format!(
                "all-reduce needs a contiguous float32 tensor, got {:?}",
                t.kind()
            )));
        }
        let count = t.numel();
        let ptr = t.data_ptr();
        let mut stream: *mut c_void = std::ptr::null_mut();
        // SAFETY: `stream` is a writable slot; exceptions are caught.
        if unsafe { bv2w_cuda_current_stream(self.device, &mut stream) } != 0 {
            return Err(TorchExtError::Nccl(format!(
                "cannot get libtorch's current stream of cuda:{}",
                self.device
            )));
        }
        // SAFETY: `ptr` points to `count` contiguous f32 values on this
        // communicator's device, alive (borrowed mutably) for the call; the
        // operation is ordered on `stream` with the kernels that wrote and
        // will read the buffer. In place: send and receive buffers are equal.
        let rc = unsafe {
            (self.nccl.lib.all_reduce)(ptr, ptr, count, NCCL_FLOAT32, NCCL_SUM, self.comm, stream)
        };
        self.nccl.check("ncclAllReduce", rc)
    }
}

impl Drop for NcclComm {
    fn drop(&mut self) {
        // SAFETY: `comm` came from a successful ncclCommInitRank and is
        // destroyed once.
        let _ = unsafe { (self.nccl.lib.comm_destroy)(self.comm) };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn load_reports_a_clear_error_or_loads() {
        // Here (no GPU, but the wheel's nvidia-nccl may be on the loader's
        // path or not): either it loads, or the error names the library.
        match Nccl::load() {
            Ok(n) => assert!(format!("{n:?}").contains("nccl")),
            Err(e) => {
                let s = e.to_string();
                assert!(s.contains("libnccl.so.2"), "{s}");
            }
        }
    }
}
