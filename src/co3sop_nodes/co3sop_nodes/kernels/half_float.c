/* float32 <-> IEEE half (float16) conversions of a feature volume: see co3sop_nodes/kernels/half_float.py.
 *
 * GCC's and Clang's _Float16 converts with the CPU's instructions where it has them (F16C, AVX-512), a vector
 * at a time, rounding to nearest even as numpy's astype does (NaN and infinity kept, subnormals exact).
 */
#include <stdint.h>

void to_half(const float *restrict in, _Float16 *restrict out, int64_t start, int64_t end) {
  for (int64_t i = start; i < end; ++i) out[i] = (_Float16)in[i];
}

void from_half(const _Float16 *restrict in, float *restrict out, int64_t start, int64_t end) {
  for (int64_t i = start; i < end; ++i) out[i] = (float)in[i];
}
