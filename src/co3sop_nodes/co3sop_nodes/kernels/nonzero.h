/* Shared by the kernels that follow the set bytes of a sparse voxel row (included, compiled into each). */
#include <stdint.h>
#include <string.h>

#if defined(__AVX512BW__)
#include <immintrin.h>
#endif

/* The index of the first nonzero byte of row[k, n), or n: while they are all zero (a row of a scan's occupancy,
 * about 1 % set, or of a label grid's visible voxels is mostly such runs), 64 bytes at a time on AVX-512 (the last
 * ones by a masked load), else eight. */
static inline int64_t next_nonzero(const uint8_t *row, int64_t k, int64_t n) {
#if defined(__AVX512BW__)
  for (; k < n; k += 64) {
    const __mmask64 in = n - k >= 64 ? ~(__mmask64)0 : ((__mmask64)1 << (n - k)) - 1;
    const __m512i bytes = _mm512_maskz_loadu_epi8(in, row + k);
    const uint64_t set = _mm512_test_epi8_mask(bytes, bytes);
    if (set) return k + __builtin_ctzll(set);
  }
  return n;
#else
  for (; k + 8 <= n; k += 8) {
    uint64_t word;
    memcpy(&word, row + k, 8);
    if (word) break;
  }
  while (k < n && !row[k]) ++k;
  return k;
#endif
}
