// A caching CPU allocator for libtorch: freed blocks of 64 KiB or more are
// kept in size-keyed free lists and handed out again, instead of going back
// to glibc, which returns large blocks to the kernel (munmap) so that every
// new activation of a forward pass page-faults its memory in again. A
// request takes the smallest free block of its size class or up to a quarter
// larger. The
// CUDA caching allocator does the same for device memory; on this project's
// CPU profile the kernel's page clearing was about a quarter of a model
// call (docs/benchmarks.md).
//
// A block is [header (64 bytes: its rounded size) | data]; the deleter reads
// the header, so the DataPtr needs no context and the allocator is "simple"
// (raw_deleter is set). Blocks of 2 MiB or more are 2 MiB-aligned and
// advised as transparent huge pages, as libtorch's own allocator does with
// THP_MEM_ALLOC_ENABLE=1. The cache holds at most `limit` bytes of free
// blocks: a freed block that would exceed it releases the least recently
// freed blocks first (so blocks of sizes an earlier phase used, the
// transformer's before the VAE's, make room for the current phase's instead
// of filling the cache for good); a failed allocation releases the whole
// cache and tries once more.

#include <c10/core/Allocator.h>
#include <c10/core/CPUAllocator.h>
#include <c10/util/Exception.h>

#include <sys/mman.h>

#include <atomic>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <mutex>
#include <deque>
#include <map>

namespace {

constexpr size_t kHeader = 64;
constexpr size_t kMinCached = size_t(1) << 16;
constexpr size_t kHuge = size_t(2) << 20;

size_t round_up(size_t n, size_t to) { return (n + to - 1) / to * to; }

// The size class of a request of `n` data bytes (header included).
size_t size_class(size_t n) {
  size_t total = n + kHeader;
  if (total < kMinCached) return total;          // not cached
  if (total < (size_t(1) << 20)) return round_up(total, 4096);
  if (total < (size_t(16) << 20)) return round_up(total, size_t(64) << 10);
  return round_up(total, kHuge);
}

struct Stats {
  std::atomic<uint64_t> hits{0};
  std::atomic<uint64_t> misses{0};
  // Bytes of the blocks handed out and not yet freed (size classes, header
  // included; every block this allocator made, cached size or not), and the
  // most there were since the last reset: CPU counterparts of CUDA's
  // memory_allocated / max_memory_allocated.
  std::atomic<uint64_t> live{0};
  std::atomic<uint64_t> peak{0};
};

// A free block and when it was freed (a global counter).
struct Entry {
  void* base;
  uint64_t seq;
};

struct Cache {
  std::mutex mu;
  // size class -> its free blocks, oldest first.
  std::map<size_t, std::deque<Entry>> free_blocks;
  // when freed -> size class, over every free block: the oldest comes first.
  std::map<uint64_t, size_t> by_age;
  uint64_t next_seq = 0;
  size_t cached_bytes = 0;
  size_t limit = 0;
  Stats stats;

  // The most recently freed block of the first class in [cls, max_cls], or
  // nullptr. Caller holds mu.
  void* take(size_t cls, size_t max_cls) {
    auto it = free_blocks.lower_bound(cls);
    if (it == free_blocks.end() || it->first > max_cls) return nullptr;
    Entry e = it->second.back();
    it->second.pop_back();
    by_age.erase(e.seq);
    cached_bytes -= it->first;
    if (it->second.empty()) free_blocks.erase(it);
    return e.base;
  }

  // Releases the least recently freed blocks until `room` more bytes fit
  // under the limit (or nothing is left). Caller holds mu.
  void evict_for(size_t room) {
    while (!by_age.empty() && cached_bytes + room > limit) {
      auto oldest = by_age.begin();
      size_t cls = oldest->second;
      auto it = free_blocks.find(cls);
      // The oldest block overall is its class's oldest: the front.
      Entry e = it->second.front();
      it->second.pop_front();
      if (it->second.empty()) free_blocks.erase(it);
      by_age.erase(oldest);
      cached_bytes -= cls;
      std::free(e.base);
    }
  }

  void release_all() {
    std::lock_guard<std::mutex> g(mu);
    for (auto& kv : free_blocks)
      for (const Entry& e : kv.second) std::free(e.base);
    free_blocks.clear();
    by_age.clear();
    cached_bytes = 0;
  }
};

// Leaked on purpose: tensors may be freed by static destructors after main.
Cache* cache() {
  static Cache* c = new Cache();
  return c;
}

void* fresh_block(size_t cls) {
  size_t align = cls >= kHuge ? kHuge : kHeader;
  void* base = nullptr;
  if (posix_memalign(&base, align, cls) != 0) return nullptr;
#ifdef MADV_HUGEPAGE
  if (cls >= kHuge) madvise(base, cls, MADV_HUGEPAGE);
#endif
  return base;
}

void delete_block(void* data) {
  if (data == nullptr) return;
  void* base = static_cast<char*>(data) - kHeader;
  size_t cls = 0;
  std::memcpy(&cls, base, sizeof(cls));
  cache()->stats.live.fetch_sub(cls);
  if (cls < kMinCached) {
    std::free(base);
    return;
  }
  Cache* c = cache();
  {
    std::lock_guard<std::mutex> g(c->mu);
    if (cls <= c->limit) {
      c->evict_for(cls);
      uint64_t seq = c->next_seq++;
      c->free_blocks[cls].push_back({base, seq});
      c->by_age.emplace(seq, cls);
      c->cached_bytes += cls;
      return;
    }
  }
  std::free(base);
}

struct CachingCpuAllocator final : public c10::Allocator {
  c10::DataPtr allocate(size_t n) override {
    size_t cls = size_class(n);
    void* base = nullptr;
    Cache* c = cache();
    if (cls >= kMinCached) {
      std::lock_guard<std::mutex> g(c->mu);
      // Best fit: the smallest free class at least `cls`, at most a quarter
      // larger (the block keeps its own class in its header).
      base = c->take(cls, cls + cls / 4);
    }
    if (base != nullptr) {
      c->stats.hits++;
      // A free block up to a quarter larger: it keeps its own class.
      std::memcpy(&cls, base, sizeof(cls));
    } else {
      if (cls >= kMinCached) c->stats.misses++;
      base = fresh_block(cls);
      if (base == nullptr) {
        c->release_all();
        base = fresh_block(cls);
      }
      TORCH_CHECK(base != nullptr, "bridgev2w CPU allocator: out of memory allocating ", n,
                  " bytes");
      std::memcpy(base, &cls, sizeof(cls));
    }
    uint64_t now = c->stats.live.fetch_add(cls) + cls;
    uint64_t peak = c->stats.peak.load();
    while (now > peak && !c->stats.peak.compare_exchange_weak(peak, now)) {
    }
    void* data = static_cast<char*>(base) + kHeader;
    return {data, data, &delete_block, c10::Device(c10::DeviceType::CPU)};
  }

  c10::DeleterFnPtr raw_deleter() const override { return &delete_block; }

  void copy_data(void* dest, const void* src, std::size_t count) const override {
    default_copy_data(dest, src, count);
  }
};

}  // namespace

extern "C" {

// Makes the caching allocator libtorch's CPU allocator, keeping at most
// `limit_bytes` of free blocks. Idempotent (a second call only sets the limit).
void bv2w_cpu_cache_install(uint64_t limit_bytes) {
  static std::once_flag once;
  {
    std::lock_guard<std::mutex> g(cache()->mu);
    cache()->limit = static_cast<size_t>(limit_bytes);
    cache()->evict_for(0);
  }
  std::call_once(once, [] {
    static CachingCpuAllocator alloc;
    // Priority above the default allocator's registration (0).
    c10::SetCPUAllocator(&alloc, /*priority=*/1);
  });
}

// Whether libtorch's current CPU allocator is the caching one.
int bv2w_cpu_cache_active() {
  return dynamic_cast<CachingCpuAllocator*>(c10::GetCPUAllocator()) != nullptr ? 1 : 0;
}

// Cache statistics: hits, misses (fresh blocks of cached sizes), bytes held free.
void bv2w_cpu_cache_stats(uint64_t* hits, uint64_t* misses, uint64_t* cached_bytes) {
  Cache* c = cache();
  *hits = c->stats.hits.load();
  *misses = c->stats.misses.load();
  std::lock_guard<std::mutex> g(c->mu);
  *cached_bytes = c->cached_bytes;
}

// Frees every cached block.
void bv2w_cpu_cache_release() { cache()->release_all(); }

// Bytes of blocks in use now and at most since the last reset.
void bv2w_cpu_cache_memory(uint64_t* live, uint64_t* peak) {
  Cache* c = cache();
  *live = c->stats.live.load();
  *peak = c->stats.peak.load();
}

// Starts a new peak from the bytes in use now.
void bv2w_cpu_cache_reset_peak() {
  Cache* c = cache();
  c->stats.peak.store(c->stats.live.load());
}

}  // extern "C"
