/* The transposition of a float32 matrix, for moving volumes between channels-first (C, V) and channels-last (V, C)
 * (see co3sop_nodes/kernels/transpose.py). PyTorch copies a transposed view element by element within tiles, about
 * 2 cycles an element for (32, 24576); here 8x8 blocks are transposed in AVX registers (8 loads, 24 shuffles, 8
 * stores), the edges that do not fill a block element by element. Without AVX every element goes that way.
 */
#include <stdint.h>
#if defined(__AVX__)
#include <immintrin.h>
#endif

/* out[j][i] = in[i][j] for the rows i in [i0, i1) and columns j in [j0, j1) of in (R x S, row stride s) */
static void elements(const float *in, float *out, int64_t r, int64_t s, int64_t i0, int64_t i1, int64_t j0,
                     int64_t j1) {
  for (int64_t j = j0; j < j1; j++)
    for (int64_t i = i0; i < i1; i++) out[j * r + i] = in[i * s + j];
}

#if defined(__AVX__)
/* the 8x8 block at in (row stride s) into out (row stride r), transposed */
static inline void block8(const float *in, int64_t s, float *out, int64_t r) {
  __m256 a[8], b[8];
  for (int k = 0; k < 8; k++) a[k] = _mm256_loadu_ps(in + k * s);
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
#endif

/* in (R, S) row-major -> out (S, R) row-major, for the columns [start, end) of in (the rows of out) */
void transpose(const float *in, float *out, int64_t r, int64_t s, int64_t start, int64_t end) {
#if defined(__AVX__)
  const int64_t r8 = r - r % 8;
  int64_t j = start;
  for (; j + 8 <= end; j += 8)
    for (int64_t i = 0; i < r8; i += 8) block8(in + i * s + j, s, out + j * r + i, r);
  elements(in, out, r, s, 0, r8, j, end);
  elements(in, out, r, s, r8, r, start, end);
#else
  elements(in, out, r, s, 0, r, start, end);
#endif
}
