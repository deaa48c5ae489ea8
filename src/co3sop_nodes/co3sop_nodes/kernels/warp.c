/* Trilinear resampling of a channels-last volume on the ego's grid, for output voxels [start, end): the inference
 * path of co3sop_nodes/model/warp.py, whose definition is grid_sample (trilinear, zeros outside,
 * align_corners=False) on a grid from affine_grid. Each output voxel's sampling point is affine_grid's: theta
 * applied to the voxel centre in normalised coordinates. Channels-last, a voxel's channels are contiguous: each
 * output voxel is 8 corners x C multiply-adds, accumulated in registers. Also the sum of the in-bounds corners'
 * weights: the warp of a volume of ones, from which the warp mask is read. The features are written in float32, or
 * for a bfloat16 path rounded to bfloat16 (to nearest even, as PyTorch converts) by warp_trilinear_bf16: the
 * attention reads them so, and one pass over them is saved.
 */
#include <math.h>
#include <stdint.h>

#include "bfloat16.h"

#define MAX_FEATURES 256

/* Output voxels [start, end): their cf feature channels into dst (float32, or bfloat16 where `bf16`), the confidence
 * into last and the in-bounds weight into filled. Inlined with cf and bf16 constants where the caller's are (the
 * presets' 32, 48 and 128 channels), so that a voxel's accumulators live in registers. */
static inline __attribute__((always_inline)) void warp_voxels(const float *restrict src, const float *restrict conf_src,
                                                               int64_t nx, int64_t ny, int64_t nz, const int64_t cf,
                                                               const float *restrict theta, const float *restrict base,
                                                               void *restrict dst, const int bf16,
                                                               float *restrict last, float *restrict filled,
                                                               int64_t start, int64_t end) {
  for (int64_t v = start; v < end; ++v) {
    const int64_t i = v / (ny * nz), j = v / nz % ny, l = v % nz;
    const float bx = base[i], by = base[nx + j], bz = base[nx + ny + l];
    const float gz = theta[0] * bz + theta[1] * by + theta[2] * bx + theta[3];
    const float gy = theta[4] * bz + theta[5] * by + theta[6] * bx + theta[7];
    const float gx = theta[8] * bz + theta[9] * by + theta[10] * bx + theta[11];
    /* grid_sample's unnormalisation: ((g + 1) * size - 1) / 2 */
    const float x = ((gx + 1) * nx - 1) / 2, y = ((gy + 1) * ny - 1) / 2, z = ((gz + 1) * nz - 1) / 2;
    float acc[MAX_FEATURES];
    float conf = 0.0f, sum = 0.0f;
    for (int64_t k = 0; k < cf; ++k) acc[k] = 0.0f;
    if (x > -1.0f && x < nx && y > -1.0f && y < ny && z > -1.0f && z < nz) { /* else outside (or NaN) */
      const float fx = floorf(x), fy = floorf(y), fz = floorf(z), ax = x - fx, ay = y - fy, az = z - fz;
      const int64_t x0 = (int64_t)fx, y0 = (int64_t)fy, z0 = (int64_t)fz;
      for (int corner = 0; corner < 8; ++corner) {
        const int64_t ci = x0 + (corner >> 2), cj = y0 + ((corner >> 1) & 1), cl = z0 + (corner & 1);
        if (ci < 0 || ci >= nx || cj < 0 || cj >= ny || cl < 0 || cl >= nz) continue;
        const float w =
            ((corner >> 2) ? ax : 1 - ax) * (((corner >> 1) & 1) ? ay : 1 - ay) * ((corner & 1) ? az : 1 - az);
        const int64_t at = (ci * ny + cj) * nz + cl;
        const float *in = src + at * cf;
        for (int64_t k = 0; k < cf; ++k) acc[k] += w * in[k];
        conf += w * conf_src[at];
        sum += w;
      }
    }
    if (bf16)
      for (int64_t k = 0; k < cf; ++k) ((uint16_t *)dst)[v * cf + k] = to_bf16(acc[k]);
    else
      for (int64_t k = 0; k < cf; ++k) ((float *)dst)[v * cf + k] = acc[k];
    last[v] = conf;
    filled[v] = sum;
  }
}

/* the cases compiled apart: the presets' channel counts, then any C */
#define WARP_CASES(bf16)                                                                           \
  if (c == 32)                                                                                     \
    warp_voxels(src, conf_src, nx, ny, nz, 32, theta, base, dst, bf16, last, filled, start, end);  \
  else if (c == 48)                                                                                \
    warp_voxels(src, conf_src, nx, ny, nz, 48, theta, base, dst, bf16, last, filled, start, end);  \
  else if (c == 128)                                                                               \
    warp_voxels(src, conf_src, nx, ny, nz, 128, theta, base, dst, bf16, last, filled, start, end); \
  else                                                                                             \
    warp_voxels(src, conf_src, nx, ny, nz, c, theta, base, dst, bf16, last, filled, start, end);

/* src: (X, Y, Z, C) the features, channels-last, and conf_src (X, Y, Z) the confidence; theta: (3, 4) affine_grid's
 * matrix, rows and columns in grid_sample's (w, h, d) = (z, y, x) order; base: affine_grid's voxel centres in
 * [-1, 1] along x, then y, then z (X + Y + Z values) -> dst (V, C) the features, last (V,) the confidence,
 * filled (V,); C at most MAX_FEATURES */
void warp_trilinear(const float *restrict src, const float *restrict conf_src, int64_t nx, int64_t ny, int64_t nz,
                    int64_t c, const float *restrict theta, const float *restrict base, float *restrict dst,
                    float *restrict last, float *restrict filled, int64_t start, int64_t end) {
  WARP_CASES(0)
}

/* warp_trilinear with dst (V, C) bfloat16 */
void warp_trilinear_bf16(const float *restrict src, const float *restrict conf_src, int64_t nx, int64_t ny,
                         int64_t nz, int64_t c, const float *restrict theta, const float *restrict base,
                         uint16_t *restrict dst, float *restrict last, float *restrict filled, int64_t start,
                         int64_t end) {
  WARP_CASES(1)
}
