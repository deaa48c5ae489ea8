/* bfloat16 as bits: a float rounded to it (to nearest, ties to even, as PyTorch's and the hardware's conversions
 * round finite values), and widened back (exactly). */
#ifndef CO3SOP_BFLOAT16_H
#define CO3SOP_BFLOAT16_H

#include <stdint.h>

static inline uint16_t to_bf16(float f) {
  union { float f; uint32_t u; } x = {f};
  return (uint16_t)((x.u + 0x7FFFu + ((x.u >> 16) & 1u)) >> 16);
}

static inline float bf16_float(uint16_t b) {
  union { uint32_t u; float f; } x = {(uint32_t)b << 16};
  return x.f;
}

#endif
