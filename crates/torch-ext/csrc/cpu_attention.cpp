// Softmax attention in bf16 on x86 CPUs with AVX512-BF16, for inference.
//
// libtorch's CPU flash attention multiplies bf16 tiles through MKL's
// `gemm_bf16bf16f32`, which on CPUs without AMX widens them to f32 and runs
// `sgemm` (no faster than f32 attention). Here the same algorithm runs its
// two products on oneDNN's bf16 micro-kernel (`at::native::cpublas::brgemm`,
// `vdpbf16ps`): per (batch, head), keys are laid out once as K^T and values
// once in the VNNI layout that kernel reads (pairs of rows interleaved);
// then per block of QUERY_BLOCK queries and KEY_BLOCK keys:
//
//   S = Q K^T (f32), online softmax (running max and sum, scale folded into
//   the exponent), P = exp(...) rounded to bf16, O = O * alpha + P V (f32),
//
// and the output is O / sum rounded to bf16: libtorch's flash attention up
// to the order of summation (it also rounds P to bf16 before P V).
//
// The output [B, heads, Lq, D] is a view of a [B, Lq, heads, D] buffer, so
// that the caller's transpose and reshape to [B, Lq, heads * D] copy nothing.
//
// Every extern function catches C++ exceptions and reports them as a null
// result plus a message in the caller's buffer: none may unwind into Rust.

#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <ATen/native/CPUBlas.h>
#include <c10/util/Exception.h>

#include "shim_error.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

#if defined(__x86_64__) && defined(__GNUC__)
#define BV2W_X86 1
#include <immintrin.h>
#define BV2W_AVX512BF16 __attribute__((target("avx512f,avx512bw,avx512vl,avx512dq,avx512bf16")))
#endif

namespace {

constexpr int64_t QUERY_BLOCK = 64;
constexpr int64_t KEY_BLOCK = 512;

using bf16 = c10::BFloat16;

#ifdef BV2W_X86

// exp(x) for 16 lanes: x = n ln2 + r (Cody-Waite), a degree-7 polynomial in r
// (Cephes' expf coefficients, ~1 ulp), times 2^n by `scalef`. x below -87
// gives ~0 (the softmax's exponents are <= 0).
BV2W_AVX512BF16 inline __m512 exp16(__m512 x) {
  x = _mm512_max_ps(x, _mm512_set1_ps(-87.f));
  const __m512 n = _mm512_roundscale_ps(_mm512_mul_ps(x, _mm512_set1_ps(1.44269504088896341f)),
                                        _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  __m512 r = _mm512_fnmadd_ps(n, _mm512_set1_ps(0.693145751953125f), x);
  r = _mm512_fnmadd_ps(n, _mm512_set1_ps(1.428606765330187045e-06f), r);
  __m512 p = _mm512_set1_ps(1.9875691500e-4f);
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(1.3981999507e-3f));
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(8.3334519073e-3f));
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(4.1665795894e-2f));
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(1.6666665459e-1f));
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(5.0000001201e-1f));
  p = _mm512_fmadd_ps(_mm512_mul_ps(p, r), r, _mm512_add_ps(r, _mm512_set1_ps(1.f)));
  return _mm512_scalef_ps(p, n);
}

inline __mmask16 tail_mask(int64_t count) {
  return static_cast<__mmask16>((1u << count) - 1u);
}

// One block of scores S [m x n] (row stride ld_s, f32): updates the running
// row max and sum, writes P = exp(scale * (S - max)) as bf16 [m x n_even]
// (row stride ld_p; the column past an odd n is 0) and alpha, the factor the
// accumulated output rows are rescaled by.
BV2W_AVX512BF16 void softmax_block(const float* s, int64_t ld_s, int64_t m, int64_t n,
                                   int64_t n_even, float scale, float* row_max, float* row_sum,
                                   float* alpha, bf16* p, int64_t ld_p) {
  const __m512 neg_inf = _mm512_set1_ps(-INFINITY);
  for (int64_t i = 0; i < m; ++i) {
    const float* row = s + i * ld_s;
    __m512 vmax = neg_inf;
    int64_t j = 0;
    for (; j + 16 <= n; j += 16) vmax = _mm512_max_ps(vmax, _mm512_loadu_ps(row + j));
    if (j < n) vmax = _mm512_max_ps(vmax, _mm512_mask_loadu_ps(neg_inf, tail_mask(n - j), row + j));
    const float old_max = row_max[i];
    const float new_max = std::max(old_max, _mm512_reduce_max_ps(vmax));
    const float a = old_max == -INFINITY ? 0.f : std::exp((old_max - new_max) * scale);
    const __m512 vscale = _mm512_set1_ps(scale);
    const __m512 offset = _mm512_set1_ps(-new_max * scale);
    __m512 vsum = _mm512_setzero_ps();
    bf16* p_row = p + i * ld_p;
    for (j = 0; j + 16 <= n; j += 16) {
      const __m512 e = exp16(_mm512_fmadd_ps(_mm512_loadu_ps(row + j), vscale, offset));
      vsum = _mm512_add_ps(vsum, e);
      _mm256_storeu_si256(reinterpret_cast<__m256i*>(p_row + j),
                          reinterpret_cast<__m256i>(_mm512_cvtneps_pbh(e)));
    }
    if (j < n) {
      const __mmask16 k = tail_mask(n - j);
      const __m512 e = _mm512_maskz_mov_ps(
          k, exp16(_mm512_fmadd_ps(_mm512_maskz_loadu_ps(k, row + j), vscale, offset)));
      vsum = _mm512_add_ps(vsum, e);
      _mm256_mask_storeu_epi16(p_row + j, k, reinterpret_cast<__m256i>(_mm512_cvtneps_pbh(e)));
    }
    if (n_even != n) std::memset(p_row + n, 0, sizeof(bf16));
    row_sum[i] = row_sum[i] * a + _mm512_reduce_add_ps(vsum);
    row_max[i] = new_max;
    alpha[i] = a;
  }
}

// out[i, :] = o[i, :] * factor[i] for m rows of d values (f32), in place.
BV2W_AVX512BF16 void scale_rows(float* o, int64_t m, int64_t d, const float* factor) {
  for (int64_t i = 0; i < m; ++i) {
    const __m512 f = _mm512_set1_ps(factor[i]);
    float* row = o + i * d;
    int64_t j = 0;
    for (; j + 16 <= d; j += 16) _mm512_storeu_ps(row + j, _mm512_mul_ps(_mm512_loadu_ps(row + j), f));
    if (j < d) {
      const __mmask16 k = tail_mask(d - j);
      _mm512_mask_storeu_ps(row + j, k, _mm512_mul_ps(_mm512_maskz_loadu_ps(k, row + j), f));
    }
  }
}

// dst[i * ld_dst + j] = bf16(o[i * d + j] / sum[i]) for m rows of d values.
BV2W_AVX512BF16 void normalise_rows(const float* o, int64_t m, int64_t d, const float* row_sum,
                                    bf16* dst, int64_t ld_dst) {
  for (int64_t i = 0; i < m; ++i) {
    const __m512 inv = _mm512_set1_ps(1.f / row_sum[i]);
    const float* row = o + i * d;
    bf16* out = dst + i * ld_dst;
    int64_t j = 0;
    for (; j + 16 <= d; j += 16) {
      _mm256_storeu_si256(reinterpret_cast<__m256i*>(out + j),
                          reinterpret_cast<__m256i>(
                              _mm512_cvtneps_pbh(_mm512_mul_ps(_mm512_loadu_ps(row + j), inv))));
    }
    if (j < d) {
      const __mmask16 k = tail_mask(d - j);
      _mm256_mask_storeu_epi16(out + j, k,
                               reinterpret_cast<__m256i>(_mm512_cvtneps_pbh(
                                   _mm512_mul_ps(_mm512_maskz_loadu_ps(k, row + j), inv))));
    }
  }
}

// A [batch, heads, rows, d] tensor's element (b, h, row, 0).
template <typename T>
T* row_ptr(const at::Tensor& t, int64_t b, int64_t h, int64_t row) {
  return static_cast<T*>(t.data_ptr()) + b * t.stride(0) + h * t.stride(1) + row * t.stride(2);
}

at::Tensor attention(const at::Tensor& q, const at::Tensor& k, const at::Tensor& v, double scale) {
  for (const auto* t : {&q, &k, &v}) {
    TORCH_CHECK(t->dim() == 4, "expected [batch, heads, tokens, head_dim] tensors, got ", t->sizes());
    TORCH_CHECK(t->scalar_type() == at::kBFloat16 && t->device().is_cpu(),
                "expected bf16 CPU tensors, got ", t->scalar_type(), " on ", t->device());
    TORCH_CHECK(t->stride(3) == 1, "head_dim must be contiguous (stride 1), got strides ",
                t->strides());
  }
  const int64_t batch = q.size(0), heads = q.size(1), lq = q.size(2), d = q.size(3);
  const int64_t lk = k.size(2);
  TORCH_CHECK(k.size(0) == batch && v.size(0) == batch && k.size(1) == heads &&
                  v.size(1) == heads && v.size(2) == lk && k.size(3) == d && v.size(3) == d,
              "q ", q.sizes(), ", k ", k.sizes(), ", v ", v.sizes(),
              ": expected the same batch, heads and head_dim, and as many values as keys");
  TORCH_CHECK(d % 2 == 0 && d > 0, "head_dim must be even, got ", d);
  TORCH_CHECK(lk > 0, "no keys");
  const int64_t bh = batch * heads;
  const int64_t lk_even = (lk + 1) / 2 * 2;
  // [B, Lq, heads, D] viewed as [B, heads, Lq, D].
  at::Tensor out = at::empty({batch, lq, heads, d}, q.options()).permute({0, 2, 1, 3});
  if (lq == 0) return out;
  // Per (b, h): K^T as [D/2, lk_even] pairs (bf16 x 2 = one u32), V as
  // [lk_even/2, D, 2]; the row past an odd lk is zero.
  at::Tensor k_t = at::empty({bh, d / 2, lk_even}, q.options().dtype(at::kInt));
  at::Tensor v_pairs = at::empty({bh, lk_even / 2, d, 2}, q.options());
  at::parallel_for(0, bh, 1, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      const int64_t b = i / heads, h = i % heads;
      uint32_t* kt = static_cast<uint32_t*>(k_t.data_ptr()) + i * (d / 2) * lk_even;
      bf16* vp = static_cast<bf16*>(v_pairs.data_ptr()) + i * lk_even * d;
      for (int64_t j = 0; j < lk; ++j) {
        const bf16* k_row = row_ptr<bf16>(k, b, h, j);
        for (int64_t pair = 0; pair < d / 2; ++pair) {
          std::memcpy(kt + pair * lk_even + j, k_row + 2 * pair, sizeof(uint32_t));
        }
        const bf16* v_row = row_ptr<bf16>(v, b, h, j);
        bf16* dst = vp + (j / 2) * d * 2 + (j % 2);
        for (int64_t c = 0; c < d; ++c) dst[c * 2] = v_row[c];
      }
      if (lk_even != lk) {
        for (int64_t pair = 0; pair < d / 2; ++pair) kt[pair * lk_even + lk] = 0;
        bf16* dst = vp + (lk / 2) * d * 2 + 1;
        for (int64_t c = 0; c < d; ++c) dst[c * 2] = bf16(0.f);
      }
    }
  });
  const int64_t q_blocks = (lq + QUERY_BLOCK - 1) / QUERY_BLOCK;
  const float scale_f = static_cast<float>(scale);
  at::parallel_for(0, bh * q_blocks, 1, [&](int64_t begin, int64_t end) {
    std::vector<float> s(QUERY_BLOCK * KEY_BLOCK), o(QUERY_BLOCK * d);
    std::vector<float> row_max(QUERY_BLOCK), row_sum(QUERY_BLOCK), alpha(QUERY_BLOCK);
    std::vector<bf16> p(QUERY_BLOCK * KEY_BLOCK);
    for (int64_t task = begin; task < end; ++task) {
      const int64_t i = task / q_blocks;
      const int64_t b = i / heads, h = i % heads;
      const int64_t q0 = (task % q_blocks) * QUERY_BLOCK;
      const int64_t m = std::min(QUERY_BLOCK, lq - q0);
      const bf16* q_rows = row_ptr<bf16>(q, b, h, q0);
      const bf16* kt = reinterpret_cast<const bf16*>(static_cast<const uint32_t*>(k_t.data_ptr()) +
                                                     i * (d / 2) * lk_even);
      const bf16* vp = static_cast<const bf16*>(v_pairs.data_ptr()) + i * lk_even * d;
      std::fill(row_max.begin(), row_max.end(), -INFINITY);
      std::fill(row_sum.begin(), row_sum.end(), 0.f);
      for (int64_t k0 = 0; k0 < lk; k0 += KEY_BLOCK) {
        const int64_t n = std::min(KEY_BLOCK, lk - k0);
        const int64_t n_even = (n + 1) / 2 * 2;
        // S [m, n] = Q [m, d] K^T [d, n]; K^T pairs start at column k0.
        at::native::cpublas::brgemm(m, n, d, q.stride(2), lk_even, KEY_BLOCK, false, q_rows,
                                    kt + 2 * k0, s.data(), true);
        softmax_block(s.data(), KEY_BLOCK, m, n, n_even, scale_f, row_max.data(), row_sum.data(),
                      alpha.data(), p.data(), KEY_BLOCK);
        if (k0 > 0) scale_rows(o.data(), m, d, alpha.data());
        // O [m, d] (+)= P [m, n_even] V [n_even, d]; V pairs from row k0.
        at::native::cpublas::brgemm(m, d, n_even, KEY_BLOCK, d, d, k0 > 0, p.data(),
                                    vp + k0 * d, o.data(), true);
      }
      normalise_rows(o.data(), m, d, row_sum.data(), row_ptr<bf16>(out, b, h, q0),
                     out.stride(2));
    }
    at::native::cpublas::brgemm_release(true);
  });
  return out;
}

#endif  // BV2W_X86

// Whether this CPU and libtorch run the kernel: AVX512-BF16, and a small
// attention through it matches a plain computation (libtorch without oneDNN's
// micro-kernels throws, and is then reported unavailable).
bool check_available() {
#ifdef BV2W_X86
  if (!__builtin_cpu_supports("avx512bf16")) return false;
  try {
    const auto opts = at::TensorOptions().dtype(at::kBFloat16);
    const at::Tensor q = at::linspace(-1.0, 1.0, 2 * 3 * 8, opts).reshape({1, 2, 3, 8});
    const at::Tensor k = at::linspace(1.0, -1.0, 2 * 5 * 8, opts).reshape({1, 2, 5, 8});
    const at::Tensor v = at::linspace(-2.0, 2.0, 2 * 5 * 8, opts).reshape({1, 2, 5, 8});
    const at::Tensor got = attention(q, k, v, 0.5).to(at::kFloat);
    const at::Tensor scores = at::matmul(q.to(at::kFloat), k.to(at::kFloat).transpose(2, 3)) * 0.5;
    const at::Tensor want = at::matmul(at::softmax(scores, -1), v.to(at::kFloat));
    return (got - want).abs().max().item<float>() < 0.05f;
  } catch (...) {
    return false;
  }
#else
  return false;
#endif
}

}  // namespace

extern "C" {

// 1 when `bv2w_cpu_attention_bf16` runs on this CPU, 0 otherwise (decided once).
int bv2w_cpu_attention_available() {
  static const bool available = check_available();
  return available ? 1 : 0;
}

// softmax(q k^T * scale) v for bf16 CPU tensors q [B, heads, Lq, D] and k, v
// [B, heads, Lk, D] (D even, head_dim contiguous): [B, heads, Lq, D], or null
// with the message in `err`.
void* bv2w_cpu_attention_bf16(void* q, void* k, void* v, double scale, char* err,
                              size_t err_len) {
  try {
    TORCH_CHECK(bv2w_cpu_attention_available() == 1,
                "this CPU has no AVX512-BF16 or this libtorch no oneDNN bf16 micro-kernel");
#ifdef BV2W_X86
    return new at::Tensor(attention(*static_cast<at::Tensor*>(q), *static_cast<at::Tensor*>(k),
                                    *static_cast<at::Tensor*>(v), scale));
#else
    return nullptr;
#endif
  } catch (...) {
    bv2w_set_current_error(err, err_len);
    return nullptr;
  }
}

}  // extern "C"
