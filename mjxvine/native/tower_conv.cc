// The conv tower's 3x3 VALID convolutions on the CPU (NHWC x HWIO, float32, AVX2 + FMA,
// OpenMP over the images), as XLA FFI handlers: with 8 or 16 output channels XLA's CPU
// convolution runs far below the machine's matmul rate. Built and loaded by
// mjxvine/native_conv.py.
//
//   mjxvine_tower_conv(x (N,H,W,C), k (3,3,C,F); stride) -> y (N,Ho,Wo,F)
//   mjxvine_tower_conv_kernel_grad(x (N,H,W,C), dy (N,Ho,Wo,F); stride) -> dk (3,3,C,F)
//
// Ho = (H - 3) / stride + 1; F in {8, 16}, C a multiple of 4, stride 1 or 2.
#include <immintrin.h>
#include <omp.h>
#include <cstdint>
#include <vector>
#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;
using Image = ffi::Buffer<ffi::F32, 4>;  // NHWC or HWIO
using ImageOut = ffi::ResultBuffer<ffi::F32, 4>;

namespace {

// P output pixels of one row from ow: acc[p] = sum_{kh,kw,c} x[.., s*(ow+p)+kw, c] * k[kh,kw,c,:].
template <int V, int P>
inline void ForwardBlock(const float* x, const float* k, float* y, int64_t H, int64_t W,
                         int64_t C, int64_t s, int64_t n, int64_t oh, int64_t ow) {
  constexpr int F = 8 * V;
  __m256 acc[P][V];
  for (int p = 0; p < P; ++p)
    for (int v = 0; v < V; ++v) acc[p][v] = _mm256_setzero_ps();
  for (int kh = 0; kh < 3; ++kh) {
    const float* xr = x + ((n * H + s * oh + kh) * W + s * ow) * C;
    const float* kr = k + kh * 3 * C * F;
    for (int64_t j = 0; j < 3 * C; ++j) {  // (kw, c) are contiguous in x and in k
      __m256 kv[V];
      for (int v = 0; v < V; ++v) kv[v] = _mm256_loadu_ps(kr + j * F + 8 * v);
      for (int p = 0; p < P; ++p) {
        const __m256 xb = _mm256_broadcast_ss(xr + p * s * C + j);
        for (int v = 0; v < V; ++v) acc[p][v] = _mm256_fmadd_ps(xb, kv[v], acc[p][v]);
      }
    }
  }
  for (int p = 0; p < P; ++p)
    for (int v = 0; v < V; ++v) _mm256_storeu_ps(y + (ow + p) * F + 8 * v, acc[p][v]);
}

// y[n,oh,ow,:] = sum_{kh,kw,c} x[n,s*oh+kh,s*ow+kw,c] * k[kh,kw,c,:]; F = 8*V outputs,
// P output pixels per register block.
template <int V, int P>
void Forward(const float* x, const float* k, float* y, int64_t N, int64_t H, int64_t W,
             int64_t C, int64_t s) {
  constexpr int F = 8 * V;
  const int64_t Ho = (H - 3) / s + 1, Wo = (W - 3) / s + 1;
#pragma omp parallel for schedule(static)
  for (int64_t n = 0; n < N; ++n) {
    for (int64_t oh = 0; oh < Ho; ++oh) {
      float* yrow = y + (n * Ho + oh) * Wo * F;
      int64_t ow = 0;
      for (; ow + P <= Wo; ow += P) ForwardBlock<V, P>(x, k, yrow, H, W, C, s, n, oh, ow);
      for (; ow < Wo; ++ow) ForwardBlock<V, 1>(x, k, yrow, H, W, C, s, n, oh, ow);
    }
  }
}

// dk[kh,kw,c,:] = sum_{n,oh,ow} x[n,s*oh+kh,s*ow+kw,c] * dy[n,oh,ow,:]: each thread sums
// its images into its own copy, then the copies are added in a fixed order.
template <int V>
void KernelGrad(const float* x, const float* dy, float* dk, int64_t N, int64_t H,
                int64_t W, int64_t C, int64_t s) {
  constexpr int F = 8 * V, Q = 4;  // Q (kw, c) taps per register block
  const int64_t Ho = (H - 3) / s + 1, Wo = (W - 3) / s + 1, K = 9 * C * F;
  const int T = omp_get_max_threads();
  std::vector<float> part(static_cast<size_t>(T) * K, 0.0f);
#pragma omp parallel num_threads(T)
  {
    const int t = omp_get_thread_num(), nt = omp_get_num_threads();
    float* mine = part.data() + t * K;
    const int64_t n0 = N * t / nt, n1 = N * (t + 1) / nt;
    for (int64_t kh = 0; kh < 3; ++kh) {
      for (int64_t j0 = 0; j0 < 3 * C; j0 += Q) {
        __m256 acc[Q][V];
        for (int q = 0; q < Q; ++q)
          for (int v = 0; v < V; ++v) acc[q][v] = _mm256_setzero_ps();
        for (int64_t n = n0; n < n1; ++n) {
          for (int64_t oh = 0; oh < Ho; ++oh) {
            const float* xr = x + ((n * H + s * oh + kh) * W) * C + j0;
            const float* dyr = dy + (n * Ho + oh) * Wo * F;
            for (int64_t ow = 0; ow < Wo; ++ow) {
              __m256 g[V];
              for (int v = 0; v < V; ++v) g[v] = _mm256_loadu_ps(dyr + ow * F + 8 * v);
              const float* xp = xr + s * ow * C;
              for (int q = 0; q < Q; ++q) {
                const __m256 xb = _mm256_broadcast_ss(xp + q);
                for (int v = 0; v < V; ++v) acc[q][v] = _mm256_fmadd_ps(xb, g[v], acc[q][v]);
              }
            }
          }
        }
        for (int q = 0; q < Q; ++q)
          for (int v = 0; v < V; ++v)
            _mm256_storeu_ps(mine + (kh * 3 * C + j0 + q) * F + 8 * v, acc[q][v]);
      }
    }
  }
  for (int64_t i = 0; i < K; ++i) {
    float sum = 0.0f;
    for (int t = 0; t < T; ++t) sum += part[t * K + i];
    dk[i] = sum;
  }
}

// x (N,H,W,C) and the 4-d buffer `other`: the kernel (3,3,C,F) or the output gradient
// (N,Ho,Wo,F); F is its last dimension.
ffi::Error Check(Image& x, Image& other, bool other_is_kernel, int64_t s) {
  const auto xd = x.dimensions();
  const auto od = other.dimensions();
  const int64_t C = xd[3], F = od[3];
  if (F != 8 && F != 16) return ffi::Error::InvalidArgument("tower conv: F must be 8 or 16");
  if (C % 4 != 0) return ffi::Error::InvalidArgument("tower conv: C must be a multiple of 4");
  if (s != 1 && s != 2) return ffi::Error::InvalidArgument("tower conv: stride must be 1 or 2");
  const bool fits = other_is_kernel
      ? (od[0] == 3 && od[1] == 3 && od[2] == C)
      : (od[0] == xd[0] && od[1] == (xd[1] - 3) / s + 1 && od[2] == (xd[2] - 3) / s + 1);
  if (xd[1] < 3 || xd[2] < 3 || !fits)
    return ffi::Error::InvalidArgument("tower conv: shapes do not match");
  return ffi::Error::Success();
}

ffi::Error ForwardImpl(Image x, Image k, ImageOut y, int64_t stride) {
  if (auto e = Check(x, k, true, stride); e.failure()) return e;
  const auto d = x.dimensions();
  if (k.dimensions()[3] == 8)
    Forward<1, 6>(x.typed_data(), k.typed_data(), y->typed_data(), d[0], d[1], d[2], d[3], stride);
  else
    Forward<2, 3>(x.typed_data(), k.typed_data(), y->typed_data(), d[0], d[1], d[2], d[3], stride);
  return ffi::Error::Success();
}

ffi::Error KernelGradImpl(Image x, Image dy, ImageOut dk, int64_t stride) {
  if (auto e = Check(x, dy, false, stride); e.failure()) return e;
  const auto d = x.dimensions();
  if (dy.dimensions()[3] == 8)
    KernelGrad<1>(x.typed_data(), dy.typed_data(), dk->typed_data(), d[0], d[1], d[2], d[3],
                  stride);
  else
    KernelGrad<2>(x.typed_data(), dy.typed_data(), dk->typed_data(), d[0], d[1], d[2], d[3],
                  stride);
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(mjxvine_tower_conv, ForwardImpl,
                              ffi::Ffi::Bind()
                                  .Arg<Image>()
                                  .Arg<Image>()
                                  .Ret<Image>()
                                  .Attr<int64_t>("stride"));

XLA_FFI_DEFINE_HANDLER_SYMBOL(mjxvine_tower_conv_kernel_grad, KernelGradImpl,
                              ffi::Ffi::Bind()
                                  .Arg<Image>()
                                  .Arg<Image>()
                                  .Ret<Image>()
                                  .Attr<int64_t>("stride"));
