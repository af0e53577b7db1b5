// A C interface to ATen's autocast state (ATen/autocast_mode.h), which tch's C
// API exposes only for CUDA and its default dtype. Device and dtype are this
// shim's own small codes (below), so the Rust side does not depend on the
// numeric values of c10's enums. Every function catches C++ exceptions and
// reports failure through its return value: none may unwind into Rust.

#include <ATen/autocast_mode.h>

namespace {

bool to_device(int code, at::DeviceType* out) {
  switch (code) {
    case 0: *out = at::kCPU; return true;
    case 1: *out = at::kCUDA; return true;
    default: return false;
  }
}

// 0: float32, 1: float16, 2: bfloat16; -1 for anything else.
bool to_dtype(int code, at::ScalarType* out) {
  switch (code) {
    case 0: *out = at::kFloat; return true;
    case 1: *out = at::kHalf; return true;
    case 2: *out = at::kBFloat16; return true;
    default: return false;
  }
}

int from_dtype(at::ScalarType t) {
  switch (t) {
    case at::kFloat: return 0;
    case at::kHalf: return 1;
    case at::kBFloat16: return 2;
    default: return -1;
  }
}

}  // namespace

extern "C" {

// 1 / 0: enabled or not; -1: bad device code or a libtorch error.
int bv2w_autocast_is_enabled(int device) {
  try {
    at::DeviceType d;
    if (!to_device(device, &d)) return -1;
    return at::autocast::is_autocast_enabled(d) ? 1 : 0;
  } catch (...) {
    return -1;
  }
}

// 0 on success, -1 on failure.
int bv2w_autocast_set_enabled(int device, int enabled) {
  try {
    at::DeviceType d;
    if (!to_device(device, &d)) return -1;
    at::autocast::set_autocast_enabled(d, enabled != 0);
    return 0;
  } catch (...) {
    return -1;
  }
}

// The dtype code (0, 1, 2), -1 for another dtype, -2 on failure.
int bv2w_autocast_get_dtype(int device) {
  try {
    at::DeviceType d;
    if (!to_device(device, &d)) return -2;
    return from_dtype(at::autocast::get_autocast_dtype(d));
  } catch (...) {
    return -2;
  }
}

// 0 on success, -1 on failure.
int bv2w_autocast_set_dtype(int device, int dtype) {
  try {
    at::DeviceType d;
    at::ScalarType t;
    if (!to_device(device, &d) || !to_dtype(dtype, &t)) return -1;
    at::autocast::set_autocast_dtype(d, t);
    return 0;
  } catch (...) {
    return -1;
  }
}

// The nesting depth after the change; -1 on failure.
int bv2w_autocast_increment_nesting() {
  try {
    return at::autocast::increment_nesting();
  } catch (...) {
    return -1;
  }
}

int bv2w_autocast_decrement_nesting() {
  try {
    return at::autocast::decrement_nesting();
  } catch (...) {
    return -1;
  }
}

// 0 on success, -1 on failure.
int bv2w_autocast_clear_cache() {
  try {
    at::autocast::clear_cache();
    return 0;
  } catch (...) {
    return -1;
  }
}

}  // extern "C"
