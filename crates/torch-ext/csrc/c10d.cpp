// A C interface to PyTorch's distributed engine in libtorch (c10d): the
// TCPStore (server or client, optionally under a key prefix), the Gloo
// process group (CPU) and, from c10d_nccl.cpp, the NCCL one (CUDA). Handles
// are opaque pointers owned by the Rust side, which frees each exactly once.
//
// Every function catches C++ exceptions (c10::Error, c10d's DistBackendError,
// gloo's exceptions, std::exception) and reports them as a return code plus a
// message written into the caller's buffer: none may unwind into Rust.

#include <torch/csrc/distributed/c10d/Backend.hpp>
#include <torch/csrc/distributed/c10d/PrefixStore.hpp>
#include <torch/csrc/distributed/c10d/TCPStore.hpp>
#include <torch/csrc/distributed/c10d/Work.hpp>

#ifdef BV2W_HAVE_GLOO
#define USE_C10D_GLOO 1
#include <torch/csrc/distributed/c10d/ProcessGroupGloo.hpp>
#endif

#include <cstdlib>
#include <cstring>
#include <exception>
#include <string>
#include <vector>

#include "c10d_shim.h"

#define BV2W_TRY(fail_value)                \
  catch (...) {                             \
    bv2w_set_current_error(err, err_len);   \
    return fail_value;                      \
  }

extern "C" {

// 1 when this build has the Gloo backend, 0 otherwise.
int bv2w_c10d_has_gloo() {
#ifdef BV2W_HAVE_GLOO
  return 1;
#else
  return 0;
#endif
}

// A TCPStore: the server (which also serves this process as a client) when
// `is_server`, else a client of host:port. `world` is the number of clients
// expected (informational for a client). Wrapped in a PrefixStore when
// `prefix` is not empty. NULL on failure.
void* bv2w_c10d_store_new(const char* host, int port, int is_server, int world,
                          int64_t timeout_ms, const char* prefix, char* err,
                          size_t err_len) {
  try {
    c10d::TCPStoreOptions opts;
    opts.port = static_cast<std::uint16_t>(port);
    opts.isServer = is_server != 0;
    opts.numWorkers = static_cast<std::size_t>(world);
    // The caller counts the ranks that joined itself (to name who is missing).
    opts.waitWorkers = false;
    opts.timeout = std::chrono::milliseconds(timeout_ms);
    opts.multiTenant = true;
    c10::intrusive_ptr<c10d::Store> store =
        c10::make_intrusive<c10d::TCPStore>(std::string(host), opts);
    if (prefix != nullptr && prefix[0] != '\0') {
      store = c10::make_intrusive<c10d::PrefixStore>(std::string(prefix), store);
    }
    return new BV2WStore{store};
  }
  BV2W_TRY(nullptr)
}

void bv2w_c10d_store_free(void* store) { delete static_cast<BV2WStore*>(store); }

int bv2w_c10d_store_set(void* store, const char* key, const uint8_t* data,
                        size_t len, char* err, size_t err_len) {
  try {
    std::vector<uint8_t> value(data, data + len);
    static_cast<BV2WStore*>(store)->store->set(std::string(key), value);
    return 0;
  }
  BV2W_TRY(-1)
}

// Waits for `key` (up to the store's timeout); the value is malloc'd into
// *out (free with bv2w_c10d_free), its length in *len.
int bv2w_c10d_store_get(void* store, const char* key, uint8_t** out, size_t* len,
                        char* err, size_t err_len) {
  try {
    auto value = static_cast<BV2WStore*>(store)->store->get(std::string(key));
    *len = value.size();
    *out = static_cast<uint8_t*>(std::malloc(value.empty() ? 1 : value.size()));
    if (*out == nullptr) throw std::bad_alloc();
    if (!value.empty()) std::memcpy(*out, value.data(), value.size());
    return 0;
  }
  BV2W_TRY(-1)
}

// Adds `delta` to the integer at `key` (0 when absent); the new value in *out.
int bv2w_c10d_store_add(void* store, const char* key, int64_t delta, int64_t* out,
                        char* err, size_t err_len) {
  try {
    *out = static_cast<BV2WStore*>(store)->store->add(std::string(key), delta);
    return 0;
  }
  BV2W_TRY(-1)
}

// 1 when `key` exists, 0 when not, without waiting; -1 on failure.
int bv2w_c10d_store_check(void* store, const char* key, char* err, size_t err_len) {
  try {
    return static_cast<BV2WStore*>(store)->store->check({std::string(key)}) ? 1 : 0;
  }
  BV2W_TRY(-1)
}

void bv2w_c10d_free(void* p) { std::free(p); }

// The Gloo process group of `world` ranks over `store` (its devices from
// GLOO_SOCKET_IFNAME, else this host's name or the loopback, as PyTorch's
// default). NULL on failure.
void* bv2w_c10d_gloo_new(void* store, int rank, int world, int64_t timeout_ms,
                         char* err, size_t err_len) {
  try {
#ifdef BV2W_HAVE_GLOO
    auto opts = c10d::ProcessGroupGloo::Options::create_default(
        std::chrono::milliseconds(timeout_ms));
    c10::intrusive_ptr<c10d::Backend> backend =
        c10::make_intrusive<c10d::ProcessGroupGloo>(
            static_cast<BV2WStore*>(store)->store, rank, world, opts);
    return new BV2WGroup{backend};
#else
    (void)store;
    (void)rank;
    (void)world;
    (void)timeout_ms;
    throw std::runtime_error(
        "this build has no Gloo backend: the gloo headers were not found when "
        "torch-ext was compiled (run scripts/setup-venv.sh, which fetches them, "
        "or set BRIDGEV2W_GLOO_INCLUDE and rebuild)");
#endif
  }
  BV2W_TRY(nullptr)
}

// Shuts the group down (NCCL: its communicators) and frees it.
void bv2w_c10d_group_free(void* group) {
  auto* g = static_cast<BV2WGroup*>(group);
  if (g == nullptr) return;
  try {
    g->backend->shutdown();
  } catch (...) {
  }
  delete g;
}

// Starts a sum all-reduce of `tensor` in place; a work handle (wait, then
// free), NULL on failure.
void* bv2w_c10d_all_reduce(void* group, void* tensor, char* err, size_t err_len) {
  try {
    std::vector<at::Tensor> ts{*static_cast<at::Tensor*>(tensor)};
    c10d::AllreduceOptions opts;  // reduceOp: SUM
    auto work = static_cast<BV2WGroup*>(group)->backend->allreduce(ts, opts);
    return new BV2WWork{work, std::move(ts)};
  }
  BV2W_TRY(nullptr)
}

// Waits for a work handle (up to the group's timeout); 0 on success.
int bv2w_c10d_work_wait(void* work, char* err, size_t err_len) {
  try {
    static_cast<BV2WWork*>(work)->work->wait();
    return 0;
  }
  BV2W_TRY(-1)
}

void bv2w_c10d_work_free(void* work) { delete static_cast<BV2WWork*>(work); }

// Rank `root`'s `tensor` into every rank's `tensor` (in place); 0 on success.
int bv2w_c10d_broadcast(void* group, void* tensor, int root, char* err,
                        size_t err_len) {
  try {
    std::vector<at::Tensor> ts{*static_cast<at::Tensor*>(tensor)};
    c10d::BroadcastOptions opts;
    opts.rootRank = root;
    static_cast<BV2WGroup*>(group)->backend->broadcast(ts, opts)->wait();
    return 0;
  }
  BV2W_TRY(-1)
}

// Every rank's `input` into `outputs[0..world]` (same shape and dtype as
// `input`, in rank order); 0 on success.
int bv2w_c10d_all_gather(void* group, void* input, void* const* outputs, int world,
                         char* err, size_t err_len) {
  try {
    std::vector<at::Tensor> in{*static_cast<at::Tensor*>(input)};
    std::vector<std::vector<at::Tensor>> out(1);
    for (int i = 0; i < world; ++i) {
      out[0].push_back(*static_cast<at::Tensor*>(outputs[i]));
    }
    static_cast<BV2WGroup*>(group)->backend->allgather(out, in)->wait();
    return 0;
  }
  BV2W_TRY(-1)
}

// Waits until every rank calls it; 0 on success.
int bv2w_c10d_barrier(void* group, char* err, size_t err_len) {
  try {
    static_cast<BV2WGroup*>(group)->backend->barrier()->wait();
    return 0;
  }
  BV2W_TRY(-1)
}

}  // extern "C"
