// The CPU kernels of the neural block map, bound to Python: the multi-resolution hash encoding
// (hash_grid_kernels.h), the one-blob encoding (one_blob_kernels.h) and the decoders' forward pass
// (decoder_kernels.h); read those files' headers for the maths, the layout and the work split.
// Built on first use by neb_slam_core/scene/_ext.py (torch.utils.cpp_extension.load).
//
// The binding takes raw data pointers (Python ints from Tensor.data_ptr()) and sizes, and includes
// pybind11 only, not torch/extension.h: that keeps the first-use compile at seconds instead of about a
// minute. hash_grid.py, one_blob.py and decoders.py check devices, dtypes, shapes and contiguity and allocate the
// outputs before calling in. The GIL is released while a kernel runs.

#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <cstdint>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <vector>

#include "hash_grid_kernels.h"
#include "decoder_kernels.h"
#include "one_blob_kernels.h"

namespace py = pybind11;
using neb_hash_grid::Level;

namespace {

template <typename P>
P* as_ptr(uintptr_t address) {
  return reinterpret_cast<P*>(address);
}

// Level table from the HashGrid buffers: offsets (L + 1) int64, resolutions (L) int64, dense (L) bool.
std::vector<Level> make_levels(int64_t n_levels, uintptr_t offsets, uintptr_t resolutions, uintptr_t dense,
                               int64_t table_size) {
  if (n_levels < 1) throw std::invalid_argument("hash_grid: need at least one level");
  if (table_size < 1 || (table_size & (table_size - 1)) != 0 || table_size > (int64_t(1) << 31))
    throw std::invalid_argument("hash_grid: table_size must be a power of two <= 2^31, got " +
                                std::to_string(table_size));
  const int64_t* o = as_ptr<const int64_t>(offsets);
  const int64_t* r = as_ptr<const int64_t>(resolutions);
  const bool* d = as_ptr<const bool>(dense);
  std::vector<Level> levels(n_levels);
  for (int64_t l = 0; l < n_levels; ++l) {
    if (r[l] < 1 || r[l] >= (int64_t(1) << 30))
      throw std::invalid_argument("hash_grid: level " + std::to_string(l) + " resolution out of range: " +
                                  std::to_string(r[l]));
    Level& lv = levels[l];
    lv.offset = o[l];
    lv.res = static_cast<int32_t>(r[l]);
    lv.dense = d[l];
    lv.mask = static_cast<uint32_t>(table_size - 1);
    int64_t rows = table_size;
    lv.stride_y = lv.stride_z = 0;
    if (lv.dense) {
      const int64_t side = r[l] + 1;
      rows = side * side * side;
      if (rows > table_size)
        throw std::invalid_argument("hash_grid: dense level " + std::to_string(l) + " needs more rows than T");
      lv.stride_y = static_cast<int32_t>(side);
      lv.stride_z = static_cast<int32_t>(side * side);
    }
    if (o[l + 1] - o[l] != rows)
      throw std::invalid_argument("hash_grid: level " + std::to_string(l) + " owns " +
                                  std::to_string(o[l + 1] - o[l]) + " rows but its indexing needs " +
                                  std::to_string(rows));
  }
  return levels;
}

// Runs STATEMENT with T (float for dtype code 0, double for 1) and kF bound to the runtime dtype code and
// feature count. Only F = 2 (the paper's) is compiled: every extra F adds seconds to the first-use build;
// hash_grid.py sends other F to the plain-torch reference.
#define NEB_DISPATCH_F(F_VALUE, STATEMENT)                                                              \
  switch (F_VALUE) {                                                                                    \
    case 2: { constexpr int kF = 2; STATEMENT; break; }                                                 \
    default:                                                                                            \
      throw std::invalid_argument("hash_grid: the fast path is built for 2 features per level, got " +  \
                                  std::to_string(F_VALUE));                                             \
  }
#define NEB_DISPATCH(DTYPE, F_VALUE, STATEMENT)                                                         \
  if ((DTYPE) == 0) {                                                                                   \
    using T = float;                                                                                    \
    NEB_DISPATCH_F(F_VALUE, STATEMENT)                                                                  \
  } else if ((DTYPE) == 1) {                                                                            \
    using T = double;                                                                                   \
    NEB_DISPATCH_F(F_VALUE, STATEMENT)                                                                  \
  } else {                                                                                              \
    throw std::invalid_argument("hash_grid: dtype code must be 0 (float32) or 1 (float64)");           \
  }

// x (n, 3), table (E, F), out (n, L*F): all contiguous, same dtype, allocated by the caller.
void forward(int dtype, int64_t F, uintptr_t x, uintptr_t table, uintptr_t out, int64_t n, int64_t n_levels,
             uintptr_t offsets, uintptr_t resolutions, uintptr_t dense, int64_t table_size, int n_threads) {
  const auto levels = make_levels(n_levels, offsets, resolutions, dense, table_size);
  if (n <= 0) return;
  NEB_DISPATCH(dtype, F,
               (neb_hash_grid::forward<T, kF>(as_ptr<const T>(x), as_ptr<const T>(table), as_ptr<T>(out), n,
                                              levels, n_threads)));
}

// grad_out (n, L*F). grad_x (n, 3) or 0 when not wanted (fully written); grad_table (E, F) or 0 when not
// wanted (must be zero-filled by the caller: the kernel adds into it).
void backward(int dtype, int64_t F, uintptr_t grad_out, uintptr_t x, uintptr_t table, uintptr_t grad_x,
              uintptr_t grad_table, int64_t n, int64_t n_levels, uintptr_t offsets, uintptr_t resolutions,
              uintptr_t dense, int64_t table_size, int n_threads) {
  const auto levels = make_levels(n_levels, offsets, resolutions, dense, table_size);
  if (n <= 0 || (!grad_x && !grad_table)) return;
  if (grad_table) {
    NEB_DISPATCH(dtype, F,
                 (neb_hash_grid::backward_table<T, kF>(as_ptr<const T>(grad_out), as_ptr<const T>(x),
                                                       as_ptr<const T>(table), as_ptr<T>(grad_table),
                                                       grad_x ? as_ptr<T>(grad_x) : nullptr, n, levels, n_threads)));
  } else {
    NEB_DISPATCH(dtype, F,
                 (neb_hash_grid::backward_points<T, kF>(as_ptr<const T>(grad_out), as_ptr<const T>(x),
                                                        as_ptr<const T>(table), as_ptr<T>(grad_x), n, levels,
                                                        n_threads)));
  }
}

template <typename T, int F>
void forward_blocks_typed(uintptr_t xw, uintptr_t centres, const std::vector<uintptr_t>& tables, double edge,
                          double blend, uintptr_t out, uintptr_t valid, uintptr_t jac, int64_t n,
                          const std::vector<Level>& levels, int n_threads) {
  std::vector<const T*> tabs;
  for (uintptr_t t : tables) tabs.push_back(as_ptr<const T>(t));
  const auto run = [&](auto with_jacobian) {  // std::true_type / std::false_type: the kernel's kJacobian
    neb_hash_grid::forward_blocks<T, F, decltype(with_jacobian)::value>(
        as_ptr<const T>(xw), as_ptr<const T>(centres), tabs, static_cast<T>(edge), static_cast<T>(blend),
        as_ptr<T>(out), as_ptr<uint8_t>(valid), as_ptr<T>(jac), n, levels, n_threads);
  };
  if (jac)
    run(std::true_type{});
  else
    run(std::false_type{});
}

// xw (n, 3) world points, centres (M, 3), tables: M addresses of (E, F) tables with one level layout,
// out (n, L*F), valid (n) bytes, jac (n, 3, L*F) or 0 when the derivatives w.r.t. the points are not
// wanted: all contiguous, same dtype, allocated by the caller.
void forward_blocks(int dtype, int64_t F, uintptr_t xw, uintptr_t centres, const std::vector<uintptr_t>& tables,
                    double edge, double blend, uintptr_t out, uintptr_t valid, uintptr_t jac, int64_t n,
                    int64_t n_levels, uintptr_t offsets, uintptr_t resolutions, uintptr_t dense, int64_t table_size,
                    int n_threads) {
  const auto levels = make_levels(n_levels, offsets, resolutions, dense, table_size);
  if (!(edge > 0)) throw std::invalid_argument("hash_grid: block edge must be positive");
  if (n <= 0) return;
  NEB_DISPATCH(dtype, F, (forward_blocks_typed<T, kF>(xw, centres, tables, edge, blend, out, valid, jac, n, levels,
                                                      n_threads)));
}

#define NEB_DISPATCH_FLOAT(DTYPE, STATEMENT)                                                            \
  if ((DTYPE) == 0) {                                                                                   \
    using T = float;                                                                                    \
    STATEMENT;                                                                                          \
  } else if ((DTYPE) == 1) {                                                                            \
    using T = double;                                                                                   \
    STATEMENT;                                                                                          \
  } else {                                                                                              \
    throw std::invalid_argument("one_blob: dtype code must be 0 (float32) or 1 (float64)");            \
  }

void check_one_blob(int64_t n_bins, double period) {
  if (n_bins < 1 || n_bins > 4096)
    throw std::invalid_argument("one_blob: n_bins out of range: " + std::to_string(n_bins));
  if (!(period > 0)) throw std::invalid_argument("one_blob: period must be positive");
}

// x (n, 3), out (n, 3 * n_bins): contiguous, same dtype, allocated by the caller.
void one_blob_forward(int dtype, uintptr_t x, uintptr_t out, int64_t n, int64_t n_bins, double period,
                      int n_threads) {
  check_one_blob(n_bins, period);
  if (n <= 0) return;
  NEB_DISPATCH_FLOAT(dtype, (neb_one_blob::forward<T>(as_ptr<const T>(x), as_ptr<T>(out), n, static_cast<int>(n_bins),
                                                      static_cast<T>(period), n_threads)));
}

// grad_out (n, 3 * n_bins), x (n, 3), grad_x (n, 3): contiguous, same dtype; grad_x fully written.
void one_blob_backward(int dtype, uintptr_t grad_out, uintptr_t x, uintptr_t grad_x, int64_t n, int64_t n_bins,
                       double period, int n_threads) {
  check_one_blob(n_bins, period);
  if (n <= 0) return;
  NEB_DISPATCH_FLOAT(dtype, (neb_one_blob::backward<T>(as_ptr<const T>(grad_out), as_ptr<const T>(x),
                                                       as_ptr<T>(grad_x), n, static_cast<int>(n_bins),
                                                       static_cast<T>(period), n_threads)));
}

template <typename T>
neb_decoders::Layer<T> layer(uintptr_t w, uintptr_t b, int64_t n_in, int64_t n_out) {
  if (n_in < 1 || n_out < 1 || n_in > 4096 || n_out > 4096)
    throw std::invalid_argument("decoders: layer sizes out of range");
  return {as_ptr<const T>(w), as_ptr<const T>(b), static_cast<int>(n_in), static_cast<int>(n_out)};
}

// blob (n, n_blob), feat (n, n_feat), sdf (n), rgb (n, 3) or 0 (geometry only): contiguous, same dtype,
// allocated by the caller. weights: the 8 addresses W1, b1, W2, b2 (geometry), W3, b3, W4, b4 (colour);
// n_hidden, n_geo_out (1 + feature_dim), n_rgb: the layer sizes (torch.nn.Linear layout).
void decoder_forward(int dtype, uintptr_t blob, uintptr_t feat, int64_t n, int64_t n_blob, int64_t n_feat,
                     const std::vector<uintptr_t>& weights, int64_t n_hidden, int64_t n_geo_out, int64_t n_rgb,
                     uintptr_t sdf, uintptr_t rgb, int n_threads) {
  if (weights.size() != 8) throw std::invalid_argument("decoders: need the 8 weight and bias addresses");
  if (n_geo_out < 1) throw std::invalid_argument("decoders: the geometry MLP needs an sdf output");
  if (n <= 0) return;
  const auto& w = weights;
  NEB_DISPATCH_FLOAT(dtype, (neb_decoders::forward<T>(
      as_ptr<const T>(blob), as_ptr<const T>(feat), static_cast<int>(n_blob), static_cast<int>(n_feat),
      layer<T>(w[0], w[1], n_blob + n_feat, n_hidden), layer<T>(w[2], w[3], n_hidden, n_geo_out),
      layer<T>(w[4], w[5], n_blob + n_geo_out - 1, n_hidden), layer<T>(w[6], w[7], n_hidden, n_rgb),
      as_ptr<T>(sdf), rgb ? as_ptr<T>(rgb) : nullptr, n, n_threads)));
}

// decoder_forward plus derivatives along 3 tangents per point (tangent t: along world axis t):
// blob_slopes (n, 3, n_blob / 3), d_feat (n, 3, n_feat), d_sdf (n, 3), d_rgb (n, 3, 3); rgb is required here.
void decoder_forward_tangents(int dtype, uintptr_t blob, uintptr_t feat, uintptr_t blob_slopes, uintptr_t d_feat, int64_t n,
                              int64_t n_blob, int64_t n_feat, const std::vector<uintptr_t>& weights, int64_t n_hidden,
                              int64_t n_geo_out, int64_t n_rgb, uintptr_t sdf, uintptr_t rgb, uintptr_t d_sdf,
                              uintptr_t d_rgb, int n_threads) {
  if (weights.size() != 8) throw std::invalid_argument("decoders: need the 8 weight and bias addresses");
  if (n_geo_out < 1) throw std::invalid_argument("decoders: the geometry MLP needs an sdf output");
  if (!rgb || !d_sdf || !d_rgb) throw std::invalid_argument("decoders: tangents need rgb, d_sdf and d_rgb");
  if (n_blob % 3 != 0) throw std::invalid_argument("decoders: tangents need a blob of 3 axis blocks");
  if (n <= 0) return;
  const auto& w = weights;
  NEB_DISPATCH_FLOAT(dtype, (neb_decoders::forward_tangents<T>(
      as_ptr<const T>(blob), as_ptr<const T>(feat), as_ptr<const T>(blob_slopes), as_ptr<const T>(d_feat),
      static_cast<int>(n_blob), static_cast<int>(n_feat),
      layer<T>(w[0], w[1], n_blob + n_feat, n_hidden), layer<T>(w[2], w[3], n_hidden, n_geo_out),
      layer<T>(w[4], w[5], n_blob + n_geo_out - 1, n_hidden), layer<T>(w[6], w[7], n_hidden, n_rgb),
      as_ptr<T>(sdf), as_ptr<T>(rgb), as_ptr<T>(d_sdf), as_ptr<T>(d_rgb), n, n_threads)));
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "NeB-SLAM hash-grid and one-blob encodings and decoders: CPU kernels on raw buffers";
  m.def("forward", &forward, "encode points: x (n, 3) -> out (n, L*F)", py::call_guard<py::gil_scoped_release>());
  m.def("forward_blocks", &forward_blocks, "features of world points blended over several blocks, optionally with their derivatives "
        "w.r.t. the points (no autograd)",
        py::call_guard<py::gil_scoped_release>());
  m.def("backward", &backward, "gradients w.r.t. the points and/or the table",
        py::call_guard<py::gil_scoped_release>());
  m.def("one_blob_forward", &one_blob_forward, "one-blob codes: x (n, 3) -> out (n, 3K)",
        py::call_guard<py::gil_scoped_release>());
  m.def("one_blob_backward", &one_blob_backward, "one-blob gradient w.r.t. the points",
        py::call_guard<py::gil_scoped_release>());
  m.def("decoder_forward_tangents", &decoder_forward_tangents,
        "both decoders and their derivatives along 3 tangents per point (no autograd)",
        py::call_guard<py::gil_scoped_release>());
  m.def("decoder_forward", &decoder_forward, "both decoders on (blob, feat) -> sdf, rgb (no gradient)",
        py::call_guard<py::gil_scoped_release>());
}
