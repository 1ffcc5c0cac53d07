// The conv tower of mjxvine.networks.ConvTower on the CPU as XLA FFI handlers: the whole
// tower (4 convs 3x3 VALID with biases and ReLUs, a max pool, the mean) in one call, each
// image in one thread through every layer in buffers that stay in the core's cache. XLA's
// CPU convolution runs its small convs (8-32 channels) far below the machine's matmul
// rate. Built twice by mjxvine/native_conv.py: with AVX2 + FMA, and with AVX-512 (16
// lanes) for CPUs that have it; the images in runs on XLA's own thread pool.
#include <immintrin.h>
#include <atomic>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <mutex>
#include <new>
#include <algorithm>
#include <type_traits>
#include <vector>
#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

// The layers (those of mjxvine.networks.CONV_LAYERS): 3x3 VALID convs of strides 2, 1,
// 2, 1 with biases and ReLUs, a 2x2 max pool after the second, the mean over the last
// one's pixels. F in {8, 16, 32} features.
//
//   mjxvine_tower(x (N,H,W,C0), k1 (3,3,C0,F), b1 (F), k2 (3,3,F,F), b2, k3, b3, k4, b4)
//       -> features (N,F)
//   mjxvine_tower_train(the same) -> features (N,F), activations (N,R)
//   mjxvine_tower_grad(the same, activations (N,R), dfeatures (N,F))
//       -> dk1, db1, ..., dk4, db4
//
// The activations are what the gradient needs of the forward pass, per image: each conv's
// output after its ReLU and the pooled output. The max pool's gradient goes to the first
// maximum of its window in row-major order, a ReLU's where its output is > 0 (as JAX's).
// The gradient w.r.t. the image is not computed (XLA's, where it is needed).

// Buffers on 64-byte boundaries: a 16-lane load or store then stays within one cache line.
template <typename T>
struct Aligned {
  using value_type = T;
  Aligned() = default;
  template <typename U> Aligned(const Aligned<U>&) {}
  T* allocate(size_t n) { return static_cast<T*>(::operator new(n * sizeof(T), std::align_val_t(64))); }
  void deallocate(T* p, size_t) { ::operator delete(p, std::align_val_t(64)); }
  template <typename U> bool operator==(const Aligned<U>&) const { return true; }
  template <typename U> bool operator!=(const Aligned<U>&) const { return false; }
};
using Floats = std::vector<float, Aligned<float>>;

// A thread's buffer `slot` of at least n floats, kept from call to call (not cleared):
// allocating it afresh in every call costs page faults in each thread's heap. A run
// uses it from start to end on one thread.
inline float* Scratch(int slot, size_t n) {
  thread_local Floats buffers[2];
  if (buffers[slot].size() < n) buffers[slot].resize(n);
  return buffers[slot].data();
}

// n floats rounded up to whole cache lines.
constexpr int64_t Lines(int64_t n) { return (n + 15) / 16 * 16; }

constexpr int kLayers = 4;
constexpr int kStride[kLayers] = {2, 1, 2, 1};
constexpr bool kPool[kLayers] = {false, true, false, false};

// The vector instructions the kernels are written in: AVX2 (8 lanes) and, in the AVX-512
// build, AVX-512 (16 lanes).
struct Avx2 {
  using Vec = __m256;
  static constexpr int kLanes = 8;
  static Vec Load(const float* p) { return _mm256_loadu_ps(p); }
  static void Store(float* p, Vec v) { _mm256_storeu_ps(p, v); }
  static Vec Set1(float x) { return _mm256_set1_ps(x); }
  static Vec Zero() { return _mm256_setzero_ps(); }
  static Vec Fma(Vec a, Vec b, Vec c) { return _mm256_fmadd_ps(a, b, c); }
  static Vec Relu(Vec v) { return _mm256_max_ps(v, _mm256_setzero_ps()); }
};

#ifdef __AVX512F__
struct Avx512 {
  using Vec = __m512;
  static constexpr int kLanes = 16;
  static Vec Load(const float* p) { return _mm512_loadu_ps(p); }
  static void Store(float* p, Vec v) { _mm512_storeu_ps(p, v); }
  static Vec Set1(float x) { return _mm512_set1_ps(x); }
  static Vec Zero() { return _mm512_setzero_ps(); }
  static Vec Fma(Vec a, Vec b, Vec c) { return _mm512_fmadd_ps(a, b, c); }
  static Vec Relu(Vec v) { return _mm512_max_ps(v, _mm512_setzero_ps()); }
};
#endif

// P output pixels of one row from ow, all F = V vectors of channels:
// out = [relu](bias + sum_{kh,kw,c} in[s*oh+kh, s*(ow+p)+kw, c] * k[kh,kw,c,:]).
template <typename S, int V, int P>
inline void ConvBlock(const float* in, int64_t W, int64_t C, const float* k,
                      const typename S::Vec* b, int64_t s, int64_t oh, int64_t ow,
                      float* orow, bool relu) {
  constexpr int L = S::kLanes, F = L * V;
  typename S::Vec acc[P][V];
  for (int p = 0; p < P; ++p)
    for (int v = 0; v < V; ++v) acc[p][v] = b[v];
  for (int kh = 0; kh < 3; ++kh) {
    const float* xr = in + ((s * oh + kh) * W + s * ow) * C;
    const float* kr = k + kh * 3 * C * F;
    for (int64_t j = 0; j < 3 * C; ++j) {  // (kw, c) are contiguous in the input and in k
      typename S::Vec kv[V];
      for (int v = 0; v < V; ++v) kv[v] = S::Load(kr + j * F + L * v);
      for (int p = 0; p < P; ++p) {
        const auto xb = S::Set1(xr[p * s * C + j]);
        for (int v = 0; v < V; ++v) acc[p][v] = S::Fma(xb, kv[v], acc[p][v]);
      }
    }
  }
  for (int p = 0; p < P; ++p)
    for (int v = 0; v < V; ++v)
      S::Store(orow + (ow + p) * F + L * v, relu ? S::Relu(acc[p][v]) : acc[p][v]);
}

// Calls block(std::integral_constant<int, P>, ow) over a row of Wo output pixels, and one
// block of the r < P left at its end.
template <int R, typename Block>
inline void RowTail(int64_t r, int64_t ow, Block& block) {
  if constexpr (R > 0) {
    if (r == R) return block(std::integral_constant<int, R>{}, ow);
    RowTail<R - 1>(r, ow, block);
  }
}

template <int P, typename Block>
inline void Row(int64_t Wo, Block&& block) {
  int64_t ow = 0;
  for (; ow + P <= Wo; ow += P) block(std::integral_constant<int, P>{}, ow);
  RowTail<P - 1>(Wo - ow, ow, block);
}

// out (Ho,Wo,F) = [relu](conv(in (H,W,C), k (3,3,C,F), stride s) + bias); one image.
template <typename S, int V, int P>
void ConvImage(const float* in, int64_t H, int64_t W, int64_t C, const float* k,
               const float* bias, int64_t s, float* out, bool relu) {
  constexpr int L = S::kLanes;
  const int64_t Ho = (H - 3) / s + 1, Wo = (W - 3) / s + 1;
  typename S::Vec b[V];
  for (int v = 0; v < V; ++v) b[v] = bias ? S::Load(bias + L * v) : S::Zero();
  for (int64_t oh = 0; oh < Ho; ++oh) {
    float* orow = out + oh * Wo * L * V;
    Row<P>(Wo, [&](auto n, int64_t ow) {
      ConvBlock<S, V, decltype(n)::value>(in, W, C, k, b, s, oh, ow, orow, relu);
    });
  }
}

// db (F) += the sum of dy (n, F) over its n pixels.
template <int F>
inline void AddBiasGrad(const float* dy, int64_t n, float* db) {
  float sum[F];
  for (int f = 0; f < F; ++f) sum[f] = db[f];
  for (int64_t p = 0; p < n; ++p)
    for (int f = 0; f < F; ++f) sum[f] += dy[p * F + f];
  for (int f = 0; f < F; ++f) db[f] = sum[f];
}

// dk (3,3,C,F) += sum_{oh,ow} in[s*oh+kh, s*ow+kw, c] * dy[oh,ow,:]; db (F) += sum dy. The
// taps (kw, c) of a kh row in blocks of Q (3C % Q == 0).
template <typename S, int V, int Q>
void KernelGradImage(const float* in, int64_t H, int64_t W, int64_t C, const float* dy,
                     int64_t s, float* dk, float* db) {
  constexpr int L = S::kLanes, F = L * V;
  const int64_t Ho = (H - 3) / s + 1, Wo = (W - 3) / s + 1;
  for (int64_t kh = 0; kh < 3; ++kh) {
    for (int64_t j0 = 0; j0 < 3 * C; j0 += Q) {
      float* dkb = dk + (kh * 3 * C + j0) * F;
      typename S::Vec acc[Q][V];
      for (int q = 0; q < Q; ++q)
        for (int v = 0; v < V; ++v) acc[q][v] = S::Load(dkb + q * F + L * v);
      for (int64_t oh = 0; oh < Ho; ++oh) {
        const float* xr = in + (s * oh + kh) * W * C + j0;
        const float* dyr = dy + oh * Wo * F;
        for (int64_t ow = 0; ow < Wo; ++ow) {
          typename S::Vec g[V];
          for (int v = 0; v < V; ++v) g[v] = S::Load(dyr + ow * F + L * v);
          const float* xp = xr + s * ow * C;
          for (int q = 0; q < Q; ++q) {
            const auto xb = S::Set1(xp[q]);
            for (int v = 0; v < V; ++v) acc[q][v] = S::Fma(xb, g[v], acc[q][v]);
          }
        }
      }
      for (int q = 0; q < Q; ++q)
        for (int v = 0; v < V; ++v) S::Store(dkb + q * F + L * v, acc[q][v]);
    }
  }
  AddBiasGrad<F>(dy, Ho * Wo, db);
}

// As KernelGradImage for one input channel: all 9 taps in one pass.
template <typename S, int V>
void KernelGradImageFirst(const float* in, int64_t H, int64_t W, const float* dy, int64_t s,
                          float* dk, float* db) {
  constexpr int L = S::kLanes, F = L * V;
  const int64_t Ho = (H - 3) / s + 1, Wo = (W - 3) / s + 1;
  typename S::Vec acc[9][V];
  for (int q = 0; q < 9; ++q)
    for (int v = 0; v < V; ++v) acc[q][v] = S::Load(dk + q * F + L * v);
  for (int64_t oh = 0; oh < Ho; ++oh) {
    for (int64_t ow = 0; ow < Wo; ++ow) {
      typename S::Vec g[V];
      for (int v = 0; v < V; ++v) g[v] = S::Load(dy + (oh * Wo + ow) * F + L * v);
      for (int q = 0; q < 9; ++q) {
        const auto xb = S::Set1(in[(s * oh + q / 3) * W + s * ow + q % 3]);
        for (int v = 0; v < V; ++v) acc[q][v] = S::Fma(xb, g[v], acc[q][v]);
      }
    }
  }
  for (int q = 0; q < 9; ++q)
    for (int v = 0; v < V; ++v) S::Store(dk + q * F + L * v, acc[q][v]);
  AddBiasGrad<F>(dy, Ho * Wo, db);
}

#ifdef __AVX512F__
// With AVX-512 (a second build of this file, for CPUs that have it): 16 lanes a vector.
// For F = 8 outputs a vector holds two taps j, j+1 (lane 2f+q: tap j+q's share of output
// f), the input's two taps a 64-bit broadcast; adjacent lanes are added at the end.
inline __m512 Broadcast2(const float* p) {  // [p[0], p[1]] * 8
  double d;
  std::memcpy(&d, p, sizeof d);
  return _mm512_castpd_ps(_mm512_set1_pd(d));
}

// The taps (kw, c) of a kernel row in pairs: M = ceil(3C / 2) vectors a row.
inline int64_t PairsPerRow(int64_t C) { return (3 * C + 1) / 2; }

// k (3, 3C, 8), the taps (kw, c) of each kh contiguous -> (3, M, 16): lane 2f+q of pair m
// of row kh is k[kh, 2m+q, f] (0 past the row's last tap, where 3C is odd).
inline Floats InterleaveTaps(const float* k, int64_t C) {
  const int64_t M = PairsPerRow(C);
  Floats out(3 * M * 16, 0.0f);
  for (int64_t kh = 0; kh < 3; ++kh)
    for (int64_t j = 0; j < 3 * C; ++j)
      for (int f = 0; f < 8; ++f)
        out[(kh * M + j / 2) * 16 + 2 * f + j % 2] = k[(kh * 3 * C + j) * 8 + f];
  return out;
}

// The input's taps j, j+1 (j alone at the end of an odd row, whose pair's weight is 0).
inline __m512 InputPair(const float* xr, int64_t j, int64_t row) {
  return j + 1 < row ? Broadcast2(xr + j) : _mm512_set1_ps(xr[j]);
}

template <int P>
inline void ConvBlockPair(const float* in, int64_t W, int64_t C, const float* ki, __m512 b2,
                          int64_t s, int64_t oh, int64_t ow, float* orow, bool relu) {
  __m512 acc[P];
  for (int p = 0; p < P; ++p) acc[p] = _mm512_setzero_ps();
  const int64_t M = PairsPerRow(C);
  for (int kh = 0; kh < 3; ++kh) {
    const float* xr = in + ((s * oh + kh) * W + s * ow) * C;
    const float* kr = ki + kh * M * 16;
    for (int64_t m = 0; m < M; ++m) {
      const __m512 kv = _mm512_loadu_ps(kr + m * 16);
      for (int p = 0; p < P; ++p)
        acc[p] = _mm512_fmadd_ps(InputPair(xr + p * s * C, 2 * m, 3 * C), kv, acc[p]);
    }
  }
  const __m512i even = _mm512_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30);
  const __m512i odd = _mm512_setr_epi32(1, 3, 5, 7, 9, 11, 13, 15, 17, 19, 21, 23, 25, 27, 29, 31);
  const __m512 zero = _mm512_setzero_ps();
  for (int p = 0; p < P; p += 2) {  // two pixels' 8 outputs a vector
    const __m512 other = p + 1 < P ? acc[p + 1] : zero;
    __m512 y = _mm512_add_ps(_mm512_permutex2var_ps(acc[p], even, other),
                             _mm512_permutex2var_ps(acc[p], odd, other));
    y = _mm512_add_ps(y, b2);
    if (relu) y = _mm512_max_ps(y, zero);
    if (p + 1 < P) _mm512_storeu_ps(orow + (ow + p) * 8, y);
    else _mm256_storeu_ps(orow + (ow + p) * 8, _mm512_castps512_ps256(y));
  }
}

// As ConvImage for F = 8, with the kernel from InterleaveTaps.
template <int P>
void ConvImagePair(const float* in, int64_t H, int64_t W, int64_t C, const float* ki,
                   const float* bias, int64_t s, float* out, bool relu) {
  const int64_t Ho = (H - 3) / s + 1, Wo = (W - 3) / s + 1;
  const __m512 b2 = bias ? _mm512_broadcast_f32x8(_mm256_loadu_ps(bias)) : _mm512_setzero_ps();
  for (int64_t oh = 0; oh < Ho; ++oh) {
    float* orow = out + oh * Wo * 8;
    Row<P>(Wo, [&](auto n, int64_t ow) {
      ConvBlockPair<decltype(n)::value>(in, W, C, ki, b2, s, oh, ow, orow, relu);
    });
  }
}

// As KernelGradImage for F = 8, C a multiple of 8: the taps (kw, c) of a kh row in
// blocks of 2 Q2.
template <int Q2>
void KernelGradImagePair(const float* in, int64_t H, int64_t W, int64_t C, const float* dy,
                         int64_t s, float* dk, float* db) {
  const int64_t Ho = (H - 3) / s + 1, Wo = (W - 3) / s + 1;
  const __m512i spread = _mm512_setr_epi32(0, 8, 1, 9, 2, 10, 3, 11, 4, 12, 5, 13, 6, 14, 7, 15);
  const __m512i gather = _mm512_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14, 1, 3, 5, 7, 9, 11, 13, 15);
  const __m512i twice = _mm512_setr_epi32(0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 5, 5, 6, 6, 7, 7);
  for (int64_t kh = 0; kh < 3; ++kh) {
    for (int64_t j0 = 0; j0 < 3 * C; j0 += 2 * Q2) {
      float* dkb = dk + (kh * 3 * C + j0) * 8;
      __m512 acc[Q2];  // lane 2f+q: dk[kh, j0 + 2m + q, f]
      for (int m = 0; m < Q2; ++m)
        acc[m] = _mm512_permutexvar_ps(spread, _mm512_loadu_ps(dkb + m * 16));
      for (int64_t oh = 0; oh < Ho; ++oh) {
        const float* xr = in + (s * oh + kh) * W * C + j0;
        const float* dyr = dy + oh * Wo * 8;
        for (int64_t ow = 0; ow < Wo; ++ow) {
          const __m512 g = _mm512_permutexvar_ps(
              twice, _mm512_castps256_ps512(_mm256_loadu_ps(dyr + ow * 8)));
          const float* xp = xr + s * ow * C;
          for (int m = 0; m < Q2; ++m)
            acc[m] = _mm512_fmadd_ps(Broadcast2(xp + 2 * m), g, acc[m]);
        }
      }
      for (int m = 0; m < Q2; ++m)
        _mm512_storeu_ps(dkb + m * 16, _mm512_permutexvar_ps(gather, acc[m]));
    }
  }
  AddBiasGrad<8>(dy, Ho * Wo, db);
}

// As KernelGradImage for F = 8 and one input channel: all 9 taps in one pass, each kernel
// row as the pair (kw 0, 1) and kw 2 alone (whose odd lanes are not used).
inline void KernelGradImageFirstPair(const float* in, int64_t H, int64_t W, const float* dy,
                                     int64_t s, float* dk, float* db) {
  const int64_t Ho = (H - 3) / s + 1, Wo = (W - 3) / s + 1;
  const __m512i twice = _mm512_setr_epi32(0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 5, 5, 6, 6, 7, 7);
  __m512 pair[3], last[3];
  for (int kh = 0; kh < 3; ++kh) pair[kh] = last[kh] = _mm512_setzero_ps();
  for (int64_t oh = 0; oh < Ho; ++oh) {
    const float* dyr = dy + oh * Wo * 8;
    for (int64_t ow = 0; ow < Wo; ++ow) {
      const __m512 g = _mm512_permutexvar_ps(
          twice, _mm512_castps256_ps512(_mm256_loadu_ps(dyr + ow * 8)));
      for (int kh = 0; kh < 3; ++kh) {
        const float* xp = in + (s * oh + kh) * W + s * ow;
        pair[kh] = _mm512_fmadd_ps(Broadcast2(xp), g, pair[kh]);
        last[kh] = _mm512_fmadd_ps(_mm512_set1_ps(xp[2]), g, last[kh]);
      }
    }
  }
  alignas(64) float a[16], b[16];
  for (int kh = 0; kh < 3; ++kh) {
    _mm512_store_ps(a, pair[kh]);
    _mm512_store_ps(b, last[kh]);
    for (int f = 0; f < 8; ++f) {
      dk[(kh * 3 + 0) * 8 + f] += a[2 * f];
      dk[(kh * 3 + 1) * 8 + f] += a[2 * f + 1];
      dk[(kh * 3 + 2) * 8 + f] += b[2 * f];
    }
  }
  AddBiasGrad<8>(dy, Ho * Wo, db);
}

#endif

// The layers' sizes, and where each image's activations lie in its (R,) slice.
struct TowerShapes {
  int64_t N, C0, F;
  int64_t h[kLayers + 1], w[kLayers + 1];  // h[0] the image's, h[i] conv i-1's output
  int64_t ph, pw;                          // the pooled size
  int64_t act_at[kLayers + 1], pooled_at, R;
  size_t buffer;                           // floats of each of Backward's 3 buffers
};

template <int V>
struct Tower {
  static constexpr int F = 8 * V;
  static constexpr int P = V == 1 ? 10 : (V == 2 ? 5 : 2);  // output pixels per block
  static constexpr int Q = V == 1 ? 12 : (V == 2 ? 6 : 3);  // kernel-gradient taps per block

  static constexpr int kPairP = 10;  // AVX-512, F = 8: output pixels per block
  static constexpr int kWideP = V == 2 ? 12 : 8, kWideQ = V == 2 ? 12 : 6;  // F = 16, 32

  const TowerShapes& t;
  const float* k[kLayers];
  const float* b[kLayers];
  Floats k_back[kLayers];  // k flipped, in and out swapped: the input gradient's
  Floats k_pair[kLayers], k_back_pair[kLayers];  // InterleaveTaps' (AVX-512, F = 8)

  Tower(const TowerShapes& shapes, const float* const* ks, const float* const* bs,
        bool backward)
      : t(shapes) {
    for (int i = 0; i < kLayers; ++i) k[i] = ks[i], b[i] = bs[i];
    for (int i = 1; i < kLayers && backward; ++i) {  // no input gradient for the image
      k_back[i].resize(9 * F * F);
      for (int kh = 0; kh < 3; ++kh)
        for (int kw = 0; kw < 3; ++kw)
          for (int c = 0; c < F; ++c)
            for (int f = 0; f < F; ++f)
              k_back[i][((kh * 3 + kw) * F + f) * F + c] =
                  k[i][(((2 - kh) * 3 + (2 - kw)) * F + c) * F + f];
    }
#ifdef __AVX512F__
    if constexpr (V == 1) {
      for (int i = 0; i < kLayers; ++i) {
        k_pair[i] = InterleaveTaps(k[i], InC(i));
        if (!k_back[i].empty()) k_back_pair[i] = InterleaveTaps(k_back[i].data(), F);
      }
    }
#endif
  }

  // out = [relu](conv(in (H,W,C), kk, stride s) + bias) (kpair: kk's InterleaveTaps, or
  // empty), by the widest kernel that applies.
  void Conv(const float* in, int64_t H, int64_t W, int64_t C, const float* kk,
            const Floats& kpair, const float* bias, int64_t s, float* out,
            bool relu) const {
#ifdef __AVX512F__
    if constexpr (V == 1) {
      if (!kpair.empty())
        return ConvImagePair<kPairP>(in, H, W, C, kpair.data(), bias, s, out, relu);
    } else {
      return ConvImage<Avx512, V / 2, kWideP>(in, H, W, C, kk, bias, s, out, relu);
    }
#endif
    ConvImage<Avx2, V, P>(in, H, W, C, kk, bias, s, out, relu);
  }

  // dk += .., db += .. of a conv of in (H,W,C) with output gradient g, by the widest
  // kernel that applies.
  void KernelGrad(const float* in, int64_t H, int64_t W, int64_t C, const float* g,
                  int64_t s, float* dk, float* db) const {
#ifdef __AVX512F__
    if constexpr (V == 1) {
      if (C == 1) return KernelGradImageFirstPair(in, H, W, g, s, dk, db);
      if (C % 8 == 0) return KernelGradImagePair<12>(in, H, W, C, g, s, dk, db);
    } else {
      if (C == 1) return KernelGradImageFirst<Avx512, V / 2>(in, H, W, g, s, dk, db);
      if ((3 * C) % kWideQ == 0)
        return KernelGradImage<Avx512, V / 2, kWideQ>(in, H, W, C, g, s, dk, db);
    }
#endif
    if (V == 1 && C == 1)
      KernelGradImageFirst<Avx2, 1>(in, H, W, g, s, dk, db);
    else if ((3 * C) % Q == 0)
      KernelGradImage<Avx2, V, Q>(in, H, W, C, g, s, dk, db);
    else
      KernelGradImage<Avx2, V, 3>(in, H, W, C, g, s, dk, db);
  }

  // conv i's input: its size, channels and data (a: the image's activations).
  int64_t InH(int i) const { return i > 0 && kPool[i - 1] ? t.ph : t.h[i]; }
  int64_t InW(int i) const { return i > 0 && kPool[i - 1] ? t.pw : t.w[i]; }
  int64_t InC(int i) const { return i == 0 ? t.C0 : F; }
  const float* In(const float* x, const float* a, int i) const {
    return i == 0 ? x : a + (kPool[i - 1] ? t.pooled_at : t.act_at[i]);
  }

  void Forward(const float* x, float* a, float* feat) const {
    for (int i = 0; i < kLayers; ++i) {
      Conv(In(x, a, i), InH(i), InW(i), InC(i), k[i], k_pair[i], b[i], kStride[i],
           a + t.act_at[i + 1], true);
      if (kPool[i]) Pool(a + t.act_at[i + 1], t.w[i + 1], a + t.pooled_at);
    }
    const int64_t n = t.h[kLayers] * t.w[kLayers];
    const float* last = a + t.act_at[kLayers];
    const __m256 scale = _mm256_set1_ps(1.0f / static_cast<float>(n));
    for (int v = 0; v < V; ++v) {
      __m256 sum = _mm256_setzero_ps();
      for (int64_t p = 0; p < n; ++p) sum = _mm256_add_ps(sum, _mm256_loadu_ps(last + p * F + 8 * v));
      _mm256_storeu_ps(feat + 8 * v, _mm256_mul_ps(sum, scale));
    }
  }

  // a (.., w, F) -> pooled (ph, pw, F), the max of each 2x2 window.
  void Pool(const float* a, int64_t w, float* pooled) const {
    for (int64_t i = 0; i < t.ph; ++i)
      for (int64_t j = 0; j < t.pw; ++j)
        for (int v = 0; v < V; ++v) {
          const float* q = a + ((2 * i) * w + 2 * j) * F + 8 * v;
          const __m256 m = _mm256_max_ps(
              _mm256_max_ps(_mm256_loadu_ps(q), _mm256_loadu_ps(q + F)),
              _mm256_max_ps(_mm256_loadu_ps(q + w * F), _mm256_loadu_ps(q + w * F + F)));
          _mm256_storeu_ps(pooled + (i * t.pw + j) * F + 8 * v, m);
        }
  }

  // The pool's gradient: gp (ph, pw, F) to the first maximum of each window of a
  // (h, w, F) in row-major order -> g (h, w, F), zero elsewhere.
  void PoolGrad(const float* a, int64_t h, int64_t w, const float* pooled, const float* gp,
                float* g) const {
    std::fill(g, g + h * w * F, 0.0f);
    const __m256 zero = _mm256_setzero_ps();
    for (int64_t i = 0; i < t.ph; ++i)
      for (int64_t j = 0; j < t.pw; ++j)
        for (int v = 0; v < V; ++v) {
          const int64_t o = (i * t.pw + j) * F + 8 * v;
          const __m256 m = _mm256_loadu_ps(pooled + o), d = _mm256_loadu_ps(gp + o);
          __m256 free = _mm256_castsi256_ps(_mm256_set1_epi32(-1));  // no maximum taken yet
          const int64_t at[4] = {0, F, w * F, w * F + F};
          for (int q = 0; q < 4; ++q) {
            const int64_t e = ((2 * i) * w + 2 * j) * F + 8 * v + at[q];
            const __m256 hit = _mm256_and_ps(free, _mm256_cmp_ps(_mm256_loadu_ps(a + e), m, _CMP_EQ_OQ));
            _mm256_storeu_ps(g + e, _mm256_blendv_ps(zero, d, hit));
            free = _mm256_andnot_ps(hit, free);
          }
        }
  }

  // g (Ho,Wo,F), the gradient w.r.t. conv i's output -> dx (H,W,F) w.r.t. its input: the
  // stride-1 conv of g dilated by the stride and padded by 2 with the flipped kernel.
  void InputGrad(const float* g, int i, int64_t H, int64_t W, float* padded, float* dx) const {
    const int64_t s = kStride[i], Ho = (H - 3) / s + 1, Wo = (W - 3) / s + 1;
    const int64_t Hp = H + 2, Wp = W + 2;
    std::fill(padded, padded + Hp * Wp * F, 0.0f);
    for (int64_t oh = 0; oh < Ho; ++oh)
      for (int64_t ow = 0; ow < Wo; ++ow)
        std::copy(g + (oh * Wo + ow) * F, g + (oh * Wo + ow + 1) * F,
                  padded + ((2 + s * oh) * Wp + 2 + s * ow) * F);
    Conv(padded, Hp, Wp, F, k_back[i].data(), k_back_pair[i], nullptr, 1, dx, false);
  }

  // Adds this image's parameter gradients into dk[i], db[i] (the thread's copies); work:
  // 3 t.buffer floats.
  void Backward(const float* x, const float* a, const float* dfeat, float* work,
                float* const* dk, float* const* db) const {
    float* g = work;                      // the gradient w.r.t. the current conv's output
    float* gin = work + t.buffer;         // ... w.r.t. its input
    float* padded = work + 2 * t.buffer;
    const int64_t n = t.h[kLayers] * t.w[kLayers];
    for (int64_t p = 0; p < n; ++p)
      for (int f = 0; f < F; ++f) g[p * F + f] = dfeat[f] / static_cast<float>(n);
    for (int i = kLayers - 1; i >= 0; --i) {
      const float* out = a + t.act_at[i + 1];
      for (int64_t e = 0; e < t.h[i + 1] * t.w[i + 1] * F; ++e)
        g[e] = out[e] > 0.0f ? g[e] : 0.0f;  // the ReLU's
      const int64_t H = InH(i), W = InW(i), C = InC(i);
      KernelGrad(In(x, a, i), H, W, C, g, kStride[i], dk[i], db[i]);
      if (i == 0) break;
      InputGrad(g, i, H, W, padded, gin);
      if (kPool[i - 1])
        PoolGrad(a + t.act_at[i], t.h[i], t.w[i], a + t.pooled_at, gin, g);
      else
        std::swap(g, gin);
    }
  }
};

using K4 = ffi::Buffer<ffi::F32, 4>;
using B1 = ffi::Buffer<ffi::F32, 1>;
using F2 = ffi::Buffer<ffi::F32, 2>;  // (N, F) or (N, R)
using K4Out = ffi::ResultBuffer<ffi::F32, 4>;
using B1Out = ffi::ResultBuffer<ffi::F32, 1>;
using F2Out = ffi::ResultBuffer<ffi::F32, 2>;

ffi::Error TowerCheck(const K4& x, const K4* const* ks, const B1* const* bs, TowerShapes& t) {
  const auto xd = x.dimensions();
  t.N = xd[0], t.h[0] = xd[1], t.w[0] = xd[2], t.C0 = xd[3];
  t.F = ks[0]->dimensions()[3];
  if (t.F != 8 && t.F != 16 && t.F != 32)
    return ffi::Error::InvalidArgument("tower: features must be 8, 16 or 32");
  int64_t at = 0;
  size_t most = 0;
  for (int i = 0; i < kLayers; ++i) {
    const auto kd = ks[i]->dimensions();
    if (kd[0] != 3 || kd[1] != 3 || kd[2] != (i == 0 ? t.C0 : t.F) || kd[3] != t.F ||
        bs[i]->dimensions()[0] != t.F)
      return ffi::Error::InvalidArgument("tower: kernel or bias shapes do not match");
    const bool pooled_in = i > 0 && kPool[i - 1];
    const int64_t H = pooled_in ? t.ph : t.h[i], W = pooled_in ? t.pw : t.w[i];
    if (H < 3 || W < 3) return ffi::Error::InvalidArgument("tower: image too small");
    if (i > 0) most = std::max<size_t>(most, (H + 2) * (W + 2) * t.F);  // InputGrad's pad
    t.h[i + 1] = (H - 3) / kStride[i] + 1, t.w[i + 1] = (W - 3) / kStride[i] + 1;
    t.act_at[i + 1] = at, at += Lines(t.h[i + 1] * t.w[i + 1] * t.F);
    most = std::max<size_t>(most, t.h[i + 1] * t.w[i + 1] * t.F);
    if (kPool[i]) {
      t.ph = t.h[i + 1] / 2, t.pw = t.w[i + 1] / 2;
      if (t.ph < 1 || t.pw < 1) return ffi::Error::InvalidArgument("tower: image too small");
      t.pooled_at = at, at += Lines(t.ph * t.pw * t.F);
    }
  }
  t.R = at;
  t.buffer = Lines(most);
  return ffi::Error::Success();
}

// ---------------------------------------------------------------------------------------
// Threads: each call is cut into runs of consecutive images, and the runs go to XLA's own
// intra-op thread pool (the one its CPU ops and its other thunks run on), so that a tower
// call and whatever XLA runs beside it, another tower call included, share the cores
// instead of each starting threads of its own. A call returns a future at once: the
// caller's thread is free for XLA's other work, and the future is set when the last run
// is done.

// The most threads one call runs on: $MJXVINE_NATIVE_THREADS where set (>= 1), else the
// pool's size. The results do not depend on it.
int64_t Threads(ffi::ThreadPool& pool, int64_t runs) {
  int64_t n = pool.num_threads();
  if (const char* env = std::getenv("MJXVINE_NATIVE_THREADS")) n = std::atoll(env);
  return std::clamp<int64_t>(n, 1, std::max<int64_t>(runs, 1));
}

// A call's work: Run(r) for every r in [0, runs), taken in turn by up to Threads() tasks
// on the pool, then Done() once, by the task that finishes last, and the future set.
struct Job {
  int64_t runs = 0;
  std::atomic<int64_t> next{0}, tasks{0};
  ffi::Promise promise;

  virtual ~Job() = default;
  virtual void Run(int64_t r) = 0;
  virtual void Done() {}

  static void Work(const std::shared_ptr<Job>& job) {
    for (int64_t r = job->next++; r < job->runs; r = job->next++) job->Run(r);
    if (--job->tasks == 0) {
      job->Done();
      job->promise.SetAvailable();
    }
  }

  // Starts `job` on the pool; its buffers must live until the future is set.
  static ffi::Future Start(ffi::ThreadPool& pool, std::shared_ptr<Job> job) {
    ffi::Future future(job->promise);
    const int64_t tasks = Threads(pool, job->runs);
    job->tasks = tasks;
    for (int64_t i = 0; i < tasks; ++i) pool.Schedule([job] { Work(job); });
    return future;
  }
};

ffi::Future Failed(ffi::Error error) {
  ffi::Promise promise;
  ffi::Future future(promise);
  promise.SetError(std::move(error));
  return future;
}

// Reused buffers of floats, for what a call needs until its future is set (a thread's
// Scratch would be taken by its next call while this one's runs go on).
class BufferPool {
 public:
  Floats Take(size_t n) {
    Floats out;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      if (!free_.empty()) out = std::move(free_.back()), free_.pop_back();
    }
    if (out.size() < n) out.resize(n);
    return out;
  }
  void Give(Floats buffer) {
    std::lock_guard<std::mutex> lock(mutex_);
    free_.push_back(std::move(buffer));
  }

 private:
  std::mutex mutex_;
  std::vector<Floats> free_;
};

BufferPool& GradParts() {
  static BufferPool* pool = new BufferPool;  // never destroyed: a call may run at exit
  return *pool;
}

// Images per forward run: enough runs for the threads to balance, few enough that each
// run's setup is small beside its images.
constexpr int64_t kForwardRun = 4;

// acts: (N, R) to keep the activations, or null.
template <int V>
struct ForwardJob : Job {
  TowerShapes t;
  Tower<V> tower;
  const float* x;
  float *feat, *acts;

  ForwardJob(const TowerShapes& shapes, const float* const* ks, const float* const* bs,
             const float* x, float* feat, float* acts)
      : t(shapes), tower(t, ks, bs, false), x(x), feat(feat), acts(acts) {
    runs = (t.N + kForwardRun - 1) / kForwardRun;
  }

  void Run(int64_t r) override {
    const int64_t image = t.h[0] * t.w[0] * t.C0;
    float* mine = acts ? nullptr : Scratch(0, t.R);
    for (int64_t n = r * kForwardRun; n < std::min(t.N, (r + 1) * kForwardRun); ++n)
      tower.Forward(x + n * image, acts ? acts + n * t.R : mine, feat + n * t.F);
  }
};

// The images in kGradChunks runs of consecutive ones, each summed into its own copy of
// the gradients, the copies then added in run order: the same sums whichever thread
// takes which run, and however many threads there are.
constexpr int64_t kGradChunks = 16;

template <int V>
struct GradJob : Job {
  TowerShapes t;
  Tower<V> tower;
  const float *x, *acts, *dfeat;
  float *dk[kLayers], *db[kLayers];
  int64_t ksize[kLayers], total = 0;
  Floats part;  // runs x total: each run's copy, on cache lines of its own

  GradJob(const TowerShapes& shapes, const float* const* ks, const float* const* bs,
          const float* x, const float* acts, const float* dfeat, float* const* dks,
          float* const* dbs)
      : t(shapes), tower(t, ks, bs, true), x(x), acts(acts), dfeat(dfeat) {
    for (int i = 0; i < kLayers; ++i) {
      dk[i] = dks[i], db[i] = dbs[i];
      ksize[i] = 9 * (i == 0 ? t.C0 : t.F) * t.F, total += ksize[i] + t.F;
    }
    total = Lines(total);
    runs = std::min(kGradChunks, std::max<int64_t>(t.N, 1));
    part = GradParts().Take(runs * total);
  }

  void Run(int64_t c) override {
    float* mine = part.data() + c * total;
    std::fill(mine, mine + total, 0.0f);
    float* mdk[kLayers];
    float* mdb[kLayers];
    for (int i = 0; i < kLayers; ++i) {
      mdk[i] = mine, mine += ksize[i];
      mdb[i] = mine, mine += t.F;
    }
    float* work = Scratch(1, 3 * t.buffer);
    const int64_t image = t.h[0] * t.w[0] * t.C0;
    for (int64_t n = t.N * c / runs; n < t.N * (c + 1) / runs; ++n)
      tower.Backward(x + n * image, acts + n * t.R, dfeat + n * t.F, work, mdk, mdb);
  }

  void Done() override {
    int64_t off = 0;
    for (int i = 0; i < kLayers; ++i) {
      for (float* out : {dk[i], db[i]}) {
        const int64_t size = out == dk[i] ? ksize[i] : t.F;
        for (int64_t e = 0; e < size; ++e) {
          float sum = 0.0f;
          for (int64_t c = 0; c < runs; ++c) sum += part[c * total + off + e];
          out[e] = sum;
        }
        off += size;
      }
    }
    GradParts().Give(std::move(part));
  }
};

template <typename Fn>
void ByFeatures(int64_t F, Fn&& fn) {
  if (F == 8) fn(std::integral_constant<int, 1>{});
  else if (F == 16) fn(std::integral_constant<int, 2>{});
  else fn(std::integral_constant<int, 4>{});
}

ffi::Future TowerForwardAny(ffi::ThreadPool& pool, K4& x, K4& k1, B1& b1, K4& k2, B1& b2,
                            K4& k3, B1& b3, K4& k4, B1& b4, float* feat, F2Out* acts) {
  TowerShapes t;
  const K4* kb[] = {&k1, &k2, &k3, &k4};
  const B1* bb[] = {&b1, &b2, &b3, &b4};
  if (auto e = TowerCheck(x, kb, bb, t); e.failure()) return Failed(std::move(e));
  if (acts && ((*acts)->dimensions()[0] != t.N || (*acts)->dimensions()[1] != t.R))
    return Failed(ffi::Error::InvalidArgument("tower: activations shape does not match"));
  const float* ks[] = {k1.typed_data(), k2.typed_data(), k3.typed_data(), k4.typed_data()};
  const float* bs[] = {b1.typed_data(), b2.typed_data(), b3.typed_data(), b4.typed_data()};
  float* a = acts ? (*acts)->typed_data() : nullptr;
  std::shared_ptr<Job> job;
  ByFeatures(t.F, [&](auto v) {
    job = std::make_shared<ForwardJob<decltype(v)::value>>(t, ks, bs, x.typed_data(), feat, a);
  });
  return Job::Start(pool, std::move(job));
}

ffi::Future TowerForwardImpl(ffi::ThreadPool pool, K4 x, K4 k1, B1 b1, K4 k2, B1 b2, K4 k3,
                             B1 b3, K4 k4, B1 b4, F2Out feat) {
  return TowerForwardAny(pool, x, k1, b1, k2, b2, k3, b3, k4, b4, feat->typed_data(), nullptr);
}

ffi::Future TowerTrainImpl(ffi::ThreadPool pool, K4 x, K4 k1, B1 b1, K4 k2, B1 b2, K4 k3,
                           B1 b3, K4 k4, B1 b4, F2Out feat, F2Out acts) {
  return TowerForwardAny(pool, x, k1, b1, k2, b2, k3, b3, k4, b4, feat->typed_data(), &acts);
}

ffi::Future TowerGradImpl(ffi::ThreadPool pool, K4 x, K4 k1, B1 b1, K4 k2, B1 b2, K4 k3,
                          B1 b3, K4 k4, B1 b4, F2 acts, F2 dfeat, K4Out dk1, B1Out db1,
                          K4Out dk2, B1Out db2, K4Out dk3, B1Out db3, K4Out dk4, B1Out db4) {
  TowerShapes t;
  const K4* kb[] = {&k1, &k2, &k3, &k4};
  const B1* bb[] = {&b1, &b2, &b3, &b4};
  if (auto e = TowerCheck(x, kb, bb, t); e.failure()) return Failed(std::move(e));
  if (dfeat.dimensions()[0] != t.N || dfeat.dimensions()[1] != t.F ||
      acts.dimensions()[0] != t.N || acts.dimensions()[1] != t.R)
    return Failed(ffi::Error::InvalidArgument(
        "tower grad: activations or dfeatures shape does not match"));
  const float* ks[] = {k1.typed_data(), k2.typed_data(), k3.typed_data(), k4.typed_data()};
  const float* bs[] = {b1.typed_data(), b2.typed_data(), b3.typed_data(), b4.typed_data()};
  float* dk[] = {dk1->typed_data(), dk2->typed_data(), dk3->typed_data(), dk4->typed_data()};
  float* db[] = {db1->typed_data(), db2->typed_data(), db3->typed_data(), db4->typed_data()};
  std::shared_ptr<Job> job;
  ByFeatures(t.F, [&](auto v) {
    job = std::make_shared<GradJob<decltype(v)::value>>(
        t, ks, bs, x.typed_data(), acts.typed_data(), dfeat.typed_data(), dk, db);
  });
  return Job::Start(pool, std::move(job));
}

}  // namespace

#define TOWER_ARGS .Ctx<ffi::ThreadPool>().Arg<K4>().Arg<K4>().Arg<B1>().Arg<K4>().Arg<B1>().Arg<K4>().Arg<B1>().Arg<K4>().Arg<B1>()

XLA_FFI_DEFINE_HANDLER_SYMBOL(mjxvine_tower, TowerForwardImpl,
                              ffi::Ffi::Bind() TOWER_ARGS.Ret<F2>());

XLA_FFI_DEFINE_HANDLER_SYMBOL(mjxvine_tower_train, TowerTrainImpl,
                              ffi::Ffi::Bind() TOWER_ARGS.Ret<F2>().Ret<F2>());

XLA_FFI_DEFINE_HANDLER_SYMBOL(mjxvine_tower_grad, TowerGradImpl,
                              ffi::Ffi::Bind() TOWER_ARGS.Arg<F2>().Arg<F2>()
                                  .Ret<K4>().Ret<B1>().Ret<K4>().Ret<B1>()
                                  .Ret<K4>().Ret<B1>().Ret<K4>().Ret<B1>());
