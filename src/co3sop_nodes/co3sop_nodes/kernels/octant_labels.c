/* The head's full-resolution stage for parent voxels [start, end): see co3sop_nodes/kernels/octant.py.
 *
 * One 16-lane vector per channel holds two parents' 8 octants each (their fine voxels), so every layer is a
 * short sequence of vector multiply-adds kept in registers, fused with the argmax and the label's softmax
 * probability. 16 lanes fill an AVX-512 register; without AVX-512 the compiler splits them over two AVX2 ones
 * (comparisons: `gt`). Compiled per head shape: C1 (channels at 1/2), C2 (at full resolution) and K (classes) are
 * defined on the command line.
 * GCC/Clang vector extensions, no intrinsics: any target compiles it. What bounds it is chains of dependent
 * operations more than their count: the argmax is a tree of pairwise maxima and the softmax's sum is four sums.
 * Sums run in the reference's order per voxel (over input channels), so logits match it to float rounding; with
 * REDUCED=1 (a reduced-precision path, compiled with fused multiply-adds) they round once per multiply-add, the
 * classifier's weights are scaled by log2 e so that the softmax's exp is a power of two, and its series is shorter.
 * With DOT_BF16=1 (bfloat16 or uint8 parents on a CPU with AVX-512 BF16) the three layers' products are bfloat16 dot
 * products of channel pairs (vdpbf16ps, two multiply-adds per lane): weights and hidden activations rounded to
 * bfloat16 as a bfloat16 layer rounds them, sums in float32. uint8 parents are integers, exact in bfloat16.
 */
#include <stdint.h>
#include <string.h>

#include "bfloat16.h"
#if defined(__AVX512F__)
#include <immintrin.h>
#endif

typedef float f16 __attribute__((vector_size(64)));
typedef int32_t i16 __attribute__((vector_size(64)));
typedef f16 f16u __attribute__((aligned(4)));  /* for loads from arrays numpy aligned to less than 64 bytes */

/* parents as the head computed them: float32, bfloat16 (PARENTS_BF16=1: its bits are a float32's upper half), or
 * uint8 (PARENTS_U8=1: an int8 head's quantized values, their scale folded into the transposed convolution's weights) */
#if PARENTS_BF16
typedef uint16_t parent_t;
#elif PARENTS_U8
typedef uint8_t parent_t;
#else
typedef float parent_t;
#endif

#if C1 % 2
#error "C1 must be even: parents' channels are read in pairs"
#endif

/* loops over channels and classes unrolled in full while a layer's vectors fit in registers; a wider head's
 * spill anyway, and unrolling it in full takes the compiler minutes (BENCHMARKS.md) */
#if C2 <= 16
#define UNROLL 64
#else
#define UNROLL 16
#endif
#define PRAGMA(x) _Pragma(#x)
#define UNROLL_BY(n) PRAGMA(GCC unroll n)
#define UNROLLED UNROLL_BY(UNROLL)

static inline f16 select(i16 m, f16 a, f16 b) { return (f16)(((i16)a & m) | ((i16)b & ~m)); }

/* a > b per lane (-1 where true). GCC splits a 16-lane vector's arithmetic over narrower registers but compares
 * lane by lane in scalar code, so without AVX-512 the comparison is made in register-wide parts */
#if defined(__AVX512F__)
static inline i16 gt(f16 a, f16 b) { return a > b; }
#else
#if defined(__AVX__)
#define PART 8
#else
#define PART 4
#endif
typedef float fpart __attribute__((vector_size(4 * PART)));
typedef int32_t ipart __attribute__((vector_size(4 * PART)));
static inline i16 gt(f16 a, f16 b) {
  union { f16 v; fpart p[16 / PART]; } ua = {a}, ub = {b};
  union { i16 v; ipart p[16 / PART]; } out;
  for (int k = 0; k < 16 / PART; ++k) out.p[k] = ua.p[k] > ub.p[k];
  return out.v;
}
#endif

/* the lanes of parent p (half 0; p + 1: half 1), lane = 4 (2 dx + dy) + 2 half + dz as in write_pair */
static const i16 HALF0 = {-1, -1, 0, 0, -1, -1, 0, 0, -1, -1, 0, 0, -1, -1, 0, 0};

/* channels c and c + 1 of parents a (half 0) and b (half 1), each as one vector of their lanes */
#if PARENTS_BF16
/* both channels at once, each lane a bfloat16 pair: c in the low half, c + 1 in the high half (little-endian) */
static inline i16 parent_pairs(const parent_t *a, const parent_t *b) {
  int32_t pa, pb;
  memcpy(&pa, a, 4);
  memcpy(&pb, b, 4);
  return (((i16){0} + pa) & HALF0) | (((i16){0} + pb) & ~HALF0);
}
static inline void parent_lanes(const parent_t *a, const parent_t *b, f16 out[2]) {
  const i16 ab = parent_pairs(a, b);
  out[0] = (f16)(ab << 16);
  out[1] = (f16)(ab & (int32_t)0xFFFF0000);
}
#else
static inline void parent_lanes(const parent_t *a, const parent_t *b, f16 out[2]) {
  for (int k = 0; k < 2; ++k) out[k] = select(HALF0, (f16){0} + a[k], (f16){0} + b[k]);
}
#endif

#if defined(__AVX512F__) && defined(__AVX512BW__) && defined(__AVX512VL__)
/* On AVX-512 a parent's channels are read 16 at a time into one vector of floats, and each channel's lanes are
 * taken from the two parents' vectors by one permutation (rather than a conversion and a broadcast per value) */
#define PARENT_VECTORS 1
#define CHUNKS ((C1 + 15) / 16)
/* channels [16 k, 16 k + 16) of parents a and b as floats, one vector each (masked past C1: nothing read beyond a
 * parent's channels) */
static inline void parent_chunks(const parent_t *a, const parent_t *b, f16 ca[CHUNKS], f16 cb[CHUNKS]) {
  for (int k = 0; k < CHUNKS; ++k) {
    const __mmask16 m = (__mmask16)(C1 - 16 * k >= 16 ? 0xFFFF : (1u << (C1 - 16 * k)) - 1);
#if PARENTS_U8
    ca[k] = (f16)_mm512_cvtepi32_ps(_mm512_cvtepu8_epi32(_mm_maskz_loadu_epi8(m, a + 16 * k)));
    cb[k] = (f16)_mm512_cvtepi32_ps(_mm512_cvtepu8_epi32(_mm_maskz_loadu_epi8(m, b + 16 * k)));
#elif PARENTS_BF16
    ca[k] = (f16)_mm512_slli_epi32(_mm512_cvtepu16_epi32(_mm256_maskz_loadu_epi16(m, a + 16 * k)), 16);
    cb[k] = (f16)_mm512_slli_epi32(_mm512_cvtepu16_epi32(_mm256_maskz_loadu_epi16(m, b + 16 * k)), 16);
#else
    ca[k] = (f16)_mm512_maskz_loadu_ps(m, a + 16 * k);
    cb[k] = (f16)_mm512_maskz_loadu_ps(m, b + 16 * k);
#endif
  }
}
/* channel c of parent a in half 0's lanes and of parent b in half 1's (indices 16 and up: the second vector's) */
static inline f16 parent_channel(const f16 *ca, const f16 *cb, int c) {
  const i16 idx = (i16){0} + c % 16 + (16 & ~HALF0);
  return (f16)_mm512_permutex2var_ps((__m512)ca[c / 16], (__m512i)idx, (__m512)cb[c / 16]);
}
#else
#define PARENT_VECTORS 0
#endif

/* the larger of a and b per lane (either, where equal) */
#if defined(__AVX512F__)
static inline f16 vmax(f16 a, f16 b) { return (f16)_mm512_max_ps((__m512)a, (__m512)b); }
#else
static inline f16 vmax(f16 a, f16 b) { return select(gt(b, a), b, a); }
#endif

#if defined(__AVX512F__)
/* max(v, 0) returns its second operand, 0, where v is NaN or a zero, as the comparison below does */
static inline f16 relu(f16 v) { return (f16)_mm512_max_ps((__m512)v, _mm512_setzero_ps()); }
#else
static inline f16 relu(f16 v) { return (f16)((i16)v & gt(v, (f16){0})); }
#endif

#if DOT_BF16
#if !(PARENTS_BF16 || PARENTS_U8) || C2 % 2
#error "DOT_BF16 needs bfloat16 or uint8 parents and an even C2"
#endif
static inline uint32_t bf16_pair(float lo, float hi) { return to_bf16(lo) | (uint32_t)to_bf16(hi) << 16; }

/* relu(a) and relu(b) as lanes of bfloat16 pairs, a's in the low halves: the conversion puts a's 16 lanes in the
 * low half of the vector and b's in the high half, the permutation interleaves them */
static const uint16_t INTERLEAVE[32] = {0, 16, 1, 17, 2, 18, 3, 19, 4, 20, 5, 21, 6, 22, 7, 23,
                                        8, 24, 9, 25, 10, 26, 11, 27, 12, 28, 13, 29, 14, 30, 15, 31};
static inline __m512bh relu_pairs(f16 a, f16 b) {
  const __m512i both = (__m512i)_mm512_cvtne2ps_pbh((__m512)relu(b), (__m512)relu(a));
  return (__m512bh)_mm512_permutexvar_epi16(_mm512_loadu_si512(INTERLEAVE), both);
}
/* acc + x.lo * w.lo + x.hi * w.hi per lane */
static inline f16 dot(f16 acc, __m512bh x, __m512bh w) { return (f16)_mm512_dpbf16_ps((__m512)acc, x, w); }
static inline __m512bh broadcast(uint32_t pair) { return (__m512bh)_mm512_set1_epi32((int32_t)pair); }

#if PARENTS_U8
/* channels c and c + 1 of parents a (half 0) and b (half 1) as bfloat16 pairs, c in the low half: u8_bf16[v] holds
 * the bits of v in bfloat16 */
static inline i16 parent_pairs(const parent_t *a, const parent_t *b, const uint16_t *u8_bf16) {
  const int32_t pa = u8_bf16[a[0]] | (int32_t)u8_bf16[a[1]] << 16, pb = u8_bf16[b[0]] | (int32_t)u8_bf16[b[1]] << 16;
  return (((i16){0} + pa) & HALF0) | (((i16){0} + pb) & ~HALF0);
}
#define PARENT_PAIRS(a, b) parent_pairs(a, b, u8_bf16)
#else
#define PARENT_PAIRS(a, b) parent_pairs(a, b)
#endif

/* a pointwise layer: out[o] = bias[o] + sum over i of relu(in[i]) w[i][o], pairs[i / 2 * n_out + o] holding the
 * bfloat16 pair w[i][o], w[i + 1][o] (inlined with constant sizes: every vector stays in a register) */
static inline __attribute__((always_inline)) void pointwise_bf16(const f16 *in, int n_in, const uint32_t *pairs,
                                                                 const float *bias, int n_out, f16 *out) {
UNROLLED
  for (int o = 0; o < n_out; ++o) out[o] = (f16){0} + bias[o];
UNROLLED
  for (int i = 0; i < n_in; i += 2) {
    const __m512bh r = relu_pairs(in[i], in[i + 1]);
UNROLLED
    for (int o = 0; o < n_out; ++o) out[o] = dot(out[o], r, broadcast(pairs[i / 2 * n_out + o]));
  }
}
#endif

#if REDUCED
/* Exponents below this are clamped to it: their terms vanish in the softmax's sum, which is at least 1, and they
 * never reach the subnormal floats, each of which costs an Intel core a microcode assist (with the shipped heads'
 * logits, a third of this kernel's time). */
#define EXP_FLOOR -64.0f
#if defined(__AVX512F__) && defined(__AVX512DQ__)
/* 2^d for d <= 0 (logits in base 2): 2^n 2^f with n = floor(d), f = d - n in [0, 1) taken by one instruction
 * (vreduceps), 2^f by its degree-4 minimax polynomial (within 3e-6 relative) and 2^n applied by another (vscalefps,
 * which floors its exponent itself) */
static inline f16 exp_nonpositive(f16 d) {
  d = vmax(d, (f16){0} + EXP_FLOOR);
  const f16 f = (f16)_mm512_reduce_ps((__m512)d, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC);
  const f16 p = 1.0000026f + f * (0.69300383f + f * (0.24144275f + f * (0.05201146f + f * 0.01353417f)));
  return (f16)_mm512_scalef_ps((__m512)p, (__m512)d);
}
#else
/* 2^d for d <= 0 (logits in base 2): 2^n 2^f with n = round(d) (adding 1.5 * 2^23 rounds d and leaves n in the
 * sum's low mantissa bits, which a shift by 23 moves into the exponent), |f| <= 1/2 */
static inline f16 exp_nonpositive(f16 d) {
  const f16 x = vmax(d, (f16){0} + EXP_FLOOR);
  const f16 shifted = x + 12582912.0f;
  const f16 f = x - (shifted - 12582912.0f);  /* 2^f by its degree-4 minimax polynomial, within 3e-6 relative */
  const f16 p = 0.99999928f + f * (0.69312191f + f * (0.24024744f + f * (0.05591722f + f * 0.00956987f)));
  return p * (f16)(((i16)shifted << 23) + 0x3F800000);
}
#endif
#else
/* exp(d) for d <= 0 within ~2e-5 relative (the confidence needs 1/255): 2^(d log2 e) = 2^i 2^f with
 * i = floor, 2^f by its Taylor series to degree 6; below 2^-126 it is clamped (negligible in the sum) */
static inline f16 exp_nonpositive(f16 d) {
  f16 x = d * 1.44269504f;
  x = select(gt(x, (f16){0} - 126.0f), x, (f16){0} - 126.0f);
  i16 t = __builtin_convertvector(x, i16);            /* toward zero */
  i16 i = t + gt(__builtin_convertvector(t, f16), x);  /* floor: a true comparison is -1 */
  f16 f = (x - __builtin_convertvector(i, f16)) * 0.69314718f;
  f16 p = 1.0f + f * (1.0f + f * (0.5f + f * (1.0f / 6 + f * (1.0f / 24 + f * (1.0f / 120 + f * (1.0f / 720))))));
  return p * (f16)((i + 127) << 23);
}
#endif

typedef uint8_t b16 __attribute__((vector_size(16)));

/* A pair's 16 lanes, lane = 4 (2 dx + dy) + 2 half + dz for octant (dx, dy, dz) of parent p + half: for two parents
 * p, p + 1 of one z-row each (dx, dy) column's four fine voxels are four consecutive lanes and four consecutive
 * bytes of the output, written at once. */
static inline void write_pair(uint8_t *restrict out, b16 lanes, int64_t fine, int64_t fz, int64_t fy) {
  uint32_t run[4];
  memcpy(run, &lanes, 16);
  memcpy(out + fine, run, 4);
  memcpy(out + fine + fz, run + 1, 4);
  memcpy(out + fine + fy, run + 2, 4);
  memcpy(out + fine + fy + fz, run + 3, 4);
}

/* parents (X1, Y1, Z1, C1), channels contiguous, parent (x, y, z) at element x sx + y sy + z sz (any layout: the
 * head's reduced path stores z outermost); [start, end) in flat (x, y, z) order; up_w (C1, C2, 16) and up_b (C2, 16):
 * the transposed convolution in lane order (write_pair); point_w (C2 in, C2 out); cls_w (C2, K) -> labels and
 * round(255 p(label)), both (2 X1, 2 Y1, 2 Z1) uint8: each octant written at its fine voxel */
void octant_labels(const parent_t *restrict parents, int64_t sx, int64_t sy, int64_t sz, int64_t y1, int64_t z1,
                   int64_t start, int64_t end,
                   const f16u *restrict up_w, const f16u *restrict up_b, const float *restrict point_w,
                   const float *restrict point_b, const float *restrict cls_w, const float *restrict cls_b,
                   uint8_t *restrict labels, uint8_t *restrict confidence) {
  const int64_t fz = 2 * z1, fy = 2 * y1 * fz;  /* strides of the fine grid along y and x (z: 1) */
#if REDUCED
  float w_cls[C2 * K], b_cls[K];  /* logits in base 2 */
  for (int i = 0; i < C2 * K; ++i) w_cls[i] = cls_w[i] * 1.44269504f;
  for (int q = 0; q < K; ++q) b_cls[q] = cls_b[q] * 1.44269504f;
#else
  const float *w_cls = cls_w, *b_cls = cls_b;
#endif
#if DOT_BF16
  /* the weights as bfloat16 pairs of consecutive input channels: up per lane, the others broadcast */
  i16 up_pairs[C1 / 2 * C2];
  uint32_t point_pairs[C2 / 2 * C2], cls_pairs[C2 / 2 * K];
  for (int c = 0; c < C1; c += 2)
    for (int j = 0; j < C2; ++j)
      for (int lane = 0; lane < 16; ++lane)
        up_pairs[c / 2 * C2 + j][lane] = bf16_pair(up_w[c * C2 + j][lane], up_w[(c + 1) * C2 + j][lane]);
  for (int c = 0; c < C2; c += 2) {
    for (int d = 0; d < C2; ++d)
      point_pairs[c / 2 * C2 + d] = bf16_pair(point_w[c * C2 + d], point_w[(c + 1) * C2 + d]);
    for (int q = 0; q < K; ++q) cls_pairs[c / 2 * K + q] = bf16_pair(w_cls[c * K + q], w_cls[(c + 1) * K + q]);
  }
#if PARENTS_U8
  uint16_t u8_bf16[256];
  for (int v = 0; v < 256; ++v) u8_bf16[v] = to_bf16((float)v);
#endif
#endif
  int64_t px = start / (y1 * z1), py = (start / z1) % y1, pz = start % z1;
  for (int64_t p = start; p < end;) {
    const int paired = p + 1 < end && pz + 1 < z1;  /* else p alone, in both halves */
    const parent_t *xa = parents + px * sx + py * sy + pz * sz, *xb = paired ? xa + sz : xa;
    f16 h[C2], g[C2], logits[K];
UNROLLED
    for (int j = 0; j < C2; ++j) h[j] = up_b[j];
#if DOT_BF16
UNROLLED
    for (int c = 0; c < C1; c += 2) {
      const __m512bh x = (__m512bh)PARENT_PAIRS(xa + c, xb + c);
UNROLLED
      for (int j = 0; j < C2; ++j) h[j] = dot(h[j], x, (__m512bh)up_pairs[c / 2 * C2 + j]);
    }
    pointwise_bf16(h, C2, point_pairs, point_b, C2, g);
    pointwise_bf16(g, C2, cls_pairs, b_cls, K, logits);
#else
#if PARENT_VECTORS
    f16 ca[CHUNKS], cb[CHUNKS];
    parent_chunks(xa, xb, ca, cb);
UNROLLED
    for (int c = 0; c < C1; ++c) {
      const f16 xc = parent_channel(ca, cb, c);
UNROLLED
      for (int j = 0; j < C2; ++j) h[j] += xc * up_w[c * C2 + j];
    }
#else
UNROLLED
    for (int c = 0; c < C1; c += 2) {
      f16 xc[2];
      parent_lanes(xa + c, xb + c, xc);
#pragma GCC unroll 2
      for (int k = 0; k < 2; ++k)
UNROLLED
        for (int j = 0; j < C2; ++j) h[j] += xc[k] * up_w[(c + k) * C2 + j];
    }
#endif
UNROLLED
    for (int d = 0; d < C2; ++d) g[d] = (f16){0} + point_b[d];
UNROLLED
    for (int c = 0; c < C2; ++c) {
      const f16 r = relu(h[c]);
UNROLLED
      for (int d = 0; d < C2; ++d) g[d] += r * point_w[c * C2 + d];
    }
UNROLLED
    for (int q = 0; q < K; ++q) logits[q] = (f16){0} + b_cls[q];
UNROLLED
    for (int d = 0; d < C2; ++d) {
      const f16 r = relu(g[d]);
UNROLLED
      for (int q = 0; q < K; ++q) logits[q] += r * w_cls[d * K + q];
    }
#endif
    /* argmax: at each level the later of two neighbours wins only if strictly greater, so the first maximum wins
     * as in torch's argmax */
    f16 val[K];
    i16 idx[K];
UNROLLED
    for (int q = 0; q < K; ++q) val[q] = logits[q], idx[q] = (i16){0} + q;
#pragma GCC unroll 8
    for (int width = 1; width < K; width *= 2)
UNROLLED
      for (int q = 0; q + width < K; q += 2 * width) {
        const i16 later = gt(val[q + width], val[q]);
        val[q] = vmax(val[q], val[q + width]);
        idx[q] = (later & idx[q + width]) | (~later & idx[q]);
      }
    f16 part[4] = {{0}, {0}, {0}, {0}};
UNROLLED
    for (int q = 0; q < K; ++q) part[q % 4] += exp_nonpositive(logits[q] - val[0]);
    const f16 conf = 255.0f / ((part[0] + part[1]) + (part[2] + part[3])) + 0.5f;  /* the sum >= 1: in [0.5, 255.5] */
    const b16 label8 = __builtin_convertvector(idx[0], b16);
    const b16 conf8 = __builtin_convertvector(__builtin_convertvector(conf, i16), b16);
    const int64_t fine = 2 * (px * fy + py * fz + pz);
    if (paired) {
      write_pair(labels, label8, fine, fz, fy);
      write_pair(confidence, conf8, fine, fz, fy);
    } else {
      for (int lane = 0; lane < 16; lane += (lane & 1) ? 3 : 1) {  /* half 0's lanes: 0, 1, 4, 5, 8, ... */
        const int64_t at = fine + (lane >> 3) * fy + ((lane >> 2) & 1) * fz + (lane & 1);
        labels[at] = label8[lane];
        confidence[at] = conf8[lane];
      }
    }
    const int step = paired ? 2 : 1;
    p += step;
    if ((pz += step) == z1) {
      pz = 0;
      if (++py == y1) py = 0, ++px;
    }
  }
}
