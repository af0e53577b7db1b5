// oneDNN's linear layer as libtorch registers it for inference
// (`mkldnn::_linear_pointwise`, the op torch.compile's CPU backend calls
// with frozen weights): `x W^T + b` with an optional fused post-op (tanh
// GELU here), on a plain `[out, in]` weight or one reordered once into
// oneDNN's blocked layout (`mkldnn::_reorder_linear_weight`). The ops are
// called through the dispatcher, boxed, so no C++ signature of theirs is
// compiled in here; a libtorch built without oneDNN has no such schema and
// `bv2w_onednn_available` says so.
//
// Every function catches C++ exceptions and reports them as a null result
// plus a message in the caller's buffer: none may unwind into Rust.

#include <ATen/ATen.h>
#include <ATen/core/dispatch/Dispatcher.h>
#include <ATen/core/grad_mode.h>
#include <ATen/core/stack.h>
#include <c10/util/Exception.h>

#include "shim_error.h"

#include <cstdint>
#include <optional>
#include <string>

namespace {

std::optional<c10::OperatorHandle> find_op(const char* name) {
  return c10::Dispatcher::singleton().findSchema({name, ""});
}

}  // namespace

extern "C" {

// 1 when libtorch registers both oneDNN linear ops, 0 otherwise.
int bv2w_onednn_available() {
  try {
    return find_op("mkldnn::_linear_pointwise").has_value() &&
                   find_op("mkldnn::_reorder_linear_weight").has_value()
               ? 1
               : 0;
  } catch (...) {
    return 0;
  }
}

// Whether autograd records operations on this thread (GradMode).
int bv2w_grad_mode_enabled() { return at::GradMode::is_enabled() ? 1 : 0; }

// The version counter of a tensor's data (bumped by every in-place change).
uint64_t bv2w_tensor_version(void* tensor) {
  try {
    return static_cast<uint64_t>(static_cast<at::Tensor*>(tensor)->_version());
  } catch (...) {
    return UINT64_MAX;
  }
}

// `weight` [out, in] reordered into oneDNN's layout for linear layers (an
// opaque mkldnn tensor), or null with the message in `err`.
void* bv2w_onednn_pack_linear_weight(void* weight, char* err, size_t err_len) {
  try {
    static const auto op = find_op("mkldnn::_reorder_linear_weight");
    TORCH_CHECK(op.has_value(), "this libtorch has no mkldnn::_reorder_linear_weight");
    torch::jit::Stack stack;
    stack.emplace_back(*static_cast<at::Tensor*>(weight));
    stack.emplace_back();  // batch_size: None
    op->callBoxed(&stack);
    return new at::Tensor(stack.at(0).toTensor());
  } catch (...) {
    bv2w_set_current_error(err, err_len);
    return nullptr;
  }
}

// `input W^T + bias` (bias may be null) followed by `post_op` (0: none,
// 1: tanh GELU), `weight` plain [out, in] or packed by the function above;
// null with the message in `err` on failure.
void* bv2w_onednn_linear(void* input, void* weight, void* bias, int post_op, char* err,
                         size_t err_len) {
  try {
    static const auto op = find_op("mkldnn::_linear_pointwise");
    TORCH_CHECK(op.has_value(), "this libtorch has no mkldnn::_linear_pointwise");
    TORCH_CHECK(post_op == 0 || post_op == 1, "unknown post-op code ", post_op);
    torch::jit::Stack stack;
    stack.emplace_back(*static_cast<at::Tensor*>(input));
    stack.emplace_back(*static_cast<at::Tensor*>(weight));
    if (bias != nullptr) {
      stack.emplace_back(*static_cast<at::Tensor*>(bias));
    } else {
      stack.emplace_back();
    }
    stack.emplace_back(std::string(post_op == 1 ? "gelu" : "none"));
    stack.emplace_back(c10::List<std::optional<at::Scalar>>());
    if (post_op == 1) {
      stack.emplace_back(std::string("tanh"));
    } else {
      stack.emplace_back();
    }
    op->callBoxed(&stack);
    return new at::Tensor(stack.at(0).toTensor());
  } catch (...) {
    bv2w_set_current_error(err, err_len);
    return nullptr;
  }
}

}  // extern "C"
