// The two shared decoders, forward only (no gradient): the CPU kernel (plain C++ and OpenMP, no torch).
//
// Written by hand because the queries that need no gradient (tracking's renders and spatial
// differences, meshing, evaluation renders) are dominated by memory traffic, not arithmetic, when torch
// runs the decoders layer by layer: each layer's input and output for all N points goes through memory
// (N x 80 after a concatenation, N x 32, N x 16, N x 63 after another, ...), at 32 to 80 values per point
// against about 5,000 multiply-adds. Here the points go through in blocks small enough for L1 and both
// MLPs run on a block before the next is loaded.
//
// Maths (identical to Decoders.forward in decoders.py, which the tests compare against):
//   x   = [blob | feat]                   (n_blob + n_feat)
//   h   = relu(W1 x + b1)                 (n_hidden)
//   o   = W2 h + b2                       (1 + n_geo): sdf = o[0], g = o[1:]
//   y   = [blob | g]                      (n_blob + n_geo)
//   k   = relu(W3 y + b3)                 (n_hidden)
//   rgb = sigmoid(W4 k + b4)              (3)
// Weights are torch.nn.Linear's: W (out, in) row-major.
//
// Speed: inside a block the values are stored feature-major (one row of kBlockPoints values per feature),
// so a layer is, per output, a sum over inputs of a weight times a row. Four outputs and sixteen points
// (float32) are accumulated at once in vector registers: each loaded input vector feeds four
// multiply-adds. (A plain loop over a row of accumulators ran at a third of that: the compiler kept the
// accumulators in memory.)
// The sums run over the inputs in order (torch's matrix product may group them differently: results
// agree to float rounding).

#pragma once

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace neb_decoders {

constexpr int kBlockPoints = 64;

template <typename T>
struct Layer {
  const T* w;  // (n_out, n_in) row-major
  const T* b;  // (n_out)
  int n_in;
  int n_out;
};

// A vector of kLanes values (GCC/Clang vector extension: AVX registers where the build enables them,
// pairs of narrower ones elsewhere); loads and stores go through memcpy, so no alignment is assumed.
template <typename T>
struct Vec {
  static constexpr int kBytes = 32;
  static constexpr int kLanes = kBytes / sizeof(T);
  typedef T type __attribute__((vector_size(kBytes)));
  static inline type load(const T* p) {
    type v;
    __builtin_memcpy(&v, p, kBytes);
    return v;
  }
  static inline void store(T* p, type v) { __builtin_memcpy(p, &v, kBytes); }
  static inline type splat(T x) { return type{} + x; }
};

// kJ outputs j0 .. j0 + kJ - 1 of one layer for all kBlockPoints points: out[j][.] = bias_j + sum_k w[j][k]
// in[k][.] over the rows of up to two inputs (a, then b; n_in = na + nb), with relu when asked. The
// kJ x kBlockPoints accumulators stay in registers (kJ x 8 / lanes vectors) while the inputs stream by,
// each loaded row serving kJ outputs.
template <typename T, int kJ>
inline void dense_tile(const Layer<T>& L, int j0, const T* a, int na, const T* b, int nb, T* out, bool relu) {
  using V = Vec<T>;
  using vec = typename V::type;
  constexpr int kVecs = kBlockPoints / V::kLanes;
  const T* w[kJ];
  for (int jj = 0; jj < kJ; ++jj) w[jj] = L.w + static_cast<int64_t>(j0 + jj) * L.n_in;
  for (int half = 0; half < kVecs; half += 2) {  // two vectors of points at a time: 2 kJ accumulators
    vec acc[kJ][2];
    for (int jj = 0; jj < kJ; ++jj) acc[jj][0] = acc[jj][1] = V::splat(L.b[j0 + jj]);
    for (int part = 0; part < 2; ++part) {  // the rows of a, then of b
      const T* rows = (part == 0 ? a : b) + half * V::kLanes;
      const int n_rows = part == 0 ? na : nb, k0 = part == 0 ? 0 : na;
      for (int k = 0; k < n_rows; ++k) {
        const vec x0 = V::load(rows + k * kBlockPoints), x1 = V::load(rows + k * kBlockPoints + V::kLanes);
        for (int jj = 0; jj < kJ; ++jj) {
          const vec wk = V::splat(w[jj][k0 + k]);
          acc[jj][0] += wk * x0;
          acc[jj][1] += wk * x1;
        }
      }
    }
    for (int jj = 0; jj < kJ; ++jj) {
      T* dst = out + (j0 + jj) * kBlockPoints + half * V::kLanes;
      for (int h = 0; h < 2; ++h) {
        vec v = acc[jj][h];
        if (relu) v = v > V::splat(T(0)) ? v : V::splat(T(0));
        V::store(dst + h * V::kLanes, v);
      }
    }
  }
}

// All outputs of one layer for the block: tiles of 4 outputs, then single ones.
template <typename T>
inline void dense(const Layer<T>& L, const T* a, int na, const T* b, int nb, T* out, bool relu) {
  int j = 0;
  for (; j + 4 <= L.n_out; j += 4) dense_tile<T, 4>(L, j, a, na, b, nb, out, relu);
  for (; j < L.n_out; ++j) dense_tile<T, 1>(L, j, a, na, b, nb, out, relu);
}

// blob (n, n_blob), feat (n, n_feat) -> sdf (n), rgb (n, 3) (rgb may be null: the geometry MLP only).
// geo1: (n_hidden, n_blob + n_feat), geo2: (1 + n_geo, n_hidden), col1: (n_hidden, n_blob + n_geo),
// col2: (3, n_hidden).
template <typename T>
void forward(const T* __restrict blob, const T* __restrict feat, int n_blob, int n_feat, Layer<T> geo1,
             Layer<T> geo2, Layer<T> col1, Layer<T> col2, T* __restrict sdf, T* __restrict rgb, int64_t n,
             int n_threads) {
  const int n_hidden = geo1.n_out, n_geo_out = geo2.n_out, n_rgb = col2.n_out;
  const int64_t n_blocks = (n + kBlockPoints - 1) / kBlockPoints;
#pragma omp parallel num_threads(n_threads)
  {
    // per thread, feature-major: inputs, hidden layer, geometry output, colour hidden, colour output
    std::vector<T> buf(static_cast<size_t>(kBlockPoints) *
                       (n_blob + n_feat + n_hidden + n_geo_out + n_hidden + n_rgb));
    T* x_blob = buf.data();
    T* x_feat = x_blob + n_blob * kBlockPoints;
    T* hidden = x_feat + n_feat * kBlockPoints;
    T* geo_out = hidden + n_hidden * kBlockPoints;
    T* c_hidden = geo_out + n_geo_out * kBlockPoints;
    T* c_out = c_hidden + n_hidden * kBlockPoints;
#pragma omp for schedule(static)
    for (int64_t blk = 0; blk < n_blocks; ++blk) {
      const int64_t i0 = blk * kBlockPoints;
      const int m = static_cast<int>(std::min<int64_t>(kBlockPoints, n - i0));
      // transpose the block's inputs to feature-major (a short last block is padded with zeros)
      for (int p = 0; p < kBlockPoints; ++p) {
        const bool in = p < m;
        const T* b_row = blob + (i0 + p) * n_blob;
        const T* f_row = feat + (i0 + p) * n_feat;
        for (int k = 0; k < n_blob; ++k) x_blob[k * kBlockPoints + p] = in ? b_row[k] : T(0);
        for (int k = 0; k < n_feat; ++k) x_feat[k * kBlockPoints + p] = in ? f_row[k] : T(0);
      }
      dense(geo1, x_blob, n_blob, x_feat, n_feat, hidden, true);
      dense(geo2, hidden, n_hidden, hidden, 0, geo_out, false);
      for (int p = 0; p < m; ++p) sdf[i0 + p] = geo_out[p];
      if (rgb == nullptr) continue;
      dense(col1, x_blob, n_blob, geo_out + kBlockPoints, n_geo_out - 1, c_hidden, true);
      dense(col2, c_hidden, n_hidden, c_hidden, 0, c_out, false);
      for (int p = 0; p < m; ++p)
        for (int c = 0; c < n_rgb; ++c)
          rgb[(i0 + p) * n_rgb + c] = T(1) / (T(1) + std::exp(-c_out[c * kBlockPoints + p]));
    }
  }
}

}  // namespace neb_decoders
