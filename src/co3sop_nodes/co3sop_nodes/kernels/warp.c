/* Trilinear resampling of a channels-last volume at given points, for output voxels [start, end): the inference
 * path of co3sop_nodes/model/warp.py, whose definition is grid_sample (trilinear, zeros outside,
 * align_corners=False) on a grid from affine_grid. Channels-last, a voxel's channels are contiguous: each output
 * voxel is 8 corners x C multiply-adds. Also the sum of the in-bounds corners' weights: the warp of a volume of
 * ones, from which the warp mask is read.
 */
#include <math.h>
#include <stdint.h>

/* src: (X, Y, Z, C); grid: (V, 3) as grid_sample's (w, h, d) = (z, y, x) coordinates in [-1, 1] -> dst (V, C - 1)
 * the first C - 1 channels, last (V,) the last one (a confidence beside its features), filled (V,) */
void warp_trilinear(const float *restrict src, int64_t nx, int64_t ny, int64_t nz, int64_t c, const float *restrict grid,
                    float *restrict dst, float *restrict last, float *restrict filled, int64_t start, int64_t end) {
  const int64_t cf = c - 1;
  for (int64_t v = start; v < end; ++v) {
    float *out = dst + v * cf;
    for (int64_t k = 0; k < cf; ++k) out[k] = 0.0f;
    last[v] = filled[v] = 0.0f;
    /* grid_sample's unnormalisation: ((g + 1) * size - 1) / 2 */
    const float x = ((grid[3 * v + 2] + 1) * nx - 1) / 2, y = ((grid[3 * v + 1] + 1) * ny - 1) / 2,
                z = ((grid[3 * v] + 1) * nz - 1) / 2;
    if (!(x > -1.0f && x < nx && y > -1.0f && y < ny && z > -1.0f && z < nz)) continue;  /* outside (or NaN) */
    const float fx = floorf(x), fy = floorf(y), fz = floorf(z), ax = x - fx, ay = y - fy, az = z - fz;
    const int64_t x0 = (int64_t)fx, y0 = (int64_t)fy, z0 = (int64_t)fz;
    for (int corner = 0; corner < 8; ++corner) {
      const int64_t i = x0 + (corner >> 2), j = y0 + ((corner >> 1) & 1), l = z0 + (corner & 1);
      if (i < 0 || i >= nx || j < 0 || j >= ny || l < 0 || l >= nz) continue;
      const float w = ((corner >> 2) ? ax : 1 - ax) * (((corner >> 1) & 1) ? ay : 1 - ay) * ((corner & 1) ? az : 1 - az);
      const float *in = src + ((i * ny + j) * nz + l) * c;
      for (int64_t k = 0; k < cf; ++k) out[k] += w * in[k];
      last[v] += w * in[cf];
      filled[v] += w;
    }
  }
}
