/* The sum of two uint8-quantized volumes, requantized: see co3sop_nodes/kernels/quantized_add.py.
 *
 * Volumes stored (rows, Z, XY, C) (z-outer, channels innermost): out = a sa / so + b sb / so + offset[z][c], rounded
 * to nearest even and clamped to [0, 255] (zero points 0), for z-rows [start, end) of all rows * Z; ka = sa / so,
 * kb = sb / so, offset in steps of so. Float32 arithmetic, which the compiler vectorises.
 */
#include <stdint.h>

#include "quantize.h"

void quantized_add(const uint8_t *restrict a, float ka, const uint8_t *restrict b, float kb,
                   const float *restrict offset, uint8_t *restrict out, int64_t nz, int64_t nxy, int64_t start,
                   int64_t end) {
  for (int64_t row = start; row < end; ++row) {
    const float *off = offset + (row % nz) * C;
    const int64_t at = row * nxy * C;
    for (int64_t v = 0; v < nxy; ++v)
      for (int c = 0; c < C; ++c) {
        const int64_t i = at + v * C + c;
        out[i] = to_uint8((float)a[i] * ka + (float)b[i] * kb + off[c]);
      }
  }
}
