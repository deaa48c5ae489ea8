/* uint8 quantization as PyTorch's with zero point 0: v (already divided by the scale) rounded to nearest even and
 * clamped to [0, 255]. The rounding is the addition's (exact for 0 <= v < 2^23), which the compiler vectorises, where
 * libm's nearbyintf is a call per value. */
#ifndef CO3SOP_QUANTIZE_H
#define CO3SOP_QUANTIZE_H

#include <stdint.h>

static inline uint8_t to_uint8(float v) {
  v = v > 255.0f ? 255.0f : (v > 0.0f ? v : 0.0f);
  return (uint8_t)((v + 0x1p23f) - 0x1p23f);
}

#endif
