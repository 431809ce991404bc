// One-blob encoding of world points: the CPU kernels (plain C++ and OpenMP, no torch).
//
// Written by hand because torch evaluates the encoding as a chain of about ten element-wise ops over an
// (N, 3, K) tensor (divide, remainder, subtract, abs, minimum, multiply, square, exp), each a pass over
// memory, and autograd keeps and walks every one of them backwards: on 2 cores that chain cost more than
// the decoders it feeds. Here one pass over the points does the whole code, and one the gradient.
//
// Maths (identical to encode_reference in one_blob.py, which the tests compare against): for each axis
// of a world point x, the phase p = x / period mod 1 (in [0, 1], as torch.remainder), bin j's centre
// c_j = (j + 1/2) / K, and its code exp(-t^2 / 2) with t = K * (the signed distance from c_j to p on the
// unit circle). The output is axis-major: out[n, a*K + j].
//
// Two exponentials per axis instead of K: with j0 the bin holding p and u = p K - j0 - 1/2 in [-1/2, 1/2],
// bin j0 + m (mod K) lies at t = u - m, and consecutive codes differ by a factor that itself shrinks by
// e^-1 per bin:
//   code(m + 1) = code(m) exp(u - m - 1/2)         (m = 0, 1, ...: walking up the circle)
//   code(m - 1) = code(m) exp(-(u - m) - 1/2)      (m = 0, -1, ...: walking down)
// Each bin is reached from the side where it is nearer, so it takes the shorter way round: with K even,
// the bin opposite j0 (m = +-K/2) goes up when u >= 0 and down otherwise. The products carry a relative
// rounding error of at most about K/2 float ulps (the tests bound the difference to the reference).
//
// Gradient: d code / d x = -t K code / period, summed over the K bins of the axis with the output
// gradient. The backward recomputes the codes (cheaper than keeping the (N, 3K) output).
//
// Work split: points in static chunks over the threads; every point's outputs are its own, so results
// are deterministic.

#pragma once

#include <omp.h>

#include <cmath>
#include <cstdint>
#include <limits>

namespace neb_one_blob {

// One axis of one point: visits every bin once as f(bin, t, code), bins in the order of the walk.
template <typename T, typename F>
inline void walk_axis(T x, T period, int K, F&& f) {
  T p = std::fmod(x / period, T(1));  // torch.remainder(x / period, 1): fmod, then into [0, 1)
  if (p < T(0)) p += T(1);            // (may round up to exactly 1: then j0 = K - 1, u = 1/2)
  if (!std::isfinite(p)) {
    const T nan = std::numeric_limits<T>::quiet_NaN();
    for (int j = 0; j < K; ++j) f(j, nan, nan);
    return;
  }
  int j0 = static_cast<int>(std::floor(p * T(K)));
  j0 = j0 < 0 ? 0 : (j0 > K - 1 ? K - 1 : j0);
  const T u = p * T(K) - T(j0) - T(0.5);
  const int n_up = (K % 2 == 1 || u >= T(0)) ? K / 2 + 1 : K / 2;  // m = 0 .. n_up - 1
  const T inv_e = T(0.36787944117144233);                          // e^-1
  const T code0 = std::exp(T(-0.5) * u * u);
  const T up = std::exp(u - T(0.5));                               // code(1) / code(0)
  T code = code0, ratio = up;
  int bin = j0;
  for (int m = 0; m < n_up; ++m) {
    f(bin, u - T(m), code);
    code *= ratio;
    ratio *= inv_e;
    bin = bin + 1 == K ? 0 : bin + 1;
  }
  code = code0;
  ratio = inv_e / up;                                              // code(-1) / code(0) = exp(-u - 1/2)
  bin = j0;
  for (int m = -1; m > n_up - 1 - K; --m) {
    code *= ratio;
    ratio *= inv_e;
    bin = bin == 0 ? K - 1 : bin - 1;
    f(bin, u - T(m), code);
  }
}

// x (n, 3) -> out (n, 3K).
template <typename T>
void forward(const T* __restrict x, T* __restrict out, int64_t n, int K, T period, int n_threads) {
#pragma omp parallel for schedule(static) num_threads(n_threads)
  for (int64_t i = 0; i < n; ++i) {
    for (int a = 0; a < 3; ++a) {
      T* row = out + i * 3 * K + a * K;
      walk_axis<T>(x[3 * i + a], period, K, [row](int bin, T, T code) { row[bin] = code; });
    }
  }
}

// grad_out (n, 3K), x (n, 3) -> grad_x (n, 3), fully written.
template <typename T>
void backward(const T* __restrict grad_out, const T* __restrict x, T* __restrict grad_x, int64_t n, int K,
              T period, int n_threads) {
  const T scale = -T(K) / period;
#pragma omp parallel for schedule(static) num_threads(n_threads)
  for (int64_t i = 0; i < n; ++i) {
    for (int a = 0; a < 3; ++a) {
      const T* g = grad_out + i * 3 * K + a * K;
      T sum = T(0);
      walk_axis<T>(x[3 * i + a], period, K, [g, &sum](int bin, T t, T code) { sum += g[bin] * code * t; });
      grad_x[3 * i + a] = scale * sum;
    }
  }
}

}  // namespace neb_one_blob
