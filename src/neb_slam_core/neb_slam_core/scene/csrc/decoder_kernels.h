// The two shared decoders, forward only (no gradient), optionally with directional derivatives along three
// input tangents: the CPU kernels (plain C++ and OpenMP, no torch).
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
//
// Tangents (forward_tangents; tracking's spatial gradients, tangent t = the derivative of the encodings
// along world axis t): the same layers without biases carry a tangent, a ReLU passes it where its primal
// input is positive, the sigmoid scales it by rgb (1 - rgb):
//   dh = [W1 dx] (h > 0),  do = W2 dh,  dk = [W3 [dblob | do[1:]]] (k > 0),  drgb = rgb (1 - rgb) W4 dk.
// The one-blob code is axis-major (3 blocks of K = n_blob / 3 codes, block a a function of axis a alone),
// so tangent t moves only block t of the blob: it is passed as those K slopes, and only their K weight
// columns enter the two first layers (a third of the blob's multiply-adds).

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
// in[k][.] over the rows of up to two inputs (a at weight columns 0 .. na - 1, b at columns b_col ..
// b_col + nb - 1; usually b_col = na and n_in = na + nb), with relu when asked. The
// kJ x kBlockPoints accumulators stay in registers (kJ x 8 / lanes vectors) while the inputs stream by,
// each loaded row serving kJ outputs.
template <typename T, int kJ>
inline void dense_tile(const Layer<T>& L, int j0, const T* a, int na, const T* b, int nb, int b_col, T* out,
                       bool relu) {
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
      const int n_rows = part == 0 ? na : nb, k0 = part == 0 ? 0 : b_col;
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
inline void dense(const Layer<T>& L, const T* a, int na, const T* b, int nb, T* out, bool relu, int b_col = -1) {
  if (b_col < 0) b_col = na;
  int j = 0;
  for (; j + 4 <= L.n_out; j += 4) dense_tile<T, 4>(L, j, a, na, b, nb, b_col, out, relu);
  for (; j < L.n_out; ++j) dense_tile<T, 1>(L, j, a, na, b, nb, b_col, out, relu);
}

// Rows [i0, i0 + m) of a point-major array (row p at src + p * stride, dims values) to feature-major dst
// (dims rows of kBlockPoints values); a short last block is padded with zeros.
template <typename T>
inline void transpose_block(const T* src, int64_t stride, int dims, int m, T* dst) {
  for (int p = 0; p < kBlockPoints; ++p) {
    const T* row = src + p * stride;
    for (int k = 0; k < dims; ++k) dst[k * kBlockPoints + p] = p < m ? row[k] : T(0);
  }
}

// One block's feature-major buffers for one pass through both MLPs, carved out of a thread's buffer.
template <typename T>
struct Pass {
  T *blob, *feat, *hidden, *geo, *c_hidden, *c_out;
  static size_t size(int n_blob, int n_feat, int n_hidden, int n_geo_out, int n_rgb) {
    return static_cast<size_t>(kBlockPoints) * (n_blob + n_feat + 2 * n_hidden + n_geo_out + n_rgb);
  }
  Pass(T* base, int n_blob, int n_feat, int n_hidden, int n_geo_out) {
    blob = base;
    feat = blob + n_blob * kBlockPoints;
    hidden = feat + n_feat * kBlockPoints;
    geo = hidden + n_hidden * kBlockPoints;
    c_hidden = geo + n_geo_out * kBlockPoints;
    c_out = c_hidden + n_hidden * kBlockPoints;
  }
};

// The primal pass of points [i0, i0 + m): their inputs into pass.blob and pass.feat, the geometry MLP,
// then (when colour) the colour MLP up to its pre-sigmoid outputs.
template <typename T>
inline void primal_block(const Layer<T>& geo1, const Layer<T>& geo2, const Layer<T>& col1, const Layer<T>& col2,
                         const T* blob, const T* feat, int n_blob, int n_feat, int64_t i0, int m, Pass<T>& pass,
                         bool colour) {
  transpose_block(blob + i0 * n_blob, n_blob, n_blob, m, pass.blob);
  transpose_block(feat + i0 * n_feat, n_feat, n_feat, m, pass.feat);
  dense(geo1, pass.blob, n_blob, pass.feat, n_feat, pass.hidden, true);
  dense(geo2, pass.hidden, geo1.n_out, pass.hidden, 0, pass.geo, false);
  if (!colour) return;
  dense(col1, pass.blob, n_blob, pass.geo + kBlockPoints, geo2.n_out - 1, pass.c_hidden, true);
  dense(col2, pass.c_hidden, col1.n_out, pass.c_hidden, 0, pass.c_out, false);
}

template <typename T>
inline T sigmoid(T v) {
  return T(1) / (T(1) + std::exp(-v));
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
    std::vector<T> buf(Pass<T>::size(n_blob, n_feat, n_hidden, n_geo_out, n_rgb));  // per thread
    Pass<T> pass(buf.data(), n_blob, n_feat, n_hidden, n_geo_out);
#pragma omp for schedule(static)
    for (int64_t blk = 0; blk < n_blocks; ++blk) {
      const int64_t i0 = blk * kBlockPoints;
      const int m = static_cast<int>(std::min<int64_t>(kBlockPoints, n - i0));
      primal_block(geo1, geo2, col1, col2, blob, feat, n_blob, n_feat, i0, m, pass, rgb != nullptr);
      for (int p = 0; p < m; ++p) sdf[i0 + p] = pass.geo[p];
      if (rgb == nullptr) continue;
      for (int p = 0; p < m; ++p)
        for (int c = 0; c < n_rgb; ++c) rgb[(i0 + p) * n_rgb + c] = sigmoid(pass.c_out[c * kBlockPoints + p]);
    }
  }
}

// forward plus the derivatives along 3 tangents per point: blob_slopes (n, 3, n_blob / 3) (tangent t of
// blob code t * K + j, the other blocks' tangents being 0), d_feat (n, 3, n_feat) -> d_sdf (n, 3),
// d_rgb (n, 3, 3): entry [p, t] (resp. [p, t, c]) is the derivative along tangent t.
template <typename T>
void forward_tangents(const T* __restrict blob, const T* __restrict feat, const T* __restrict blob_slopes,
                      const T* __restrict d_feat, int n_blob, int n_feat, Layer<T> geo1, Layer<T> geo2,
                      Layer<T> col1, Layer<T> col2, T* __restrict sdf, T* __restrict rgb, T* __restrict d_sdf,
                      T* __restrict d_rgb, int64_t n, int n_threads) {
  constexpr int kTangents = 3;
  const int K = n_blob / kTangents;
  const int n_hidden = geo1.n_out, n_geo_out = geo2.n_out, n_rgb = col2.n_out;
  const int64_t n_blocks = (n + kBlockPoints - 1) / kBlockPoints;
  // the tangents' layers: the same weights, zero biases
  const std::vector<T> zeros(static_cast<size_t>(std::max(n_hidden, std::max(n_geo_out, n_rgb))), T(0));
  const Layer<T> tgeo2{geo2.w, zeros.data(), geo2.n_in, geo2.n_out}, tcol2{col2.w, zeros.data(), col2.n_in, col2.n_out};
#pragma omp parallel num_threads(n_threads)
  {
    // per thread: the primal's buffers, then one tangent's (its blob rows: K of them)
    const size_t one = Pass<T>::size(n_blob, n_feat, n_hidden, n_geo_out, n_rgb);
    std::vector<T> buf(2 * one);
    Pass<T> pass(buf.data(), n_blob, n_feat, n_hidden, n_geo_out);
    Pass<T> tan(buf.data() + one, K, n_feat, n_hidden, n_geo_out);
#pragma omp for schedule(static)
    for (int64_t blk = 0; blk < n_blocks; ++blk) {
      const int64_t i0 = blk * kBlockPoints;
      const int m = static_cast<int>(std::min<int64_t>(kBlockPoints, n - i0));
      primal_block(geo1, geo2, col1, col2, blob, feat, n_blob, n_feat, i0, m, pass, true);
      for (int p = 0; p < m; ++p) {
        sdf[i0 + p] = pass.geo[p];
        for (int c = 0; c < n_rgb; ++c) {
          const T s = sigmoid(pass.c_out[c * kBlockPoints + p]);
          rgb[(i0 + p) * n_rgb + c] = s;
          pass.c_out[c * kBlockPoints + p] = s * (T(1) - s);  // from here on: the sigmoid's slope
        }
      }
      for (int t = 0; t < kTangents; ++t) {
        transpose_block(blob_slopes + (i0 * kTangents + t) * K, kTangents * K, K, m, tan.blob);
        transpose_block(d_feat + (i0 * kTangents + t) * n_feat, kTangents * n_feat, n_feat, m, tan.feat);
        // block t's weight columns of the first layers: the layer seen from column t K, the other input's
        // columns shifted back by as much
        const Layer<T> geo1_t{geo1.w + t * K, zeros.data(), geo1.n_in, geo1.n_out};
        const Layer<T> col1_t{col1.w + t * K, zeros.data(), col1.n_in, col1.n_out};
        dense(geo1_t, tan.blob, K, tan.feat, n_feat, tan.hidden, false, n_blob - t * K);
        for (int j = 0; j < n_hidden * kBlockPoints; ++j) tan.hidden[j] = pass.hidden[j] > T(0) ? tan.hidden[j] : T(0);
        dense(tgeo2, tan.hidden, n_hidden, tan.hidden, 0, tan.geo, false);
        dense(col1_t, tan.blob, K, tan.geo + kBlockPoints, n_geo_out - 1, tan.c_hidden, false, n_blob - t * K);
        for (int j = 0; j < n_hidden * kBlockPoints; ++j)
          tan.c_hidden[j] = pass.c_hidden[j] > T(0) ? tan.c_hidden[j] : T(0);
        dense(tcol2, tan.c_hidden, n_hidden, tan.c_hidden, 0, tan.c_out, false);
        for (int p = 0; p < m; ++p) {
          d_sdf[(i0 + p) * kTangents + t] = tan.geo[p];
          for (int c = 0; c < n_rgb; ++c)
            d_rgb[((i0 + p) * kTangents + t) * n_rgb + c] = pass.c_out[c * kBlockPoints + p] * tan.c_out[c * kBlockPoints + p];
        }
      }
    }
  }
}

}  // namespace neb_decoders
