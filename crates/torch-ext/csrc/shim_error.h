// Error reporting shared by the C++ shims: every extern "C" function catches
// C++ exceptions and writes their message into a caller's buffer (none may
// unwind into Rust).
#pragma once

#include <cstddef>
#include <string>

// Writes `message` (truncated, NUL-terminated) into err[0..err_len].
void bv2w_set_error(char* err, size_t err_len, const std::string& message);
// From inside a catch block: the current exception's message into err
// (c10::Error without libtorch's C++ backtrace).
void bv2w_set_current_error(char* err, size_t err_len);
