// The NCCL process group (CUDA) of the c10d shim (see c10d.cpp). Compiled
// only when the libtorch in use has CUDA and the CUDA and NCCL headers of the
// PyPI wheels it depends on are present (build.rs); otherwise c10d.cpp's
// caller gets the stub below, which says why.

#include "c10d_shim.h"

#include <stdexcept>

#ifdef BV2W_HAVE_NCCL
#define USE_C10D_NCCL 1
#include <c10/cuda/CUDAGuard.h>
#include <torch/csrc/distributed/c10d/ProcessGroupNCCL.hpp>
#endif

extern "C" {

// 1 when this build has the NCCL backend, 0 otherwise.
int bv2w_c10d_has_nccl() {
#ifdef BV2W_HAVE_NCCL
  return 1;
#else
  return 0;
#endif
}

// The NCCL process group of `world` ranks over `store`, this rank on CUDA
// device `device`. NULL on failure.
void* bv2w_c10d_nccl_new(void* store, int rank, int world, int device,
                         int64_t timeout_ms, char* err, size_t err_len) {
  try {
#ifdef BV2W_HAVE_NCCL
    // Collectives run on this rank's device: make it current, as
    // torch.cuda.set_device(LOCAL_RANK) does before init_process_group.
    c10::cuda::set_device(static_cast<c10::DeviceIndex>(device));
    auto opts = c10d::ProcessGroupNCCL::Options::create();
    opts->timeout = std::chrono::milliseconds(timeout_ms);
    c10::intrusive_ptr<c10d::Backend> backend =
        c10::make_intrusive<c10d::ProcessGroupNCCL>(
            static_cast<BV2WStore*>(store)->store, rank, world, opts);
    // Bind the group to the device (eager communicator init, as
    // init_process_group(device_id=...)): errors surface here, not later.
    backend->eagerConnectSingleDevice(
        at::Device(at::kCUDA, static_cast<c10::DeviceIndex>(device)));
    return new BV2WGroup{backend};
#else
    (void)store;
    (void)rank;
    (void)world;
    (void)device;
    (void)timeout_ms;
    throw std::runtime_error(
        "this build has no NCCL backend: its libtorch has no CUDA, or the CUDA "
        "and NCCL headers (PyPI nvidia-cuda-runtime, nvidia-cuda-crt, "
        "nvidia-cuda-cccl, nvidia-nccl) were missing when torch-ext was compiled");
#endif
  } catch (...) {
    bv2w_set_current_error(err, err_len);
    return nullptr;
  }
}

}  // extern "C"
