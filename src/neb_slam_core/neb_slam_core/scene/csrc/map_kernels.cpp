// The CPU kernels of the neural block map as one Python module, neb_slam_core.scene._map_kernels: the
// multi-resolution hash encoding (hash_grid_kernels.h), the one-blob encoding (one_blob_kernels.h) and the
// decoders' forward pass (decoder_kernels.h), and the marking of a block's observed space
// (observed_kernels.h); read those files' headers for the maths, the layout and the
// work split. Built when the package is installed (setup.py: a torch CppExtension); neb_slam_core/scene/_ext.py
// compiles it on first use (torch.utils.cpp_extension.load) only when that build is missing or was made
// from other sources, flags, torch or CPU (the build key below).
//
// Every function takes torch tensors and checks them itself: CPU, dtype (float32 or float64, one dtype for
// all the floating-point arguments; int64 and bool for the level buffers), shape and contiguity. A failed
// check is a RuntimeError (TORCH_CHECK) naming the function and the argument. The functions allocate and
// return their outputs; the kernels run with the GIL released, on torch's intra-op thread count.

#include <torch/extension.h>

#include <cstdint>
#include <optional>
#include <sstream>
#include <string>
#include <tuple>
#include <type_traits>
#include <vector>

#include "hash_grid_kernels.h"
#include "decoder_kernels.h"
#include "observed_kernels.h"
#include "one_blob_kernels.h"

// The hash of the sources, flags, torch and Python versions and CPU the module was built for
// (_ext.build_key); _ext.py loads a module only when it equals the hash of what it has at hand.
#ifndef NEB_MAP_KERNELS_BUILD_KEY
#define NEB_MAP_KERNELS_BUILD_KEY unknown
#endif
#define NEB_STRINGIFY_(X) #X
#define NEB_STRINGIFY(X) NEB_STRINGIFY_(X)

namespace py = pybind11;
using at::Tensor;
using neb_hash_grid::Level;

namespace {

constexpr int64_t kAny = -1;  // a size check_tensor accepts whatever it is

std::string shape_text(const std::vector<int64_t>& shape) {
  std::ostringstream s;
  s << "(";
  for (size_t d = 0; d < shape.size(); ++d) {
    if (d) s << ", ";
    if (shape[d] == kAny)
      s << "*";
    else
      s << shape[d];
  }
  s << (shape.size() == 1 ? ",)" : ")");
  return s.str();
}

// t must be a contiguous CPU tensor of `dtype` and `shape` (kAny: any size); fn and arg name it in the error.
void check_tensor(const Tensor& t, const char* fn, const std::string& arg, at::ScalarType dtype,
                  const std::vector<int64_t>& shape) {
  TORCH_CHECK(t.device().is_cpu(), fn, ": ", arg, " must be a CPU tensor, got one on ", t.device());
  TORCH_CHECK(t.scalar_type() == dtype, fn, ": ", arg, " must be ", dtype, ", got ", t.scalar_type());
  bool shape_ok = t.dim() == static_cast<int64_t>(shape.size());
  for (size_t d = 0; shape_ok && d < shape.size(); ++d) shape_ok = shape[d] == kAny || t.size(d) == shape[d];
  TORCH_CHECK(shape_ok, fn, ": ", arg, " must have shape ", shape_text(shape), ", got ", t.sizes());
  TORCH_CHECK(t.is_contiguous(), fn, ": ", arg, " must be contiguous");
}

// The floating-point dtype of the call, taken from its first float argument t: float32 or float64.
at::ScalarType float_dtype(const Tensor& t, const char* fn, const char* arg) {
  TORCH_CHECK(t.device().is_cpu(), fn, ": ", arg, " must be a CPU tensor, got one on ", t.device());
  TORCH_CHECK(t.scalar_type() == at::kFloat || t.scalar_type() == at::kDouble, fn, ": ", arg,
              " must be float32 or float64, got ", t.scalar_type());
  return t.scalar_type();
}

// The level table from the HashGrid buffers: offsets (L + 1) int64, resolutions (L) int64, dense (L) bool,
// checked against each other, table_size T and the table's rows.
std::vector<Level> make_levels(const char* fn, const Tensor& offsets, const Tensor& resolutions, const Tensor& dense,
                               int64_t table_size, int64_t table_rows) {
  const int64_t n_levels = resolutions.dim() == 1 ? resolutions.size(0) : 0;
  TORCH_CHECK(n_levels >= 1, fn, ": resolutions must have shape (L,) with L >= 1, got ", resolutions.sizes());
  check_tensor(resolutions, fn, "resolutions", at::kLong, {n_levels});
  check_tensor(offsets, fn, "offsets", at::kLong, {n_levels + 1});
  check_tensor(dense, fn, "dense", at::kBool, {n_levels});
  TORCH_CHECK(table_size >= 1 && (table_size & (table_size - 1)) == 0 && table_size <= (int64_t(1) << 31), fn,
              ": table_size must be a power of two <= 2^31, got ", table_size);
  const int64_t* o = offsets.data_ptr<int64_t>();
  const int64_t* r = resolutions.data_ptr<int64_t>();
  const bool* d = dense.data_ptr<bool>();
  TORCH_CHECK(o[0] == 0 && o[n_levels] == table_rows, fn, ": offsets must run from 0 to the table's ", table_rows,
              " rows, got ", o[0], " to ", o[n_levels]);
  std::vector<Level> levels(n_levels);
  for (int64_t l = 0; l < n_levels; ++l) {
    TORCH_CHECK(r[l] >= 1 && r[l] < (int64_t(1) << 30), fn, ": resolutions[", l, "] out of range: ", r[l]);
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
      TORCH_CHECK(rows <= table_size, fn, ": dense level ", l, " needs more rows than table_size");
      lv.stride_y = static_cast<int32_t>(side);
      lv.stride_z = static_cast<int32_t>(side * side);
    }
    TORCH_CHECK(o[l + 1] - o[l] == rows, fn, ": level ", l, " owns ", o[l + 1] - o[l],
                " rows of the table but its indexing needs ", rows);
  }
  return levels;
}

// Runs STATEMENT with T bound to float or double (DTYPE: at::kFloat or at::kDouble, as float_dtype checks).
#define NEB_DISPATCH_FLOAT(DTYPE, STATEMENT) \
  if ((DTYPE) == at::kFloat) {               \
    using T = float;                         \
    STATEMENT;                               \
  } else {                                   \
    using T = double;                        \
    STATEMENT;                               \
  }

// ... and kF bound to the features per level F_VALUE. Only F = 2 (the paper's) is compiled: hash_grid.py sends
// other F to the plain-torch reference.
#define NEB_DISPATCH(DTYPE, F_VALUE, FN, STATEMENT)                                                      \
  TORCH_CHECK((F_VALUE) == 2, FN, ": the fast path is built for 2 features per level, got a table of ", \
              (F_VALUE), " columns");                                                                    \
  NEB_DISPATCH_FLOAT(DTYPE, constexpr int kF = 2; STATEMENT)

// The checked arguments of a call on one grid: points x (n, 3), table (E, F) and its level layout.
struct GridCall {
  at::ScalarType dtype;
  std::vector<Level> levels;
  int64_t n, F;
  int64_t width() const { return static_cast<int64_t>(levels.size()) * F; }  // L*F, the features per point
};

GridCall check_grid_call(const char* fn, const Tensor& x, const Tensor& table, const Tensor& offsets,
                         const Tensor& resolutions, const Tensor& dense, int64_t table_size) {
  const auto dtype = float_dtype(x, fn, "x");
  check_tensor(x, fn, "x", dtype, {kAny, 3});
  check_tensor(table, fn, "table", dtype, {kAny, kAny});
  return {dtype, make_levels(fn, offsets, resolutions, dense, table_size, table.size(0)), x.size(0), table.size(1)};
}

// x (n, 3), table (E, F) -> (n, L*F).
Tensor hash_grid_forward(const Tensor& x, const Tensor& table, const Tensor& offsets, const Tensor& resolutions,
                         const Tensor& dense, int64_t table_size) {
  constexpr const char* fn = "hash_grid_forward";
  const GridCall c = check_grid_call(fn, x, table, offsets, resolutions, dense, table_size);
  Tensor out = at::empty({c.n, c.width()}, x.options());
  if (c.n <= 0) return out;
  const int n_threads = at::get_num_threads();
  NEB_DISPATCH(c.dtype, c.F, fn,
               (neb_hash_grid::forward<T, kF>(x.data_ptr<T>(), table.data_ptr<T>(), out.data_ptr<T>(), c.n, c.levels,
                                              n_threads)));
  return out;
}

// grad_out (n, L*F) -> the gradients w.r.t. x (n, 3) when need_x and w.r.t. the table (E, F) when need_table
// (None otherwise): only what is asked for is computed.
std::tuple<std::optional<Tensor>, std::optional<Tensor>> hash_grid_backward(
    const Tensor& grad_out, const Tensor& x, const Tensor& table, const Tensor& offsets, const Tensor& resolutions,
    const Tensor& dense, int64_t table_size, bool need_x, bool need_table) {
  constexpr const char* fn = "hash_grid_backward";
  const GridCall c = check_grid_call(fn, x, table, offsets, resolutions, dense, table_size);
  const int64_t n = c.n;
  const auto& levels = c.levels;
  check_tensor(grad_out, fn, "grad_out", c.dtype, {n, c.width()});
  std::optional<Tensor> grad_x, grad_table;
  if (need_x) grad_x = at::empty_like(x);
  if (need_table) grad_table = at::zeros_like(table);  // the kernel adds into it
  if (n <= 0 || !(need_x || need_table)) return {grad_x, grad_table};
  const int n_threads = at::get_num_threads();
  if (need_table) {
    NEB_DISPATCH(c.dtype, c.F, fn,
                 (neb_hash_grid::backward_table<T, kF>(grad_out.data_ptr<T>(), x.data_ptr<T>(), table.data_ptr<T>(),
                                                       grad_table->data_ptr<T>(),
                                                       need_x ? grad_x->data_ptr<T>() : nullptr, n, levels,
                                                       n_threads)));
  } else {
    NEB_DISPATCH(c.dtype, c.F, fn,
                 (neb_hash_grid::backward_points<T, kF>(grad_out.data_ptr<T>(), x.data_ptr<T>(), table.data_ptr<T>(),
                                                        grad_x->data_ptr<T>(), n, levels, n_threads)));
  }
  return {grad_x, grad_table};
}

template <typename T, int F>
void forward_blocks_typed(const Tensor& xw, const Tensor& centres, const std::vector<Tensor>& tables, double edge,
                          double blend, Tensor& out, Tensor& valid, std::optional<Tensor>& jac,
                          const std::vector<Level>& levels, int n_threads) {
  std::vector<const T*> tabs;
  for (const Tensor& t : tables) tabs.push_back(t.data_ptr<T>());
  const auto run = [&](auto with_jacobian) {  // std::true_type / std::false_type: the kernel's kJacobian
    neb_hash_grid::forward_blocks<T, F, decltype(with_jacobian)::value>(
        xw.data_ptr<T>(), centres.data_ptr<T>(), tabs, static_cast<T>(edge), static_cast<T>(blend), out.data_ptr<T>(),
        reinterpret_cast<uint8_t*>(valid.data_ptr<bool>()), jac ? jac->data_ptr<T>() : nullptr, xw.size(0), levels,
        n_threads);
  };
  if (jac)
    run(std::true_type{});
  else
    run(std::false_type{});
}

// xw (n, 3) world points, centres (M, 3), tables: M (E, F) tables with one level layout -> features (n, L*F),
// valid (n) bool and, with with_jacobian, their derivatives w.r.t. the points (n, 3, L*F) (else None).
std::tuple<Tensor, Tensor, std::optional<Tensor>> hash_grid_forward_blocks(
    const Tensor& xw, const Tensor& centres, const std::vector<Tensor>& tables, const Tensor& offsets,
    const Tensor& resolutions, const Tensor& dense, int64_t table_size, double edge, double blend,
    bool with_jacobian) {
  constexpr const char* fn = "hash_grid_forward_blocks";
  const auto dtype = float_dtype(xw, fn, "xw");
  check_tensor(xw, fn, "xw", dtype, {kAny, 3});
  TORCH_CHECK(!tables.empty(), fn, ": tables must hold at least one table");
  const int64_t n_blocks = static_cast<int64_t>(tables.size());
  check_tensor(centres, fn, "centres", dtype, {n_blocks, 3});
  check_tensor(tables[0], fn, "tables[0]", dtype, {kAny, kAny});
  for (int64_t b = 1; b < n_blocks; ++b)
    check_tensor(tables[b], fn, "tables[" + std::to_string(b) + "]", dtype, {tables[0].size(0), tables[0].size(1)});
  TORCH_CHECK(edge > 0, fn, ": edge must be positive, got ", edge);
  const auto levels = make_levels(fn, offsets, resolutions, dense, table_size, tables[0].size(0));
  const int64_t n = xw.size(0), F = tables[0].size(1), D = static_cast<int64_t>(levels.size()) * F;
  Tensor out = at::empty({n, D}, xw.options());
  Tensor valid = at::empty({n}, xw.options().dtype(at::kBool));
  std::optional<Tensor> jac;
  if (with_jacobian) jac = at::empty({n, 3, D}, xw.options());
  if (n <= 0) return {out, valid, jac};
  const int n_threads = at::get_num_threads();
  NEB_DISPATCH(dtype, F, fn,
               (forward_blocks_typed<T, kF>(xw, centres, tables, edge, blend, out, valid, jac, levels, n_threads)));
  return {out, valid, jac};
}

void check_one_blob(const char* fn, int64_t n_bins, double period) {
  TORCH_CHECK(n_bins >= 1 && n_bins <= 4096, fn, ": n_bins out of range: ", n_bins);
  TORCH_CHECK(period > 0, fn, ": period must be positive, got ", period);
}

// x (n, 3) -> codes (n, 3 * n_bins).
Tensor one_blob_forward(const Tensor& x, int64_t n_bins, double period) {
  constexpr const char* fn = "one_blob_forward";
  const auto dtype = float_dtype(x, fn, "x");
  check_tensor(x, fn, "x", dtype, {kAny, 3});
  check_one_blob(fn, n_bins, period);
  const int64_t n = x.size(0);
  Tensor out = at::empty({n, 3 * n_bins}, x.options());
  if (n <= 0) return out;
  const int n_threads = at::get_num_threads();
  NEB_DISPATCH_FLOAT(dtype, (neb_one_blob::forward<T>(x.data_ptr<T>(), out.data_ptr<T>(), n, static_cast<int>(n_bins),
                                                      static_cast<T>(period), n_threads)));
  return out;
}

// grad_out (n, 3 * n_bins), x (n, 3) -> the gradient w.r.t. x (n, 3).
Tensor one_blob_backward(const Tensor& grad_out, const Tensor& x, int64_t n_bins, double period) {
  constexpr const char* fn = "one_blob_backward";
  const auto dtype = float_dtype(x, fn, "x");
  check_tensor(x, fn, "x", dtype, {kAny, 3});
  check_one_blob(fn, n_bins, period);
  const int64_t n = x.size(0);
  check_tensor(grad_out, fn, "grad_out", dtype, {n, 3 * n_bins});
  Tensor grad_x = at::empty_like(x);
  if (n <= 0) return grad_x;
  const int n_threads = at::get_num_threads();
  NEB_DISPATCH_FLOAT(dtype, (neb_one_blob::backward<T>(grad_out.data_ptr<T>(), x.data_ptr<T>(), grad_x.data_ptr<T>(),
                                                       n, static_cast<int>(n_bins), static_cast<T>(period),
                                                       n_threads)));
  return grad_x;
}

// The decoders' weights, torch.nn.Linear layout: W1, b1, W2, b2 (geometry), W3, b3, W4, b4 (colour), with
// W1 (H, n_blob + n_feat), W2 (G, H) (sdf and G - 1 features), W3 (H, n_blob + G - 1), W4 (R, H) (colours).
struct DecoderShape {
  int64_t n_blob, n_feat, n_hidden, n_geo_out, n_rgb;
};

DecoderShape check_decoder(const char* fn, at::ScalarType dtype, const Tensor& blob, const Tensor& feat,
                           const std::vector<Tensor>& w) {
  check_tensor(blob, fn, "blob", dtype, {kAny, kAny});
  const int64_t n = blob.size(0);
  check_tensor(feat, fn, "feat", dtype, {n, kAny});
  TORCH_CHECK(w.size() == 8, fn, ": weights must be the 8 tensors W1, b1, W2, b2, W3, b3, W4, b4, got ", w.size());
  const int64_t n_blob = blob.size(1), n_feat = feat.size(1);
  const int64_t H = w[0].dim() == 2 ? w[0].size(0) : kAny, G = w[2].dim() == 2 ? w[2].size(0) : kAny;
  const int64_t R = w[6].dim() == 2 ? w[6].size(0) : kAny;
  check_tensor(w[0], fn, "weights[0] (W1)", dtype, {kAny, n_blob + n_feat});
  check_tensor(w[1], fn, "weights[1] (b1)", dtype, {H});
  check_tensor(w[2], fn, "weights[2] (W2)", dtype, {kAny, H});
  check_tensor(w[3], fn, "weights[3] (b2)", dtype, {G});
  TORCH_CHECK(G >= 1, fn, ": the geometry MLP needs an sdf output (weights[2] has 0 rows)");
  check_tensor(w[4], fn, "weights[4] (W3)", dtype, {H, n_blob + G - 1});
  check_tensor(w[5], fn, "weights[5] (b3)", dtype, {H});
  check_tensor(w[6], fn, "weights[6] (W4)", dtype, {kAny, H});
  check_tensor(w[7], fn, "weights[7] (b4)", dtype, {R});
  for (int64_t size : {n_blob + n_feat, H, G, n_blob + G - 1, R})
    TORCH_CHECK(size >= 1 && size <= 4096, fn, ": layer sizes must be in [1, 4096], got ", size);
  return {n_blob, n_feat, H, G, R};
}

template <typename T>
neb_decoders::Layer<T> layer(const Tensor& w, const Tensor& b) {
  return {w.data_ptr<T>(), b.data_ptr<T>(), static_cast<int>(w.size(1)), static_cast<int>(w.size(0))};
}

// blob (n, n_blob), feat (n, n_feat), weights (see DecoderShape) -> sdf (n) and, with with_colour, rgb (n, R)
// (else None).
std::tuple<Tensor, std::optional<Tensor>> decoder_forward(const Tensor& blob, const Tensor& feat,
                                                          const std::vector<Tensor>& weights, bool with_colour) {
  constexpr const char* fn = "decoder_forward";
  const auto dtype = float_dtype(blob, fn, "blob");
  const DecoderShape s = check_decoder(fn, dtype, blob, feat, weights);
  const int64_t n = blob.size(0);
  Tensor sdf = at::empty({n}, blob.options());
  std::optional<Tensor> rgb;
  if (with_colour) rgb = at::empty({n, s.n_rgb}, blob.options());
  if (n <= 0) return {sdf, rgb};
  const int n_threads = at::get_num_threads();
  const auto& w = weights;
  NEB_DISPATCH_FLOAT(dtype, (neb_decoders::forward<T>(
      blob.data_ptr<T>(), feat.data_ptr<T>(), static_cast<int>(s.n_blob), static_cast<int>(s.n_feat),
      layer<T>(w[0], w[1]), layer<T>(w[2], w[3]), layer<T>(w[4], w[5]), layer<T>(w[6], w[7]), sdf.data_ptr<T>(),
      with_colour ? rgb->data_ptr<T>() : nullptr, n, n_threads)));
  return {sdf, rgb};
}

// decoder_forward plus derivatives along 3 tangents per point (tangent t: along world axis t):
// blob_slopes (n, 3, n_blob / 3), d_feat (n, 3, n_feat) -> sdf (n), rgb (n, R), d_sdf (n, 3), d_rgb (n, 3, R).
std::tuple<Tensor, Tensor, Tensor, Tensor> decoder_forward_tangents(const Tensor& blob, const Tensor& feat,
                                                                    const Tensor& blob_slopes, const Tensor& d_feat,
                                                                    const std::vector<Tensor>& weights) {
  constexpr const char* fn = "decoder_forward_tangents";
  const auto dtype = float_dtype(blob, fn, "blob");
  const DecoderShape s = check_decoder(fn, dtype, blob, feat, weights);
  const int64_t n = blob.size(0);
  TORCH_CHECK(s.n_blob % 3 == 0, fn, ": blob must hold 3 axis blocks (n_blob a multiple of 3), got ", s.n_blob);
  check_tensor(blob_slopes, fn, "blob_slopes", dtype, {n, 3, s.n_blob / 3});
  check_tensor(d_feat, fn, "d_feat", dtype, {n, 3, s.n_feat});
  Tensor sdf = at::empty({n}, blob.options()), rgb = at::empty({n, s.n_rgb}, blob.options());
  Tensor d_sdf = at::empty({n, 3}, blob.options()), d_rgb = at::empty({n, 3, s.n_rgb}, blob.options());
  if (n <= 0) return {sdf, rgb, d_sdf, d_rgb};
  const int n_threads = at::get_num_threads();
  const auto& w = weights;
  NEB_DISPATCH_FLOAT(dtype, (neb_decoders::forward_tangents<T>(
      blob.data_ptr<T>(), feat.data_ptr<T>(), blob_slopes.data_ptr<T>(), d_feat.data_ptr<T>(),
      static_cast<int>(s.n_blob), static_cast<int>(s.n_feat), layer<T>(w[0], w[1]), layer<T>(w[2], w[3]),
      layer<T>(w[4], w[5]), layer<T>(w[6], w[7]), sdf.data_ptr<T>(), rgb.data_ptr<T>(), d_sdf.data_ptr<T>(),
      d_rgb.data_ptr<T>(), n, n_threads)));
  return {sdf, rgb, d_sdf, d_rgb};
}

}  // namespace

// Marks the voxels of observed (n, n, n) bool in the box [box[0:3], box[3:6]) that a depth image saw
// (observed_kernels.h): a, b, c the per-axis tables of camera coordinates (box length, 3), t (3,), all
// float32; depth (H, W) float32. Returns whether any voxel was newly marked.
bool mark_observed_box(Tensor observed, const Tensor& box, const Tensor& a, const Tensor& b, const Tensor& c,
                       const Tensor& t, const Tensor& depth, double fx, double fy, double cx, double cy,
                       double truncation, double half_diagonal) {
  constexpr const char* fn = "mark_observed_box";
  check_tensor(observed, fn, "observed", at::kBool, {kAny, kAny, kAny});
  const int64_t n = observed.size(0);
  TORCH_CHECK(observed.size(1) == n && observed.size(2) == n, fn, ": observed must be a cube (n, n, n), got ",
              observed.sizes());
  check_tensor(box, fn, "box", at::kLong, {6});
  const int64_t* i = box.data_ptr<int64_t>();
  for (int axis = 0; axis < 3; ++axis) {
    TORCH_CHECK(0 <= i[axis] && i[axis] < i[axis + 3] && i[axis + 3] <= n, fn, ": box axis ", axis, " [",
                i[axis], ", ", i[axis + 3], ") is empty or outside [0, ", n, ")");
  }
  check_tensor(a, fn, "a", at::kFloat, {i[3] - i[0], 3});
  check_tensor(b, fn, "b", at::kFloat, {i[4] - i[1], 3});
  check_tensor(c, fn, "c", at::kFloat, {i[5] - i[2], 3});
  check_tensor(t, fn, "t", at::kFloat, {3});
  check_tensor(depth, fn, "depth", at::kFloat, {kAny, kAny});
  const neb_observed::Camera cam{float(fx), float(fy), float(cx), float(cy), depth.size(1), depth.size(0)};
  return neb_observed::mark_box(reinterpret_cast<uint8_t*>(observed.data_ptr<bool>()), n, i, i + 3,
                                a.data_ptr<float>(), b.data_ptr<float>(), c.data_ptr<float>(), t.data_ptr<float>(),
                                depth.data_ptr<float>(), cam, float(truncation), float(half_diagonal),
                                at::get_num_threads());
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "NeB-SLAM map kernels (CPU, OpenMP): hash-grid and one-blob encodings, decoders, observed space";
  m.attr("build_key") = NEB_STRINGIFY(NEB_MAP_KERNELS_BUILD_KEY);
  const auto no_gil = py::call_guard<py::gil_scoped_release>();
  m.def("hash_grid_forward", &hash_grid_forward, "hash encoding: x (n, 3) -> (n, L*F)", py::arg("x"),
        py::arg("table"), py::arg("offsets"), py::arg("resolutions"), py::arg("dense"), py::arg("table_size"), no_gil);
  m.def("hash_grid_backward", &hash_grid_backward,
        "gradients w.r.t. the points and/or the table: (grad_x or None, grad_table or None)", py::arg("grad_out"),
        py::arg("x"), py::arg("table"), py::arg("offsets"), py::arg("resolutions"), py::arg("dense"),
        py::arg("table_size"), py::arg("need_x"), py::arg("need_table"), no_gil);
  m.def("hash_grid_forward_blocks", &hash_grid_forward_blocks,
        "features of world points blended over several blocks, optionally with their derivatives w.r.t. the "
        "points (no autograd): (out, valid, jac or None)",
        py::arg("xw"), py::arg("centres"), py::arg("tables"), py::arg("offsets"), py::arg("resolutions"),
        py::arg("dense"), py::arg("table_size"), py::arg("edge"), py::arg("blend"), py::arg("with_jacobian"), no_gil);
  m.def("one_blob_forward", &one_blob_forward, "one-blob codes: x (n, 3) -> (n, 3 * n_bins)", py::arg("x"),
        py::arg("n_bins"), py::arg("period"), no_gil);
  m.def("one_blob_backward", &one_blob_backward, "one-blob gradient w.r.t. the points: grad_x (n, 3)",
        py::arg("grad_out"), py::arg("x"), py::arg("n_bins"), py::arg("period"), no_gil);
  m.def("decoder_forward", &decoder_forward, "both decoders (no gradient): (sdf, rgb or None)", py::arg("blob"),
        py::arg("feat"), py::arg("weights"), py::arg("with_colour"), no_gil);
  m.def("decoder_forward_tangents", &decoder_forward_tangents,
        "both decoders and their derivatives along 3 tangents per point (no autograd): (sdf, rgb, d_sdf, d_rgb)",
        py::arg("blob"), py::arg("feat"), py::arg("blob_slopes"), py::arg("d_feat"), py::arg("weights"), no_gil);
  m.def("mark_observed_box", &mark_observed_box,
        "mark the voxels of a block's observed-space box that a depth image saw: whether any was new",
        py::arg("observed"), py::arg("box"), py::arg("a"), py::arg("b"), py::arg("c"), py::arg("t"), py::arg("depth"),
        py::arg("fx"), py::arg("fy"), py::arg("cx"), py::arg("cy"), py::arg("truncation"), py::arg("half_diagonal"),
        no_gil);
}
