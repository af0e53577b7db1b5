// The CUDA caching allocator's memory figures (what
// torch.cuda.max_memory_allocated / max_memory_reserved report), for the
// training metrics and the GPU checklist: exact peaks, where polling
// nvidia-smi sees the device's used memory every few milliseconds (the
// allocator's reserve and the CUDA context included) and can miss a short
// peak. Compiled with the CUDA headers (build.rs, as c10d_nccl.cpp);
// without them every call says "unavailable".

#include "shim_error.h"

#include <cstdint>
#include <stdexcept>
#include <string>

#ifdef BV2W_HAVE_NCCL
#include <ATen/Context.h>
#include <c10/cuda/CUDACachingAllocator.h>
#include <c10/cuda/CUDAFunctions.h>
#endif

#ifdef BV2W_HAVE_NCCL
namespace {

// The device index, checked against the devices present (the allocator's
// per-device state is indexed without a check).
c10::DeviceIndex checked_device(int device) {
  const int count = static_cast<int>(c10::cuda::device_count());
  if (device < 0 || device >= count) {
    throw std::runtime_error("no CUDA device " + std::to_string(device) + " (" +
                             std::to_string(count) + " present)");
  }
  at::globalContext().lazyInitDevice(c10::DeviceType::CUDA);
  return static_cast<c10::DeviceIndex>(device);
}

}  // namespace
#endif

extern "C" {

// out: allocated bytes now, their peak, reserved bytes now, their peak (the
// peaks since the last reset). 1 on success, 0 when this build has no CUDA,
// -1 on an error (message in err).
int bv2w_cuda_memory(int device, uint64_t* out, char* err, size_t err_len) {
  try {
#ifdef BV2W_HAVE_NCCL
    using c10::CachingAllocator::StatType;
    const auto stats =
        c10::cuda::CUDACachingAllocator::getDeviceStats(checked_device(device));
    const auto all = static_cast<size_t>(StatType::AGGREGATE);
    out[0] = static_cast<uint64_t>(stats.allocated_bytes[all].current);
    out[1] = static_cast<uint64_t>(stats.allocated_bytes[all].peak);
    out[2] = static_cast<uint64_t>(stats.reserved_bytes[all].current);
    out[3] = static_cast<uint64_t>(stats.reserved_bytes[all].peak);
    return 1;
#else
    (void)device;
    (void)out;
    return 0;
#endif
  } catch (...) {
    bv2w_set_current_error(err, err_len);
    return -1;
  }
}

// Starts the peaks again from the current figures. Return values as above.
int bv2w_cuda_reset_peak(int device, char* err, size_t err_len) {
  try {
#ifdef BV2W_HAVE_NCCL
    c10::cuda::CUDACachingAllocator::resetPeakStats(checked_device(device));
    return 1;
#else
    (void)device;
    return 0;
#endif
  } catch (...) {
    bv2w_set_current_error(err, err_len);
    return -1;
  }
}

}  // extern "C"
