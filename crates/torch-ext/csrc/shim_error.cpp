// See shim_error.h.

#include "shim_error.h"

#include <c10/util/Exception.h>

#include <algorithm>
#include <cstring>
#include <exception>

void bv2w_set_error(char* err, size_t err_len, const std::string& message) {
  if (err == nullptr || err_len == 0) return;
  size_t n = std::min(message.size(), err_len - 1);
  std::memcpy(err, message.data(), n);
  err[n] = '\0';
}

void bv2w_set_current_error(char* err, size_t err_len) {
  try {
    throw;
  } catch (const c10::Error& e) {
    // what_without_backtrace: the message, not libtorch's C++ stack.
    bv2w_set_error(err, err_len, e.what_without_backtrace());
  } catch (const std::exception& e) {
    bv2w_set_error(err, err_len, e.what());
  } catch (...) {
    bv2w_set_error(err, err_len, "unknown C++ exception");
  }
}
