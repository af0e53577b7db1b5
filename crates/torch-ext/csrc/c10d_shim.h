// Handles shared by c10d.cpp and c10d_nccl.cpp (see c10d.cpp).
#pragma once

#include <torch/csrc/distributed/c10d/Backend.hpp>
#include <torch/csrc/distributed/c10d/Store.hpp>
#include <torch/csrc/distributed/c10d/Work.hpp>

#include <string>
#include <vector>

#include "shim_error.h"

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
