/* float32 <-> IEEE half (float16) conversions of a feature volume: see co3sop_nodes/kernels/half_float.py.
 *
 * GCC's and Clang's _Float16 converts with the CPU's instructions where it has them (F16C, AVX-512) but one value
 * at a time; with F16C eight at a time by its intrinsics, which are the same instructions, rounding as the
 * processor's mode says (to nearest even, as numpy's astype; NaN and infinity kept, subnormals exact).
 *
 * The planes variants read or write a volume's halves byte-shuffled: every value's low byte, then every value's
 * high byte (n values: 2n bytes), the layout the feature codec's shuffle-zstd compresses.
 */
#include <stdint.h>
#include <string.h>

#if defined(__F16C__)
#include <immintrin.h>
#endif

void to_half(const float *restrict in, _Float16 *restrict out, int64_t start, int64_t end) {
  int64_t i = start;
#if defined(__F16C__)
  for (; i + 8 <= end; i += 8)
    _mm_storeu_si128((__m128i *)(out + i), _mm256_cvtps_ph(_mm256_loadu_ps(in + i), _MM_FROUND_CUR_DIRECTION));
#endif
  for (; i < end; ++i) out[i] = (_Float16)in[i];
}

void from_half(const _Float16 *restrict in, float *restrict out, int64_t start, int64_t end) {
  int64_t i = start;
#if defined(__F16C__)
  for (; i + 8 <= end; i += 8) _mm256_storeu_ps(out + i, _mm256_cvtph_ps(_mm_loadu_si128((const __m128i *)(in + i))));
#endif
  for (; i < end; ++i) out[i] = (float)in[i];
}

/* value i's half: low byte at out[i], high byte at out[n + i] */
void to_half_planes(const float *restrict in, uint8_t *restrict out, int64_t n, int64_t start, int64_t end) {
  int64_t i = start;
#if defined(__F16C__)
  /* the even bytes (low) into the vector's first 8, the odd (high) into its last 8 */
  const __m128i split = _mm_setr_epi8(0, 2, 4, 6, 8, 10, 12, 14, 1, 3, 5, 7, 9, 11, 13, 15);
  for (; i + 8 <= end; i += 8) {
    const __m128i h = _mm_shuffle_epi8(_mm256_cvtps_ph(_mm256_loadu_ps(in + i), _MM_FROUND_CUR_DIRECTION), split);
    _mm_storel_epi64((__m128i *)(out + i), h);
    _mm_storel_epi64((__m128i *)(out + n + i), _mm_unpackhi_epi64(h, h));
  }
#endif
  for (; i < end; ++i) {
    const _Float16 h = (_Float16)in[i];
    uint16_t bits;
    memcpy(&bits, &h, 2);
    out[i] = (uint8_t)bits, out[n + i] = (uint8_t)(bits >> 8);
  }
}

/* to_half_planes' inverse: value i from its low byte in[i] and high byte in[n + i] */
void from_half_planes(const uint8_t *restrict in, float *restrict out, int64_t n, int64_t start, int64_t end) {
  int64_t i = start;
#if defined(__F16C__)
  for (; i + 8 <= end; i += 8) {
    const __m128i h = _mm_unpacklo_epi8(_mm_loadl_epi64((const __m128i *)(in + i)),
                                        _mm_loadl_epi64((const __m128i *)(in + n + i)));
    _mm256_storeu_ps(out + i, _mm256_cvtph_ps(h));
  }
#endif
  for (; i < end; ++i) {
    const uint16_t bits = (uint16_t)(in[i] | in[n + i] << 8);
    _Float16 h;
    memcpy(&h, &bits, 2);
    out[i] = (float)h;
  }
}
