/* The LiDAR vehicle half's output layers on an int8 path: see co3sop_nodes/kernels/lidar_output.py.
 *
 * From the encoder's last uint8 volume, per voxel, in one pass over the volume instead of five: its C channels
 * dequantized (plus the background offset where given), the 1x1 feature layer plus its bias, then the 1x1
 * confidence layer on those and its sigmoid. With BF16=1 (an int8 path whose floats are bfloat16, on AVX-512 BF16)
 * rounded where the PyTorch layers round under autocast: the channels and the offset's sum to bfloat16, the feature
 * layer as bfloat16 dot products of channel pairs (vdpbf16ps: the products exact, sums in float32 in the channels'
 * order, as oneDNN's bfloat16 convolution computes them on this CPU), its output rounded to bfloat16, the sigmoid
 * looked up in a table of PyTorch's own for every bfloat16. With BF16=0 (floats in float32, any AVX-512 CPU) in
 * float32: multiply-adds in the channels' order and a vector sigmoid (within float32 rounding of PyTorch's layers,
 * whose sums run in another order). A voxel's output channels are the lanes (C / 16 vectors), a column's voxels are
 * computed a few at a time, and a block of columns is transposed 16 x 16 into the channels-first output, which takes
 * each channel's values of the block in whole vectors. C (a multiple of 32) and BF16 are defined on the command
 * line.
 */
#include <stdint.h>
#include <string.h>

#include <immintrin.h>

#include "bfloat16.h"

#if C % 32
#error "C must be a multiple of 32"
#endif
#define NV (C / 16)   /* float32 vectors of a voxel's channels */
#define BLOCK 96  /* voxels a block of columns holds (a multiple of 16): a column's nz at most */
#define GROUP 3  /* voxels of a column computed together */

/* a 16 x 16 block transposed in registers: at each level d the off-diagonal d x d blocks of each 2d x 2d one trade
 * places (row i's columns with bit d set for row i + d's without), the levels in any order */
static inline __attribute__((always_inline)) void transpose16(__m512 r[16]) {
  const __m512i lane = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
#pragma GCC unroll 4
  for (int d = 8; d >= 1; d /= 2) {
    const __m512i swap = _mm512_xor_si512(lane, _mm512_set1_epi32(d));
    const __mmask16 high = _mm512_test_epi32_mask(lane, _mm512_set1_epi32(d));  /* the columns with bit d set */
#pragma GCC unroll 16
    for (int i = 0; i < 16; ++i) {
      if (i & d) continue;
      const __m512 a = r[i], b = r[i + d];
      r[i] = _mm512_mask_blend_ps(high, a, _mm512_permutexvar_ps(swap, b));
      r[i + d] = _mm512_mask_blend_ps(high, _mm512_permutexvar_ps(swap, a), b);
    }
  }
}

#if BF16
typedef __m512bh weight_t;  /* a feature layer weight vector: bfloat16 pairs of input channels */
#else
typedef __m512 weight_t;    /* a feature layer weight vector: one input channel's weights to 16 outputs */
#endif
#define WEIGHT_ROWS (BF16 ? C / 2 : C)  /* weight vectors per output vector */

/* voxels (x, y, z .. z + n - 1) of a column, n a constant in each call: their chains of multiply-adds interleaved
 * (one voxel's C / 16 chains of dependent products would leave the unit idle for their latency); each voxel's
 * features into voxel[slot + j], its confidence layer's sum (BF16=0: before its sigmoid) into conf[slot + j] */
static inline __attribute__((always_inline)) void voxels(
    const uint8_t *restrict values, int64_t nx, int64_t ny, int64_t x, int64_t y, int64_t z0, int64_t slot, const int n,
    float scale, const float *restrict offset, const weight_t wp[][NV], const __m512 *b, const weight_t *cp,
    float conf_b, const uint16_t *restrict sigmoid, float voxel[][C], float *conf) {
  const __m512 step = _mm512_set1_ps(scale);
#if BF16
  __m512i in_v[GROUP][NV / 2];  /* 32-bit lane i of the k-th vector: channels 32 k + 2 i and 32 k + 2 i + 1 */
#else
  __m512 in_v[GROUP][NV];  /* lane i of the k-th vector: channel 16 k + i */
#endif
  for (int j = 0; j < n; ++j) {
    const int64_t z = z0 + j;
    const uint8_t *in = values + ((z * nx + x) * ny + y) * C;
    for (int k = 0; k < NV / 2; ++k) {
      __m512 lo = _mm512_cvtepi32_ps(_mm512_cvtepu8_epi32(_mm_loadu_si128((const void *)(in + 32 * k))));
      __m512 hi = _mm512_cvtepi32_ps(_mm512_cvtepu8_epi32(_mm_loadu_si128((const void *)(in + 32 * k + 16))));
      lo = _mm512_mul_ps(lo, step);
      hi = _mm512_mul_ps(hi, step);
#if BF16
      if (offset) {  /* dequantized in bfloat16, then the offset added in it */
        const float *off = offset + z * C + 32 * k;
        lo = _mm512_add_ps(_mm512_cvtpbh_ps(_mm512_cvtneps_pbh(lo)), _mm512_loadu_ps(off));
        hi = _mm512_add_ps(_mm512_cvtpbh_ps(_mm512_cvtneps_pbh(hi)), _mm512_loadu_ps(off + 16));
      }
      /* lo's 16 values in the low half, hi's in the high: channel order */
      in_v[j][k] = (__m512i)_mm512_cvtne2ps_pbh(hi, lo);
#else
      if (offset) {
        const float *off = offset + z * C + 32 * k;
        lo = _mm512_add_ps(lo, _mm512_loadu_ps(off));
        hi = _mm512_add_ps(hi, _mm512_loadu_ps(off + 16));
      }
      in_v[j][2 * k] = lo;
      in_v[j][2 * k + 1] = hi;
#endif
    }
  }
  __m512 acc[GROUP][NV];
  for (int j = 0; j < n; ++j)
    for (int v = 0; v < NV; ++v) acc[j][v] = _mm512_setzero_ps();
#pragma GCC unroll 16
  for (int i = 0; i < WEIGHT_ROWS; ++i)
    for (int j = 0; j < n; ++j) {
      /* lane i of the input in every lane, by a permutation: a store and narrow loads back would wait for the
       * store to be forwarded */
      const __m512i lane = _mm512_set1_epi32(i % 16);
#if BF16
      const __m512bh xi = (__m512bh)_mm512_permutexvar_epi32(lane, in_v[j][i / 16]);
      for (int v = 0; v < NV; ++v) acc[j][v] = _mm512_dpbf16_ps(acc[j][v], xi, wp[i][v]);
#else
      const __m512 xi = _mm512_permutexvar_ps(lane, in_v[j][i / 16]);
      for (int v = 0; v < NV; ++v) acc[j][v] = _mm512_fmadd_ps(xi, wp[i][v], acc[j][v]);
#endif
    }
  for (int j = 0; j < n; ++j) {
    __m512 csum = _mm512_setzero_ps();
#if BF16
    /* features rounded to bfloat16, in channel pairs for the confidence layer */
    for (int k = 0; k < NV / 2; ++k) {
      const __m512bh f = _mm512_cvtne2ps_pbh(_mm512_add_ps(acc[j][2 * k + 1], b[2 * k + 1]),
                                             _mm512_add_ps(acc[j][2 * k], b[2 * k]));
      csum = _mm512_dpbf16_ps(csum, f, cp[k]);
      _mm512_storeu_ps(voxel[slot + j] + 32 * k, _mm512_cvtpbh_ps((__m256bh)_mm512_castsi512_si256((__m512i)f)));
      _mm512_storeu_ps(voxel[slot + j] + 32 * k + 16,
                       _mm512_cvtpbh_ps((__m256bh)_mm512_extracti64x4_epi64((__m512i)f, 1)));
    }
    conf[slot + j] = bf16_float(sigmoid[to_bf16(_mm512_reduce_add_ps(csum) + conf_b)]);
#else
    for (int v = 0; v < NV; ++v) {
      const __m512 f = _mm512_add_ps(acc[j][v], b[v]);
      csum = _mm512_fmadd_ps(f, cp[v], csum);
      _mm512_storeu_ps(voxel[slot + j] + 16 * v, f);
    }
    conf[slot + j] = _mm512_reduce_add_ps(csum) + conf_b;
    (void)sigmoid;
#endif
  }
}

#if !BF16
/* 1 / (1 + e^-x) per lane, within a few float32 roundings: e^-x = 2^n e^r with n = round(-x log2 e) and
 * r = -x - n ln 2 (ln 2 in two parts, so r is exact to float32), e^r by its Taylor series to degree 7 on |r| <= 0.35;
 * -x clamped to [-80, 80], where the sigmoid is 1 or below 2e-35, so that e^-x is never subnormal (an Intel core's
 * microcode assist) or infinite */
static inline __m512 sigmoid16(__m512 x) {
  const __m512 t = _mm512_min_ps(_mm512_max_ps(_mm512_sub_ps(_mm512_setzero_ps(), x), _mm512_set1_ps(-80.0f)),
                                 _mm512_set1_ps(80.0f));
  const __m512 n = _mm512_roundscale_ps(_mm512_mul_ps(t, _mm512_set1_ps(1.44269504f)),
                                        _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  __m512 r = _mm512_fnmadd_ps(n, _mm512_set1_ps(0.693145752f), t);  /* ln 2's high part: 16 bits, exact products */
  r = _mm512_fnmadd_ps(n, _mm512_set1_ps(1.42860677e-6f), r);
  __m512 p = _mm512_set1_ps(1.0f / 5040);
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(1.0f / 720));
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(1.0f / 120));
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(1.0f / 24));
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(1.0f / 6));
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(0.5f));
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(1.0f));
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(1.0f));
  const __m512 e = _mm512_scalef_ps(p, n);
  return _mm512_div_ps(_mm512_set1_ps(1.0f), _mm512_add_ps(_mm512_set1_ps(1.0f), e));
}
#endif

/* values (Z, X, Y, C) uint8, voxel (z, x, y) at ((z X + x) Y + y) C (a z-outer volume's channels-last view); scale:
 * a value's step; offset (Z, C) float32, or NULL; w (C, C) the feature layer (out, in) and bias (C,), conf_w (C,)
 * and conf_b the confidence layer (BF16=1: all float32 already rounded to bfloat16); sigmoid (BF16=1): the bfloat16
 * sigmoid of every bfloat16 value, by its bits (65536) -> features (C, X, Y, Z) and confidence (X, Y, Z)
 * float32, for the columns [start, end) of X * Y in (x, y) order */
void lidar_output(const uint8_t *restrict values, int64_t nz, int64_t nx, int64_t ny, float scale,
                  const float *restrict offset, const float *restrict w, const float *restrict bias,
                  const float *restrict conf_w, float conf_b, const uint16_t *restrict sigmoid,
                  float *restrict features, float *restrict confidence, int64_t start, int64_t end) {
#if BF16
  /* the feature layer's weights as bfloat16 pairs of input channels (2i, 2i + 1), a vector per pair and output
   * vector; the confidence layer's likewise over the feature channels */
  __m512bh wp[C / 2][NV];
  __m512bh cp[NV / 2];
  for (int i = 0; i < C / 2; ++i)
    for (int v = 0; v < NV; ++v) {
      uint32_t pairs[16];
      for (int lane = 0; lane < 16; ++lane) {
        const int o = 16 * v + lane;
        pairs[lane] = to_bf16(w[o * C + 2 * i]) | (uint32_t)to_bf16(w[o * C + 2 * i + 1]) << 16;
      }
      wp[i][v] = (__m512bh)_mm512_loadu_si512(pairs);
    }
  for (int v = 0; v < NV / 2; ++v) {
    uint32_t pairs[16];
    for (int lane = 0; lane < 16; ++lane) {
      const int c = 32 * v + 2 * lane;
      pairs[lane] = to_bf16(conf_w[c]) | (uint32_t)to_bf16(conf_w[c + 1]) << 16;
    }
    cp[v] = (__m512bh)_mm512_loadu_si512(pairs);
  }
#else
  /* the feature layer's weights from input channel i, a vector per output vector; the confidence layer's per
   * vector of feature channels */
  __m512 wp[C][NV];
  __m512 cp[NV];
  for (int i = 0; i < C; ++i)
    for (int v = 0; v < NV; ++v) {
      float column[16];
      for (int lane = 0; lane < 16; ++lane) column[lane] = w[(16 * v + lane) * C + i];
      wp[i][v] = _mm512_loadu_ps(column);
    }
  for (int v = 0; v < NV; ++v) cp[v] = _mm512_loadu_ps(conf_w + 16 * v);
#endif
  __m512 b[NV];
  for (int v = 0; v < NV; ++v) b[v] = _mm512_loadu_ps(bias + 16 * v);
  const int64_t plane = nx * ny * nz;  /* a feature channel's values */
  /* the features of a block of columns, voxel by voxel, then transposed 16 x 16 at a time: a channel's values of
   * consecutive columns are consecutive in the output, so each is written in whole vectors (a column's alone would
   * be a few values in each of C planes) */
  float voxel[BLOCK][C] __attribute__((aligned(64))), conf[BLOCK];
  memset(voxel, 0, sizeof voxel);  /* a last block's rows past its voxels are transposed too, and not written */
  memset(conf, 0, sizeof conf);
  int64_t unit = 16;  /* columns whose values fill whole 16-value vectors: 16 / gcd(nz, 16) */
  while (unit > 1 && (unit / 2) * nz % 16 == 0) unit /= 2;
  int64_t per_block = unit * (BLOCK / (unit * nz));  /* blocks at multiples of it: whole cache lines each */
  if (per_block == 0) per_block = nz <= BLOCK ? BLOCK / nz : 1;
  for (int64_t first = start; first < end;) {
    int64_t last = (first / per_block + 1) * per_block;
    last = last < end ? last : end;
    for (int64_t col = first; col < last; ++col) {
      const int64_t x = col / ny, y = col % ny, slot = (col - first) * nz;
      int64_t z = 0;
      for (; z + GROUP <= nz; z += GROUP)
        voxels(values, nx, ny, x, y, z, slot + z, GROUP, scale, offset, wp, b, cp, conf_b, sigmoid, voxel, conf);
      for (; z < nz; ++z)
        voxels(values, nx, ny, x, y, z, slot + z, 1, scale, offset, wp, b, cp, conf_b, sigmoid, voxel, conf);
    }
    const int64_t n = (last - first) * nz, at = first * nz;
    for (int64_t i = 0; i < n; i += 16) {  /* masked at the block's end (a copy loop would become a library call) */
      const __mmask16 m = (__mmask16)(n - i >= 16 ? 0xFFFF : (1u << (n - i)) - 1);
      for (int c = 0; c < C; c += 16) {
        __m512 rows[16];  /* voxels i .. i + 15 (BLOCK is a multiple of 16), channels c .. c + 15 */
        for (int r = 0; r < 16; ++r) rows[r] = _mm512_load_ps(voxel[i + r] + c);
        transpose16(rows);
        for (int r = 0; r < 16; ++r) _mm512_mask_storeu_ps(features + (c + r) * plane + at + i, m, rows[r]);
      }
#if BF16
      _mm512_mask_storeu_ps(confidence + at + i, m, _mm512_loadu_ps(conf + i));
#else
      _mm512_mask_storeu_ps(confidence + at + i, m, sigmoid16(_mm512_loadu_ps(conf + i)));
#endif
    }
    first = last;
  }
}
