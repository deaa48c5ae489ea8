/* Points binned into a voxel grid's occupancy: see co3sop_nodes/kernels/point_occupancy.py.
 *
 * One pass over the points, each one's voxel computed in double precision exactly as NumPy computes it (the float32
 * coordinate widened, the origin subtracted, then divided by the voxel size: no multiply-add to contract), kept when
 * every coordinate lies in [0, n) (false for NaN), truncated to its index.
 */
#include <stdint.h>

/* points (N, stride) float32, the first three columns x, y, z -> occupancy (X, Y, Z) uint8, C order, set to 1 where
 * a point falls (the caller zeroes it) */
void point_occupancy(const float *points, int64_t n, int64_t stride, const double *origin, double voxel, int64_t nx,
                     int64_t ny, int64_t nz, uint8_t *occupancy) {
  const double dims[3] = {(double)nx, (double)ny, (double)nz};
  for (int64_t p = 0; p < n; p++) {
    const float *point = points + p * stride;
    double v[3];
    int inside = 1;
    for (int d = 0; d < 3; d++) {
      v[d] = ((double)point[d] - origin[d]) / voxel;
      inside &= (v[d] >= 0.0) & (v[d] < dims[d]);
    }
    if (inside) occupancy[((int64_t)v[0] * ny + (int64_t)v[1]) * nz + (int64_t)v[2]] = 1;
  }
}
