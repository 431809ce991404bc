// The observed-space record of a block: marking the voxels a keyframe saw (plain C++ and OpenMP, no torch).
//
// Written by hand because the torch version (BlockMap.mark_observed's reference path) evaluates about a
// dozen element-wise ops over every voxel of the box a keyframe sees (a million or more per block), each a
// pass over memory with its own temporary; a keyframe's marking then costs the tracker tens of
// milliseconds. Here one pass over the box does it, and skips voxels already seen before any arithmetic.
//
// Maths (identical to the reference path, which the tests compare against voxel for voxel): the camera
// coordinates of voxel (i, j, k) of the box are ((A[i] + B[j]) + C[k]) + t, float32 sums in that order,
// where A, B, C are the per-axis tables the caller computes (the voxel centre's world coordinate along
// one axis times the matching column of R_cw) and t = -R_cw t_wc. With z its depth, the voxel is in front
// when z > 1e-6; its pixel is (round(fx x / z + cx), round(fy y / z + cy)), rounding half to even as
// torch.round; it is seen when that pixel lies in the image, has a depth d > 0, and z <= (d + truncation)
// + half_diagonal. The arithmetic is float32 in the reference's order, so both mark the same voxels.
//
// Work split: the box's first axis in static chunks over the threads; every voxel is its own, so the
// result does not depend on the thread count.

#pragma once

#include <omp.h>

#include <cmath>
#include <cstdint>

namespace neb_observed {

struct Camera {
  float fx, fy, cx, cy;
  int64_t width, height;
};

// observed (n, n, n) bytes (0 or 1), the box [i0, i1) per axis; a (i1[0] - i0[0], 3), b (.., 3), c (.., 3)
// the per-axis tables; t (3,); depth (height, width). Returns whether any voxel was newly marked.
inline bool mark_box(uint8_t* __restrict observed, int64_t n, const int64_t* i0, const int64_t* i1,
                     const float* __restrict a, const float* __restrict b, const float* __restrict c,
                     const float* t, const float* __restrict depth, const Camera& cam, float truncation,
                     float half_diagonal, int n_threads) {
  const int64_t ni = i1[0] - i0[0], nj = i1[1] - i0[1], nk = i1[2] - i0[2];
  bool grown = false;
#pragma omp parallel for schedule(static) num_threads(n_threads) reduction(|| : grown)
  for (int64_t i = 0; i < ni; ++i) {
    for (int64_t j = 0; j < nj; ++j) {
      uint8_t* row = observed + ((i0[0] + i) * n + (i0[1] + j)) * n + i0[2];
      const float ab[3] = {a[3 * i] + b[3 * j], a[3 * i + 1] + b[3 * j + 1], a[3 * i + 2] + b[3 * j + 2]};
      for (int64_t k = 0; k < nk; ++k) {
        if (row[k]) continue;
        const float x = (ab[0] + c[3 * k]) + t[0];
        const float y = (ab[1] + c[3 * k + 1]) + t[1];
        const float z = (ab[2] + c[3 * k + 2]) + t[2];
        if (!(z > 1e-6f)) continue;
        const float px = std::nearbyint(cam.fx * x / z + cam.cx);
        const float py = std::nearbyint(cam.fy * y / z + cam.cy);
        if (!(px >= 0.0f && px < float(cam.width) && py >= 0.0f && py < float(cam.height))) continue;
        const float d = depth[int64_t(py) * cam.width + int64_t(px)];
        if (d > 0.0f && z <= (d + truncation) + half_diagonal) {
          row[k] = 1;
          grown = true;
        }
      }
    }
  }
  return grown;
}

}  // namespace neb_observed
