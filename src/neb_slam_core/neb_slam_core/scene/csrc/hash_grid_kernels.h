// Multi-resolution hash encoding of a neural block: the CPU kernels (plain C++ and OpenMP, no torch).
//
// Written by hand because no library we use ships a CPU kernel for this encoding: torch's own ops
// (gather + weighted sum per level) move far more memory than needed, and the libraries that implement
// it (tiny-cuda-nn and the like) are CUDA-only. map_kernels.cpp binds these kernels to torch.
//
// Layout and maths (identical to encode_reference in hash_grid.py, which the tests compare against):
//   x        (N, 3)     local coordinates, clamped to [0, 1] (the gradient is zero outside, as torch.clamp)
//   table    (E, F)     all levels in one flat table; level l owns rows [offset_l, offset_l + rows_l)
//   out      (N, L*F)   level-major: out[n, l*F + f]
//   per level: p = x * R, cell c = min(floor(p), R - 1) (so x == 1 stays in the grid), t = p - c in [0, 1]^3,
//   corners c + {0,1}^3 with trilinear weights,
//   dense index  ix + iy*(R+1) + iz*(R+1)^2                   when (R+1)^3 <= T,
//   hashed index (ix ^ iy*2654435761 ^ iz*805459861) & (T-1)  (uint32 arithmetic) otherwise.
// Corner k uses bit 0 of k for x, bit 1 for y, bit 2 for z.
//
// Speed (tuned on a 2-core CPU; benchmarks/encoding.py measures it, docs/benchmarks.md keeps the results).
// Points go through in blocks of kBlock: for one level, a first pass computes the 8 corner rows and
// weights of every point of the block (branch-free arithmetic the compiler vectorises), a second pass
// does the lookups. Work split across threads:
//   forward       blocks of points (dynamic schedule: a thread the OS preempts does not hold up the rest);
//                 inside a block, level by level, so the block's output rows stay in L1/L2.
//   table grad    each thread owns whole levels, so every table row is written by one thread only: no
//                 atomics, no per-thread copies of the table; the level's slice of the table (at most
//                 T x F values, 256 KB at T = 2^15) stays in cache while all points pass. The output
//                 gradient is first transposed to level-major so each level reads it contiguously. The point
//                 gradient, when also wanted, goes to per-thread (N, 3) buffers summed at the end.
//   point grad    (table grad not wanted, as in tracking) blocks of points, all levels per block.
// All results are deterministic: no atomics, fixed summation orders.
// Kernels are templated on the scalar type (float for speed, double so gradcheck can run on this path) and
// on F, the features per level.

#pragma once

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace neb_hash_grid {

constexpr uint32_t kPrimeY = 2654435761u;
constexpr uint32_t kPrimeZ = 805459861u;
// Points per block: the block's rows, weights and fractions (~20 KB in float32) stay in L1.
constexpr int kBlock = 256;

struct Level {
  int64_t offset;    // first row of this level in the flat table
  int32_t res;       // R
  bool dense;        // dense (R+1)^3 indexing, else hashed
  int32_t stride_y;  // R + 1
  int32_t stride_z;  // (R + 1)^2
  uint32_t mask;     // T - 1
};

// Corner rows (relative to the level's offset), fractions and weights of one block of points at one level.
template <typename T>
struct CellBlock {
  alignas(64) int32_t row[8][kBlock];
  alignas(64) T t[3][kBlock];
  alignas(64) T w[8][kBlock];
};

template <typename T>
inline T clamp01(T v) {
  // NaN stays NaN (both comparisons are false).
  return v < T(0) ? T(0) : (v > T(1) ? T(1) : v);
}

// Fills cb for points x[0..m) (x is (m, 3) row-major).
template <typename T>
inline void locate_block(const Level& lv, const T* __restrict x, int m, CellBlock<T>& cb) {
  const T res = static_cast<T>(lv.res);
  const int32_t last = lv.res - 1;
  alignas(64) int32_t c[3][kBlock];
  for (int d = 0; d < 3; ++d) {
#pragma omp simd
    for (int i = 0; i < m; ++i) {
      const T p = clamp01(x[3 * i + d]) * res;
      // A NaN point reads cell 0 (memory safety); its NaN fraction then makes its output NaN.
      const T pf = p >= T(0) ? std::floor(p) : T(0);
      int32_t ci = static_cast<int32_t>(pf);
      ci = ci > last ? last : ci;
      c[d][i] = ci;
      cb.t[d][i] = p - static_cast<T>(ci);
    }
  }
  if (lv.dense) {
    const int32_t sy = lv.stride_y, sz = lv.stride_z;
#pragma omp simd
    for (int i = 0; i < m; ++i) {
      const int32_t b = c[0][i] + c[1][i] * sy + c[2][i] * sz;
      cb.row[0][i] = b;
      cb.row[1][i] = b + 1;
      cb.row[2][i] = b + sy;
      cb.row[3][i] = b + 1 + sy;
      cb.row[4][i] = b + sz;
      cb.row[5][i] = b + 1 + sz;
      cb.row[6][i] = b + sy + sz;
      cb.row[7][i] = b + 1 + sy + sz;
    }
  } else {
    const uint32_t mask = lv.mask;
#pragma omp simd
    for (int i = 0; i < m; ++i) {
      const uint32_t x0 = static_cast<uint32_t>(c[0][i]), x1 = x0 + 1u;
      const uint32_t y0 = static_cast<uint32_t>(c[1][i]) * kPrimeY, y1 = y0 + kPrimeY;
      const uint32_t z0 = static_cast<uint32_t>(c[2][i]) * kPrimeZ, z1 = z0 + kPrimeZ;
      cb.row[0][i] = static_cast<int32_t>((x0 ^ y0 ^ z0) & mask);
      cb.row[1][i] = static_cast<int32_t>((x1 ^ y0 ^ z0) & mask);
      cb.row[2][i] = static_cast<int32_t>((x0 ^ y1 ^ z0) & mask);
      cb.row[3][i] = static_cast<int32_t>((x1 ^ y1 ^ z0) & mask);
      cb.row[4][i] = static_cast<int32_t>((x0 ^ y0 ^ z1) & mask);
      cb.row[5][i] = static_cast<int32_t>((x1 ^ y0 ^ z1) & mask);
      cb.row[6][i] = static_cast<int32_t>((x0 ^ y1 ^ z1) & mask);
      cb.row[7][i] = static_cast<int32_t>((x1 ^ y1 ^ z1) & mask);
    }
  }
#pragma omp simd
  for (int i = 0; i < m; ++i) {
    const T tx = cb.t[0][i], ty = cb.t[1][i], tz = cb.t[2][i];
    const T ux = T(1) - tx, uy = T(1) - ty, uz = T(1) - tz;
    const T a00 = uy * uz, a10 = ty * uz, a01 = uy * tz, a11 = ty * tz;
    cb.w[0][i] = ux * a00;
    cb.w[1][i] = tx * a00;
    cb.w[2][i] = ux * a10;
    cb.w[3][i] = tx * a10;
    cb.w[4][i] = ux * a01;
    cb.w[5][i] = tx * a01;
    cb.w[6][i] = ux * a11;
    cb.w[7][i] = tx * a11;
  }
}

// a[f] = the trilinear interpolation of point i's 8 corners (rows and weights in cb) in the level's rows tab.
template <typename T, int F>
__attribute__((always_inline)) inline void interpolate(const CellBlock<T>& cb, const T* __restrict tab, int i,
                                                       T (&a)[F]) {
  for (int f = 0; f < F; ++f) a[f] = 0;
  for (int k = 0; k < 8; ++k) {
    const T* r = tab + static_cast<int64_t>(cb.row[k][i]) * F;
    const T wk = cb.w[k][i];
    for (int f = 0; f < F; ++f) a[f] += wk * r[f];
  }
}

// s[k][i] = sum_f g[f][i] * table[row k of point i, f]: the output gradient projected on each corner.
template <typename T, int F>
inline void corner_dot(const CellBlock<T>& cb, const T* __restrict tab, const T (*g)[kBlock], int m,
                       T (*s)[kBlock]) {
  for (int k = 0; k < 8; ++k) {
#pragma omp simd
    for (int i = 0; i < m; ++i) {
      const T* r = tab + static_cast<int64_t>(cb.row[k][i]) * F;
      T acc = 0;
      for (int f = 0; f < F; ++f) acc += g[f][i] * r[f];
      s[k][i] = acc;
    }
  }
}

// d out / d x for one level, added to gx[d][i]: d w_k / d t_x = (+1 or -1) * wy * wz, d t / d x = R
// (0 where the clamp to [0, 1] cuts the gradient).
template <typename T>
inline void add_point_grad(const CellBlock<T>& cb, const T (*s)[kBlock], const T* __restrict x, T res, int m,
                           T (*gx)[kBlock]) {
#pragma omp simd
  for (int i = 0; i < m; ++i) {
    const T tx = cb.t[0][i], ty = cb.t[1][i], tz = cb.t[2][i];
    const T ux = T(1) - tx, uy = T(1) - ty, uz = T(1) - tz;
    // differences of the corner values along each axis, then interpolated over the other two axes
    const T dx00 = s[1][i] - s[0][i], dx10 = s[3][i] - s[2][i], dx01 = s[5][i] - s[4][i], dx11 = s[7][i] - s[6][i];
    const T dy00 = s[2][i] - s[0][i], dy10 = s[3][i] - s[1][i], dy01 = s[6][i] - s[4][i], dy11 = s[7][i] - s[5][i];
    const T dz00 = s[4][i] - s[0][i], dz10 = s[5][i] - s[1][i], dz01 = s[6][i] - s[2][i], dz11 = s[7][i] - s[3][i];
    const T gxv = (dx00 * uy + dx10 * ty) * uz + (dx01 * uy + dx11 * ty) * tz;
    const T gyv = (dy00 * ux + dy10 * tx) * uz + (dy01 * ux + dy11 * tx) * tz;
    const T gzv = (dz00 * ux + dz10 * tx) * uy + (dz01 * ux + dz11 * tx) * ty;
    const T vx = x[3 * i], vy = x[3 * i + 1], vz = x[3 * i + 2];
    // bitwise & (no short circuit) keeps the loop branch-free, so it vectorises
    gx[0][i] += gxv * (res * static_cast<T>((vx >= T(0)) & (vx <= T(1))));
    gx[1][i] += gyv * (res * static_cast<T>((vy >= T(0)) & (vy <= T(1))));
    gx[2][i] += gzv * (res * static_cast<T>((vz >= T(0)) & (vz <= T(1))));
  }
}

template <typename T, int F>
void forward(const T* x, const T* table, T* out, int64_t n, const std::vector<Level>& levels, int n_threads) {
  const int L = static_cast<int>(levels.size());
  const int64_t n_blocks = (n + kBlock - 1) / kBlock;
#pragma omp parallel num_threads(n_threads)
  {
    CellBlock<T> cb;
    alignas(64) T acc[F][kBlock];
#pragma omp for schedule(dynamic, 4)
    for (int64_t blk = 0; blk < n_blocks; ++blk) {
      const int64_t i0 = blk * kBlock;
      const int m = static_cast<int>(std::min<int64_t>(kBlock, n - i0));
      const T* xb = x + 3 * i0;
      for (int l = 0; l < L; ++l) {
        const Level& lv = levels[l];
        locate_block(lv, xb, m, cb);
        const T* __restrict tab = table + lv.offset * F;
#pragma omp simd
        for (int i = 0; i < m; ++i) {
          T a[F];
          interpolate<T, F>(cb, tab, i, a);
          for (int f = 0; f < F; ++f) acc[f][i] = a[f];
        }
        T* ob = out + i0 * (L * F) + l * F;
        for (int i = 0; i < m; ++i)
          for (int f = 0; f < F; ++f) ob[static_cast<int64_t>(i) * (L * F) + f] = acc[f][i];
      }
    }
  }
}

// a[f] and its derivatives da[d][f] along the three local axes (in grid cells of the level: the caller
// multiplies by R): differences of the corner values along each axis, interpolated over the other two.
template <typename T, int F>
__attribute__((always_inline)) inline void interpolate_with_slopes(const CellBlock<T>& cb, const T* __restrict tab,
                                                                   int i, T (&a)[F], T (&da)[3][F]) {
  const T* r[8];
  for (int k = 0; k < 8; ++k) r[k] = tab + static_cast<int64_t>(cb.row[k][i]) * F;
  const T tx = cb.t[0][i], ty = cb.t[1][i], tz = cb.t[2][i];
  const T ux = T(1) - tx, uy = T(1) - ty, uz = T(1) - tz;
  for (int f = 0; f < F; ++f) {
    T v = 0;
    for (int k = 0; k < 8; ++k) v += cb.w[k][i] * r[k][f];
    a[f] = v;
    da[0][f] = ((r[1][f] - r[0][f]) * uy + (r[3][f] - r[2][f]) * ty) * uz +
               ((r[5][f] - r[4][f]) * uy + (r[7][f] - r[6][f]) * ty) * tz;
    da[1][f] = ((r[2][f] - r[0][f]) * ux + (r[3][f] - r[1][f]) * tx) * uz +
               ((r[6][f] - r[4][f]) * ux + (r[7][f] - r[5][f]) * tx) * tz;
    da[2][f] = ((r[4][f] - r[0][f]) * ux + (r[5][f] - r[1][f]) * tx) * uy +
               ((r[6][f] - r[2][f]) * ux + (r[7][f] - r[3][f]) * tx) * ty;
  }
}

// Features of world points blended over several blocks (BlockMap.grid_features with more than one block
// in view; forward only, so it serves tracking, rendering without gradients and meshing, and the torch
// path in block_map.py runs when gradients are needed). Block b is the cube of edge `edge` centred at
// centres[b] with its own table tables[b]; all tables share the level layout. A point takes
//   sum_b w_b enc_b(x) / sum_b w_b   over the blocks that contain it (|x - c_b|_inf <= edge / 2),
//   w_b = clamp((edge / 2 - |x - c_b|_inf) / blend, 1e-6, 1)   (1 when blend <= 0),
// summed in the order of the blocks, the same arithmetic as that torch path; a point in no block gets
// zeros and valid 0. One pass per chunk of points: the chunk's points inside each block are compacted
// and encoded with that block's table, and their weighted features accumulate in a per-thread buffer,
// where the torch path needs a gather, an encode call, a scatter and a blend per block.
//
// With kJacobian, jac (n, 3, L*F) also receives the derivatives of those features w.r.t. the world point
// (tracking's Gauss-Newton Jacobians; the spatial gradient of one point is otherwise four encodings by
// forward differences). The same 8 rows per level give the value and its three slopes; by the quotient rule
//   d out / d x = (sum_b w_b d enc_b / dx + enc_b d w_b / dx - out sum_b d w_b / dx) / sum_b w_b,
//   d enc_b / d x = R_l / edge x the level's slope (0 along an axis where the local coordinate leaves
//   [0, 1], as the clamp of the torch path), d w_b / d x = -sign(x - c_b) / blend on the axis of the
//   largest |x - c_b| where w_b is strictly inside its clamp, else 0: autograd's gradient of that path.
template <typename T, int F, bool kJacobian>
void forward_blocks(const T* xw, const T* centres, const std::vector<const T*>& tables, T edge, T blend, T* out,
                    uint8_t* valid, T* jac, int64_t n, const std::vector<Level>& levels, int n_threads) {
  const int L = static_cast<int>(levels.size());
  const int D = L * F;
  const int n_tables = static_cast<int>(tables.size());
  const T half = T(0.5) * edge;
  const int64_t n_blocks = (n + kBlock - 1) / kBlock;
#pragma omp parallel num_threads(n_threads)
  {
    CellBlock<T> cb;
    alignas(64) T xl[3 * kBlock];
    alignas(64) T wt[kBlock];
    alignas(64) T wsum[kBlock];
    alignas(64) T dwt[3][kBlock];     // kJacobian: d w_b / d x of the compacted points
    alignas(64) T dwsum[3][kBlock];   // kJacobian: sum_b d w_b / d x
    alignas(64) T inside01[3][kBlock];  // kJacobian: 1 where the local coordinate lies in [0, 1], else 0
    int32_t idx[kBlock];
    std::vector<T> acc(static_cast<size_t>(kBlock) * D);
    std::vector<T> jacc(kJacobian ? static_cast<size_t>(kBlock) * 3 * D : 0);
#pragma omp for schedule(dynamic, 4)
    for (int64_t blk = 0; blk < n_blocks; ++blk) {
      const int64_t i0 = blk * kBlock;
      const int m = static_cast<int>(std::min<int64_t>(kBlock, n - i0));
      const T* xb = xw + 3 * i0;
      std::fill(acc.begin(), acc.begin() + static_cast<size_t>(m) * D, T(0));
      std::fill(wsum, wsum + m, T(0));
      if constexpr (kJacobian) {
        std::fill(jacc.begin(), jacc.begin() + static_cast<size_t>(m) * 3 * D, T(0));
        for (int d = 0; d < 3; ++d) std::fill(dwsum[d], dwsum[d] + m, T(0));
      }
      for (int b = 0; b < n_tables; ++b) {
        const T* c = centres + 3 * b;
        int k = 0;
        for (int i = 0; i < m; ++i) {
          const T dx = xb[3 * i] - c[0], dy = xb[3 * i + 1] - c[1], dz = xb[3 * i + 2] - c[2];
          const T ax = std::abs(dx), ay = std::abs(dy), az = std::abs(dz);
          const T to_face = half - std::max(ax, std::max(ay, az));
          if (!(to_face >= T(0))) continue;  // outside (or NaN)
          idx[k] = i;
          xl[3 * k] = dx / edge + T(0.5);
          xl[3 * k + 1] = dy / edge + T(0.5);
          xl[3 * k + 2] = dz / edge + T(0.5);
          wt[k] = blend > T(0) ? std::min(std::max(to_face / blend, T(1e-6)), T(1)) : T(1);
          if constexpr (kJacobian) {
            const T ratio = blend > T(0) ? to_face / blend : T(1);
            const bool sloped = ratio > T(1e-6) && ratio < T(1);
            // the axis of the largest offset, whose face is the nearest (ties, a set of measure zero, go
            // to the first axis; torch's amax would split the gradient between them)
            const int axis = (ax >= ay && ax >= az) ? 0 : (ay >= az ? 1 : 2);
            const T delta[3] = {dx, dy, dz};
            for (int d = 0; d < 3; ++d) {
              const T sign = delta[d] > T(0) ? T(1) : (delta[d] < T(0) ? T(-1) : T(0));
              dwt[d][k] = (sloped && d == axis) ? -sign / blend : T(0);
              const T v = xl[3 * k + d];
              inside01[d][k] = (v >= T(0) && v <= T(1)) ? T(1) : T(0);
            }
          }
          ++k;
        }
        if (k == 0) continue;
        for (int l = 0; l < L; ++l) {
          const Level& lv = levels[l];
          locate_block(lv, xl, k, cb);
          const T* __restrict tab = tables[b] + lv.offset * F;
          const T scale = static_cast<T>(lv.res) / edge;  // grid cells per metre
          for (int i = 0; i < k; ++i) {
            T a[F];
            T* dst = acc.data() + static_cast<int64_t>(idx[i]) * D + l * F;
            if constexpr (kJacobian) {
              T da[3][F];
              interpolate_with_slopes<T, F>(cb, tab, i, a, da);
              T* jd = jacc.data() + static_cast<int64_t>(idx[i]) * 3 * D + l * F;
              for (int d = 0; d < 3; ++d) {
                const T s = scale * inside01[d][i] * wt[i];
                for (int f = 0; f < F; ++f) jd[d * D + f] += s * da[d][f] + dwt[d][i] * a[f];
              }
            } else {
              interpolate<T, F>(cb, tab, i, a);
            }
            for (int f = 0; f < F; ++f) dst[f] += a[f] * wt[i];
          }
        }
        for (int i = 0; i < k; ++i) {
          wsum[idx[i]] += wt[i];
          if constexpr (kJacobian)
            for (int d = 0; d < 3; ++d) dwsum[d][idx[i]] += dwt[d][i];
        }
      }
      for (int i = 0; i < m; ++i) {
        const T denom = std::max(wsum[i], T(1e-12));
        const T* src = acc.data() + static_cast<int64_t>(i) * D;
        T* dst = out + (i0 + i) * D;
        for (int j = 0; j < D; ++j) dst[j] = src[j] / denom;
        valid[i0 + i] = wsum[i] > T(0) ? 1 : 0;
        if constexpr (kJacobian) {
          const T* jsrc = jacc.data() + static_cast<int64_t>(i) * 3 * D;
          T* jdst = jac + (i0 + i) * 3 * D;
          for (int d = 0; d < 3; ++d)
            for (int j = 0; j < D; ++j) jdst[d * D + j] = (jsrc[d * D + j] - dst[j] * dwsum[d][i]) / denom;
        }
      }
    }
  }
}

// Table gradient (into grad_table, zero-initialised), and the point gradient too when grad_x is not null.
template <typename T, int F>
void backward_table(const T* grad_out, const T* x, const T* table, T* grad_table, T* grad_x, int64_t n,
                    const std::vector<Level>& levels, int n_threads) {
  const int L = static_cast<int>(levels.size());
  const int threads = std::max(1, std::min(n_threads, L));
  // Per-thread point-gradient buffers (threads x N x 3), summed below; empty when not wanted.
  std::vector<T> gx_private(grad_x ? static_cast<size_t>(threads) * n * 3 : 0, T(0));
  // grad_out transposed to level-major (L, N, F) first, so that a thread that owns a level reads that
  // level's gradients contiguously instead of F values out of every (L*F)-value row.
  std::vector<T> g_levels(static_cast<size_t>(L) * n * F);
  const int64_t n_blocks = (n + kBlock - 1) / kBlock;
  // One parallel region (transpose, levels, sum of the point gradients) to keep fork/join costs down.
#pragma omp parallel num_threads(threads)
  {
#pragma omp for schedule(static)
    for (int64_t blk = 0; blk < n_blocks; ++blk) {
      const int64_t i0 = blk * kBlock, i1 = std::min<int64_t>(n, i0 + kBlock);
      for (int l = 0; l < L; ++l) {
        T* dst = g_levels.data() + (static_cast<int64_t>(l) * n) * F;
        for (int64_t i = i0; i < i1; ++i)
          for (int f = 0; f < F; ++f) dst[i * F + f] = grad_out[i * (L * F) + l * F + f];
      }
    }  // implicit barrier: g_levels complete
    const int tid = omp_get_thread_num();
    const int nt = omp_get_num_threads();
    T* gx_mine = grad_x ? gx_private.data() + static_cast<size_t>(tid) * n * 3 : nullptr;
    CellBlock<T> cb;
    alignas(64) T g[F][kBlock];
    alignas(64) T s[8][kBlock];
    alignas(64) T gx[3][kBlock];
    // Contiguous runs of levels per thread (every level costs the same per point). A fixed split rather than
    // dynamic scheduling keeps the summation order, hence the point gradient, bit-for-bit reproducible.
    const int l0 = L * tid / nt, l1 = L * (tid + 1) / nt;
    for (int l = l0; l < l1; ++l) {
      const Level& lv = levels[l];
      const T* __restrict tab = table + lv.offset * F;
      T* __restrict gtab = grad_table + lv.offset * F;
      for (int64_t i0 = 0; i0 < n; i0 += kBlock) {
        const int m = static_cast<int>(std::min<int64_t>(kBlock, n - i0));
        const T* xb = x + 3 * i0;
        locate_block(lv, xb, m, cb);
        const T* gb = g_levels.data() + (static_cast<int64_t>(l) * n + i0) * F;
        for (int i = 0; i < m; ++i)
          for (int f = 0; f < F; ++f) g[f][i] = gb[i * F + f];
        // scatter-add: scalar on purpose (two corners of one block can share a row)
        for (int i = 0; i < m; ++i) {
          for (int k = 0; k < 8; ++k) {
            T* r = gtab + static_cast<int64_t>(cb.row[k][i]) * F;
            const T wk = cb.w[k][i];
            for (int f = 0; f < F; ++f) r[f] += wk * g[f][i];
          }
        }
        if (gx_mine) {
          corner_dot<T, F>(cb, tab, g, m, s);
          for (int d = 0; d < 3; ++d)
            for (int i = 0; i < m; ++i) gx[d][i] = 0;
          add_point_grad(cb, s, xb, static_cast<T>(lv.res), m, gx);
          T* gxo = gx_mine + 3 * i0;
          for (int i = 0; i < m; ++i)
            for (int d = 0; d < 3; ++d) gxo[3 * i + d] += gx[d][i];
        }
      }
    }
    if (grad_x) {
#pragma omp barrier
      const int64_t total = 3 * n;
#pragma omp for schedule(static)
      for (int64_t j = 0; j < total; ++j) {
        T acc = 0;
        for (int t = 0; t < nt; ++t) acc += gx_private[static_cast<size_t>(t) * total + j];
        grad_x[j] = acc;
      }
    }
  }
}

// Point gradient only (tracking: the table is fixed): blocks of points, all levels per block.
template <typename T, int F>
void backward_points(const T* grad_out, const T* x, const T* table, T* grad_x, int64_t n,
                     const std::vector<Level>& levels, int n_threads) {
  const int L = static_cast<int>(levels.size());
  const int64_t n_blocks = (n + kBlock - 1) / kBlock;
#pragma omp parallel num_threads(n_threads)
  {
    CellBlock<T> cb;
    alignas(64) T g[F][kBlock];
    alignas(64) T s[8][kBlock];
    alignas(64) T gx[3][kBlock];
#pragma omp for schedule(dynamic, 4)
    for (int64_t blk = 0; blk < n_blocks; ++blk) {
      const int64_t i0 = blk * kBlock;
      const int m = static_cast<int>(std::min<int64_t>(kBlock, n - i0));
      const T* xb = x + 3 * i0;
      for (int d = 0; d < 3; ++d)
        for (int i = 0; i < m; ++i) gx[d][i] = 0;
      for (int l = 0; l < L; ++l) {
        const Level& lv = levels[l];
        locate_block(lv, xb, m, cb);
        const T* gb = grad_out + i0 * (L * F) + l * F;
        for (int i = 0; i < m; ++i)
          for (int f = 0; f < F; ++f) g[f][i] = gb[static_cast<int64_t>(i) * (L * F) + f];
        corner_dot<T, F>(cb, table + lv.offset * F, g, m, s);
        add_point_grad(cb, s, xb, static_cast<T>(lv.res), m, gx);
      }
      T* gxo = grad_x + 3 * i0;
      for (int i = 0; i < m; ++i)
        for (int d = 0; d < 3; ++d) gxo[3 * i + d] = gx[d][i];
    }
  }
}

}  // namespace neb_hash_grid
