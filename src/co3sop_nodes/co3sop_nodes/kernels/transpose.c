/* The transposition of a float32 matrix, for moving volumes between channels-first (C, V) and channels-last (V, C)
 * (see co3sop_nodes/kernels/transpose.py), or of a bfloat16 one into float32 (widened exactly as it is read). PyTorch
 * copies a transposed view element by element within tiles, about 2 cycles an element for (32, 24576); here 8x8
 * blocks are transposed in AVX registers (8 loads, 24 shuffles, 8 stores), the edges that do not fill a block element
 * by element. Without AVX (for bfloat16: AVX2) every element goes that way.
 */
#include <stdint.h>
#if defined(__AVX__)
#include <immintrin.h>
#endif

#include "bfloat16.h"

#if defined(__AVX2__)
#define BLOCKS_BF16 1
#else
#define BLOCKS_BF16 0
#endif

/* element k of in: a float32 matrix's, or where `bf16` a bfloat16 one's widened */
static inline float element(const void *in, const int bf16, int64_t k) {
  return bf16 ? bf16_float(((const uint16_t *)in)[k]) : ((const float *)in)[k];
}

/* out[j][i] = in[i][j] for the rows i in [i0, i1) and columns j in [j0, j1) of in (R x S, row stride s) */
static inline void elements(const void *in, const int bf16, float *out, int64_t r, int64_t s, int64_t i0, int64_t i1,
                            int64_t j0, int64_t j1) {
  for (int64_t j = j0; j < j1; j++)
    for (int64_t i = i0; i < i1; i++) out[j * r + i] = element(in, bf16, i * s + j);
}

#if defined(__AVX__)
/* 8 consecutive elements from element k of in, as float32 */
static inline __m256 load8(const void *in, const int bf16, int64_t k) {
#if BLOCKS_BF16
  if (bf16) {
    const __m256i wide = _mm256_cvtepu16_epi32(_mm_loadu_si128((const __m128i *)((const uint16_t *)in + k)));
    return _mm256_castsi256_ps(_mm256_slli_epi32(wide, 16));
  }
#endif
  return _mm256_loadu_ps((const float *)in + k);
}

/* the 8x8 block at element k of in (row stride s) into out (row stride r), transposed */
static inline void block8(const void *in, const int bf16, int64_t k, int64_t s, float *out, int64_t r) {
  __m256 a[8], b[8];
  for (int q = 0; q < 8; q++) a[q] = load8(in, bf16, k + q * s);
  for (int q = 0; q < 8; q += 2) {
    b[q] = _mm256_unpacklo_ps(a[q], a[q + 1]);
    b[q + 1] = _mm256_unpackhi_ps(a[q], a[q + 1]);
  }
  for (int q = 0; q < 8; q += 4) {
    a[q] = _mm256_shuffle_ps(b[q], b[q + 2], 0x44);
    a[q + 1] = _mm256_shuffle_ps(b[q], b[q + 2], 0xEE);
    a[q + 2] = _mm256_shuffle_ps(b[q + 1], b[q + 3], 0x44);
    a[q + 3] = _mm256_shuffle_ps(b[q + 1], b[q + 3], 0xEE);
  }
  for (int q = 0; q < 4; q++) {
    _mm256_storeu_ps(out + q * r, _mm256_permute2f128_ps(a[q], a[q + 4], 0x20));
    _mm256_storeu_ps(out + (q + 4) * r, _mm256_permute2f128_ps(a[q], a[q + 4], 0x31));
  }
}
#endif

/* in (R, S) row-major -> out (S, R) row-major, for the columns [start, end) of in (the rows of out); inlined with
 * `bf16` a constant by each caller below */
static inline __attribute__((always_inline)) void transpose_part(const void *in, const int bf16, float *out,
                                                                  int64_t r, int64_t s, int64_t start, int64_t end) {
#if defined(__AVX__)
  if (!bf16 || BLOCKS_BF16) {
    const int64_t r8 = r - r % 8;
    int64_t j = start;
    for (; j + 8 <= end; j += 8)
      for (int64_t i = 0; i < r8; i += 8) block8(in, bf16, i * s + j, s, out + j * r + i, r);
    elements(in, bf16, out, r, s, 0, r8, j, end);
    elements(in, bf16, out, r, s, r8, r, start, end);
    return;
  }
#endif
  elements(in, bf16, out, r, s, 0, r, start, end);
}

void transpose(const float *in, float *out, int64_t r, int64_t s, int64_t start, int64_t end) {
  transpose_part(in, 0, out, r, s, start, end);
}

/* in bfloat16 (R, S) -> out float32 (S, R) */
void transpose_bf16(const uint16_t *in, float *out, int64_t r, int64_t s, int64_t start, int64_t end) {
  transpose_part(in, 1, out, r, s, start, end);
}
