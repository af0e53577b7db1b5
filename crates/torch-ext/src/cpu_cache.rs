//! A caching CPU allocator for libtorch (`csrc/cpu_cache.cpp`).
//!
//! glibc hands blocks above its mmap threshold back to the kernel when they
//! are freed, so each forward pass page-faults (and the kernel zeroes) the
//! memory of its activations again. With the cache installed, freed blocks of
//! 64 KiB or more are kept in free lists keyed by size class and reused, as
//! PyTorch's CUDA caching allocator does for device memory. Smaller blocks go
//! to `malloc` as before.
//!
//! The binary installs it at start (see `bridgev2w`'s `main`); a library
//! embedded in another process (the Python package) leaves libtorch's
//! allocator alone. Tensors allocated before [`install`] keep their own
//! deleter, so installing late is safe.

use std::ffi::c_int;

extern "C" {
    fn bv2w_cpu_cache_install(limit_bytes: u64);
    fn bv2w_cpu_cache_active() -> c_int;
    fn bv2w_cpu_cache_stats(hits: *mut u64, misses: *mut u64, cached_bytes: *mut u64);
    fn bv2w_cpu_cache_release();
    fn bv2w_cpu_cache_memory(live: *mut u64, peak: *mut u64);
    fn bv2w_cpu_cache_reset_peak();
}

/// The cache's counters.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct CacheStats {
    /// Allocations served from the cache.
    pub hits: u64,
    /// Allocations of cached sizes that needed a fresh block.
    pub misses: u64,
    /// Bytes held in free blocks now.
    pub cached_bytes: u64,
}

/// Makes the caching allocator libtorch's CPU allocator, holding at most
/// `limit_bytes` of free blocks (beyond it the least recently freed ones are
/// released). A second call only changes the limit.
pub fn install(limit_bytes: u64) {
    // SAFETY: the shim takes a plain integer; it registers a static
    // allocator once (std::call_once) and sets the limit under a mutex.
    unsafe { bv2w_cpu_cache_install(limit_bytes) }
}

/// Whether libtorch's CPU allocator is the caching one.
pub fn is_active() -> bool {
    // SAFETY: reads libtorch's allocator registry; no arguments.
    unsafe { bv2w_cpu_cache_active() != 0 }
}

/// The cache's counters (zeros before [`install`]).
pub fn stats() -> CacheStats {
    let mut s = CacheStats::default();
    // SAFETY: three valid, exclusive pointers to u64 for the shim to write.
    unsafe { bv2w_cpu_cache_stats(&mut s.hits, &mut s.misses, &mut s.cached_bytes) };
    s
}

/// Frees every cached block (memory back to the system).
pub fn release() {
    // SAFETY: no arguments; the shim frees its free lists under its mutex.
    unsafe { bv2w_cpu_cache_release() }
}

/// Memory in use through the caching allocator: blocks handed out and not
/// freed (their size classes, so a little above the tensors' bytes; tensors
/// allocated before [`install`] are not counted). The CPU counterpart of
/// CUDA's `memory_allocated` / `max_memory_allocated`: what a computation
/// needs, without the cache's free blocks or the process's other memory.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct MemoryStats {
    /// Bytes in use now.
    pub live_bytes: u64,
    /// The most bytes in use at once since [`reset_peak`] (or the start).
    pub peak_bytes: u64,
}

/// The bytes in use now and their peak (zeros before [`install`]).
pub fn memory() -> MemoryStats {
    let mut m = MemoryStats::default();
    // SAFETY: two valid, exclusive pointers to u64 for the shim to write.
    unsafe { bv2w_cpu_cache_memory(&mut m.live_bytes, &mut m.peak_bytes) };
    m
}

/// Starts a new peak from the bytes in use now.
pub fn reset_peak() {
    // SAFETY: no arguments; atomics in the shim.
    unsafe { bv2w_cpu_cache_reset_peak() }
}

/// The limit `install_from_env` uses: `BRIDGEV2W_CPU_CACHE_MB` megabytes
/// (0 = no cache), by default [`default_limit`].
pub fn limit_from_env() -> Result<u64, String> {
    match std::env::var("BRIDGEV2W_CPU_CACHE_MB") {
        Err(_) => Ok(default_limit(physical_memory_bytes())),
        Ok(v) => v.trim().parse::<u64>().map(|mb| mb << 20).map_err(|_| {
            format!(
                "BRIDGEV2W_CPU_CACHE_MB={v:?}: expected whole megabytes (0 turns the cache off)"
            )
        }),
    }
}

/// The default limit for a machine with `physical` bytes of memory (`None`:
/// unknown): a quarter of it, at least 2 GiB and at most 8 GiB. A VAE decode
/// at `bench model`'s default shapes ran as fast with 4 GiB as with 8, and
/// about 14% slower with 2 (`docs/benchmarks.md`).
pub fn default_limit(physical: Option<u64>) -> u64 {
    const GIB: u64 = 1 << 30;
    physical.map_or(2 * GIB, |m| (m / 4).clamp(2 * GIB, 8 * GIB))
}

/// `MemTotal` of `/proc/meminfo`, where there is one.
fn physical_memory_bytes() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemTotal:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib << 10)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use tch::{Device, Kind, Tensor};

    #[test]
    fn the_default_limit_is_a_quarter_of_memory_within_bounds() {
        const GIB: u64 = 1 << 30;
        assert_eq!(default_limit(Some(24 * GIB)), 6 * GIB);
        assert_eq!(default_limit(Some(4 * GIB)), 2 * GIB);
        assert_eq!(default_limit(Some(512 * GIB)), 8 * GIB);
        assert_eq!(default_limit(None), 2 * GIB);
        if cfg!(target_os = "linux") {
            assert!(physical_memory_bytes().is_some_and(|m| m > GIB));
        }
    }

    /// One test (the allocator is process-wide): results equal, blocks reused,
    /// the limit honoured by releasing the oldest free blocks, release empties
    /// the cache.
    #[test]
    fn the_cache_reuses_freed_blocks_and_computes_the_same() {
        tch::manual_seed(0);
        let a = Tensor::randn([256, 256], (Kind::Float, Device::Cpu));
        let before = a.matmul(&a).sum(Kind::Double).double_value(&[]);
        assert!(!is_active());
        install(64 << 20);
        assert!(is_active());
        let s0 = stats();
        for _ in 0..5 {
            // 256 KiB results: cached sizes.
            let c = a.matmul(&a);
            assert_eq!(c.sum(Kind::Double).double_value(&[]), before);
        }
        let s1 = stats();
        assert!(s1.hits >= s0.hits + 4, "{s0:?} -> {s1:?}");
        assert!(s1.cached_bytes > 0 && s1.cached_bytes <= 64 << 20, "{s1:?}");
        // A tensor from before the install is freed by its own deleter.
        drop(a);
        // Above the limit nothing is kept.
        install(0);
        release();
        let big = Tensor::zeros([1 << 20], (Kind::Float, Device::Cpu));
        drop(big);
        assert_eq!(stats().cached_bytes, 0);
        install(64 << 20);
        let big = Tensor::ones([1 << 20], (Kind::Float, Device::Cpu));
        assert_eq!(big.sum(Kind::Double).double_value(&[]), (1 << 20) as f64);
        drop(big);
        assert!(stats().cached_bytes >= 4 << 20);
        // A reused block is not assumed zeroed by libtorch: zeros() still zeroes.
        let z = Tensor::zeros([1 << 20], (Kind::Float, Device::Cpu));
        assert_eq!(z.abs().sum(Kind::Double).double_value(&[]), 0.0);
        drop(z);
        // Over the limit the least recently freed blocks make room: of an
        // 8 MiB and then a 6 MiB block under a 12 MiB limit, the 6 MiB one
        // stays (before, the later block was the one let go).
        install(12 << 20);
        release();
        let a8 = Tensor::ones([2 << 20], (Kind::Float, Device::Cpu));
        let b6 = Tensor::ones([3 << 19], (Kind::Float, Device::Cpu));
        drop(a8);
        assert!(stats().cached_bytes >= 8 << 20);
        drop(b6);
        let s = stats();
        assert!(
            s.cached_bytes >= 6 << 20 && s.cached_bytes <= 12 << 20,
            "{s:?}"
        );
        let b6 = Tensor::empty([3 << 19], (Kind::Float, Device::Cpu));
        assert!(stats().hits > s.hits, "the 6 MiB block was kept: {s:?}");
        drop(b6);
        assert!(stats().cached_bytes <= 12 << 20);
        release();
        assert_eq!(stats().cached_bytes, 0);
        // Memory in use: a 16 MiB tensor counts while it lives, its peak
        // stays after it is freed, and a reset starts from what is in use.
        reset_peak();
        let m0 = memory();
        let t = Tensor::ones([4 << 20], (Kind::Float, Device::Cpu));
        let m1 = memory();
        assert!(
            m1.live_bytes >= m0.live_bytes + (16 << 20),
            "{m0:?} -> {m1:?}"
        );
        drop(t);
        let m2 = memory();
        assert!(
            m2.live_bytes + (16 << 20) <= m1.live_bytes,
            "{m1:?} -> {m2:?}"
        );
        assert!(
            m2.peak_bytes >= m0.live_bytes + (16 << 20),
            "{m0:?} -> {m2:?}"
        );
        reset_peak();
        let m3 = memory();
        assert!(m3.peak_bytes < m2.peak_bytes, "{m2:?} -> {m3:?}");
        assert!(m3.peak_bytes >= m3.live_bytes, "{m3:?}");
    }
}
