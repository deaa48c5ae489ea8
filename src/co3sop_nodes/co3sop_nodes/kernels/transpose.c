/* The transposition of a float32 matrix, for moving volumes between channels-first (C, V) and channels-last (V, C)
 * (see co3sop_nodes/kernels/transpose.py), or of a bfloat16 one into float32 (widened exactly as it is read). PyTorch
 * copies a transposed view element by element within tiles, about 2 cycles an element for (32, 24576); here 8x8 blocks are transposed in AVX registers (8 loads, 24 shuffles, 8
 * stores), the edges that do not fill a block element by element. Without AVX every element goes that way.
 */
#include <stdint.h>
#if defined(__AVX__)
#include <immintrin.h>
#endif

static inline float bf16_float(uint16_t b) {
  union { uint32_t u; float f; } x = {(uint32_t)b << 16};
  return x.f;
}

/* out[j][i] = in[i][j] for the rows i in [i0, i1) and columns j in [j0, j1) of in (R x S, row stride s) */
#define ELEMENTS(name, type, read)                                                                               \
  static void name(const type *in, float *out, int64_t r, int64_t s, int64_t i0, int64_t i1, int64_t j0,        \
                   int64_t j1) {                                                                                  \
    for (int64_t j = j0; j < j1; j++)                                                                            \
      for (int64_t i = i0; i < i1; i++) out[j * r + i] = read(in[i * s + j]);                                    \
  }
#define SAME(x) (x)
ELEMENTS(elements, float, SAME)
ELEMENTS(elements_bf16, uint16_t, bf16_float)

#if defined(__AVX__)
static inline __m256 load8(const float *in) { return _mm256_loadu_ps(in); }
#if defined(__AVX2__)
static inline __m256 load8_bf16(const uint16_t *in) {
  const __m256i wide = _mm256_cvtepu16_epi32(_mm_loadu_si128((const __m128i *)in));
  return _mm256_castsi256_ps(_mm256_slli_epi32(wide, 16));
}
#endif

/* the 8x8 block at in (row stride s) into out (row stride r), transposed (inlined per element type) */
#define BLOCK8(name, type, load)                                                           \
  static inline __attribute__((always_inline)) void name(const type *in, int64_t s, float *out, int64_t r) { \
    __m256 a[8];                                                                           \
    for (int k = 0; k < 8; k++) a[k] = load(in + k * s);                                   \
    block8_rows(a, out, r);                                                                \
  }

/* eight rows of 8 in registers -> their transposition, stored at out (row stride r) */
static inline __attribute__((always_inline)) void block8_rows(__m256 a[8], float *out, int64_t r) {
  __m256 b[8];
  for (int k = 0; k < 8; k += 2) {
    b[k] = _mm256_unpacklo_ps(a[k], a[k + 1]);
    b[k + 1] = _mm256_unpackhi_ps(a[k], a[k + 1]);
  }
  for (int k = 0; k < 8; k += 4) {
    a[k] = _mm256_shuffle_ps(b[k], b[k + 2], 0x44);
    a[k + 1] = _mm256_shuffle_ps(b[k], b[k + 2], 0xEE);
    a[k + 2] = _mm256_shuffle_ps(b[k + 1], b[k + 3], 0x44);
    a[k + 3] = _mm256_shuffle_ps(b[k + 1], b[k + 3], 0xEE);
  }
  for (int k = 0; k < 4; k++) {
    _mm256_storeu_ps(out + k * r, _mm256_permute2f128_ps(a[k], a[k + 4], 0x20));
    _mm256_storeu_ps(out + (k + 4) * r, _mm256_permute2f128_ps(a[k], a[k + 4], 0x31));
  }
}
BLOCK8(block8, float, load8)
#if defined(__AVX2__)
BLOCK8(block8_bf16, uint16_t, load8_bf16)
#endif
#endif

/* in (R, S) row-major -> out (S, R) row-major, for the columns [start, end) of in (the rows of out) */
#define TRANSPOSE(name, type, block, each)                                                              \
  void name(const type *in, float *out, int64_t r, int64_t s, int64_t start, int64_t end) {             \
    const int64_t r8 = r - r % 8;                                                                       \
    int64_t j = start;                                                                                  \
    for (; j + 8 <= end; j += 8)                                                                        \
      for (int64_t i = 0; i < r8; i += 8) block(in + i * s + j, s, out + j * r + i, r);                 \
    each(in, out, r, s, 0, r8, j, end);                                                                 \
    each(in, out, r, s, r8, r, start, end);                                                             \
  }
#define TRANSPOSE_ELEMENTS(name, type, each)                                                            \
  void name(const type *in, float *out, int64_t r, int64_t s, int64_t start, int64_t end) {             \
    each(in, out, r, s, 0, r, start, end);                                                              \
  }

#if defined(__AVX__)
TRANSPOSE(transpose, float, block8, elements)
#else
TRANSPOSE_ELEMENTS(transpose, float, elements)
#endif
/* in bfloat16 (R, S) -> out float32 (S, R) */
#if defined(__AVX2__)
TRANSPOSE(transpose_bf16, uint16_t, block8_bf16, elements_bf16)
#else
TRANSPOSE_ELEMENTS(transpose_bf16, uint16_t, elements_bf16)
#endif
