/* A float32 channels-last volume quantized to a z-outer uint8 one: see co3sop_nodes/kernels/quantize_volume.py.
 *
 * src (B, X, Y, Z, C) -> dst (B, Z, X, Y, C): round(src * k + zero) to nearest even, clamped to [0, 255], each
 * multiply and add rounded as PyTorch's (the source compiles without contraction), for the (b, z) planes
 * [start, end) of B * Z. C (channels) is defined on the command line.
 */
#include <stdint.h>

#include "quantize.h"

void quantize_z_outer(const float *restrict src, float k, float zero, uint8_t *restrict dst, int64_t nxy, int64_t nz,
                      int64_t start, int64_t end) {
  for (int64_t plane = start; plane < end; ++plane) {
    const float *in = src + ((plane / nz) * nxy * nz + plane % nz) * C;
    uint8_t *out = dst + plane * nxy * C;
    for (int64_t v = 0; v < nxy; ++v)
      for (int c = 0; c < C; ++c) out[v * C + c] = to_uint8(in[v * nz * C + c] * k + zero);
  }
}
