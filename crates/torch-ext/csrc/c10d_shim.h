// Handles shared by c10d.cpp and c10d_nccl.cpp (see c10d.cpp).
#pragma once

#include <torch/csrc/distributed/c10d/Backend.hpp>
#include <torch/csrc/distributed/c10d/Store.hpp>
#include <torch/csrc/distributed/c10d/Work.hpp>

#include <string>
#include <vector>

struct BV2WStore {
  c10::intrusive_ptr<c10d::Store> store;
};

struct BV2WGroup {
  c10::intrusive_ptr<c10d::Backend> backend;
};

struct BV2WWork {
  c10::intrusive_ptr<c10d::Work> work;
  // The tensors the collective works on, alive until the handle is freed.
  std::vector<at::Tensor> tensors;
};

// Writes `message` (truncated, NUL-terminated) into err[0..err_len].
void bv2w_c10d_set_error(char* err, size_t err_len, const std::string& message);
// From inside a catch block: the current exception's message into err.
void bv2w_c10d_set_current_error(char* err, size_t err_len);
