/* The first layer of a LiDAR vehicle half on a reduced-precision path: see co3sop_nodes/kernels/occupancy_conv.py.
 *
 * A 3x3x3 convolution of stride 2 and padding 1 from one binary channel (a voxelised scan, about 1 % occupied) to
 * C channels, then ReLU. Each output x-slab starts at the bias; every occupied voxel of the three input x-planes it
 * reads adds its tap's C weights to the (at most 4) outputs of the slab it falls in; the slab is then rectified
 * and written with channels innermost (the spatial axes in any order: channels-last, or z-outer for the next
 * layer), as OUT says: 0 float32, 1 bfloat16 rounded to nearest even, 2 uint8 quantized (value / scale rounded to
 * nearest even and clamped to 255, as PyTorch quantizes with zero point 0, the quotient within an ulp). The work
 * follows the occupied voxels, not the grid: oneDNN's convolution reads every voxel of its one-channel input.
 */
#include <stdint.h>
#include <stdlib.h>

#include "bfloat16.h"
#include "nonzero.h"
#include "quantize.h"

/* occupancy (X, Y, Z) uint8, nonzero = occupied; w (3, 3, 3, C) taps, bias (C,) -> out (X2, Y2, Z2, C) for output
 * x-slabs [start, end), X2 = ceil(X / 2) and so on, output voxel (x, y, z) at element x sx + y sy + z sz (its C
 * channels contiguous); `scale`: OUT=2's quantization step (unused otherwise); returns -1 if its scratch could
 * not be allocated */
int occupancy_conv(const uint8_t *restrict occupancy, int64_t nx, int64_t ny, int64_t nz, const float *restrict w,
                   const float *restrict bias, void *restrict out, int64_t sx, int64_t sy, int64_t sz, int64_t start,
                   int64_t end, float scale) {
  const int64_t ny2 = (ny + 1) / 2, nz2 = (nz + 1) / 2, slab = ny2 * nz2 * C;
  const float inverse = 1.0f / scale; /* a product, not a division, a value: PyTorch's quotient within an ulp */
  float *acc = malloc(slab * sizeof(float));
  if (!acc) return -1;
  for (int64_t ox = start; ox < end; ++ox) {
    for (int64_t v = 0; v < ny2 * nz2; ++v)
      for (int c = 0; c < C; ++c) acc[v * C + c] = bias[c];
    for (int di = 0; di < 3; ++di) {
      const int64_t ix = 2 * ox - 1 + di;
      if (ix < 0 || ix >= nx) continue;
      /* the plane's rows one after another, as one run of bytes (a row alone is a few words), in its order */
      const uint8_t *plane = occupancy + ix * ny * nz;
      for (int64_t at = next_nonzero(plane, 0, ny * nz); at < ny * nz; at = next_nonzero(plane, at + 1, ny * nz)) {
        const int64_t iy = at / nz, iz = at % nz;
        for (int dj = 0; dj < 3; ++dj) {  /* output oy reads input 2 oy - 1 + dj */
          const int64_t ty = iy + 1 - dj, oy = ty / 2;
          if ((ty & 1) || ty < 0 || oy >= ny2) continue;
          for (int dk = 0; dk < 3; ++dk) {
            const int64_t tz = iz + 1 - dk, oz = tz / 2;
            if ((tz & 1) || tz < 0 || oz >= nz2) continue;
            const float *tap = w + ((di * 3 + dj) * 3 + dk) * C;
            float *sum = acc + (oy * nz2 + oz) * C;
            for (int c = 0; c < C; ++c) sum[c] += tap[c];
          }
        }
      }
    }
    for (int64_t oy = 0; oy < ny2; ++oy)
      for (int64_t oz = 0; oz < nz2; ++oz) {
        const float *sum = acc + (oy * nz2 + oz) * C;
        const int64_t at = ox * sx + oy * sy + oz * sz;
#if OUT == 2
        uint8_t *o = (uint8_t *)out + at;
        for (int c = 0; c < C; ++c) o[c] = to_uint8(sum[c] * inverse);
#elif OUT == 1
        uint16_t *o = (uint16_t *)out + at;
        for (int c = 0; c < C; ++c) o[c] = to_bf16(sum[c] > 0.0f ? sum[c] : 0.0f);
#else
        float *o = (float *)out + at;
        for (int c = 0; c < C; ++c) o[c] = sum[c] > 0.0f ? sum[c] : 0.0f;
#endif
      }
  }
  free(acc);
  return 0;
}
