/* The head's full-resolution stage for parent voxels [start, end): see co3sop_nodes/kernels/octant.py.
 *
 * One 16-lane vector per channel holds two parents' 8 octants each (their fine voxels), so every layer is a
 * short sequence of vector multiply-adds kept in registers, fused with the argmax and the label's softmax
 * probability. 16 lanes fill an AVX-512 register (two AVX2 ones elsewhere, as fast as 8 lanes were). Compiled
 * per head shape: C1 (channels at 1/2), C2 (at full resolution) and K (classes) are defined on the command line.
 * GCC/Clang vector extensions, no intrinsics: any target compiles it.
 * Sums run in the reference's order per voxel (over input channels), so logits match it to float rounding; with
 * REDUCED=1 (a reduced-precision path, compiled with fused multiply-adds) they round once per multiply-add and the
 * softmax's exp is a shorter series.
 */
#include <stdint.h>

typedef float f16 __attribute__((vector_size(64)));
typedef int32_t i16 __attribute__((vector_size(64)));
typedef f16 f16u __attribute__((aligned(4)));  /* for loads from arrays numpy aligned to less than 64 bytes */

/* parents as the head computed them: float32, or bfloat16 (PARENTS_BF16=1: its bits are a float32's upper half) */
#if PARENTS_BF16
typedef uint16_t parent_t;
static inline float parent_value(parent_t v) {
  union { uint32_t u; float f; } x = {(uint32_t)v << 16};
  return x.f;
}
#else
typedef float parent_t;
static inline float parent_value(parent_t v) { return v; }
#endif

static inline f16 select(i16 m, f16 a, f16 b) { return (f16)(((i16)a & m) | ((i16)b & ~m)); }
static inline f16 relu(f16 v) { return (f16)((i16)v & (v > 0.0f)); }

#if REDUCED
/* exp(d) for d <= 0 on a reduced-precision path (compiled with fused multiply-adds), within ~5e-6 relative:
 * 2^(d log2 e) = 2^n 2^f with n = round, so |f| <= ln2 / 2 and a degree-5 series suffices; below 2^-126 it is
 * clamped (negligible in the sum) */
static inline f16 exp_nonpositive(f16 d) {
  f16 x = d * 1.44269504f;
  x = select(x > -126.0f, x, (f16){0} - 126.0f);
  const f16 shift = (f16){0} + 12582912.0f;  /* 1.5 * 2^23: adding it rounds to an integer */
  f16 n = (x + shift) - shift;
  f16 f = (x - n) * 0.69314718f;
  f16 p = 1.0f + f * (1.0f + f * (0.5f + f * (1.0f / 6 + f * (1.0f / 24 + f * (1.0f / 120)))));
  return p * (f16)((__builtin_convertvector(n, i16) + 127) << 23);
}
#else
/* exp(d) for d <= 0 within ~2e-5 relative (the confidence needs 1/255): 2^(d log2 e) = 2^i 2^f with
 * i = floor, 2^f by its Taylor series to degree 6; below 2^-126 it is clamped (negligible in the sum) */
static inline f16 exp_nonpositive(f16 d) {
  f16 x = d * 1.44269504f;
  x = select(x > -126.0f, x, (f16){0} - 126.0f);
  i16 t = __builtin_convertvector(x, i16);            /* toward zero */
  i16 i = t + (__builtin_convertvector(t, f16) > x);  /* floor: a true comparison is -1 */
  f16 f = (x - __builtin_convertvector(i, f16)) * 0.69314718f;
  f16 p = 1.0f + f * (1.0f + f * (0.5f + f * (1.0f / 6 + f * (1.0f / 24 + f * (1.0f / 120 + f * (1.0f / 720))))));
  return p * (f16)((i + 127) << 23);
}
#endif

/* parents (N, C1) of a (X1, Y1, Z1) grid in flat order; up_w (C1, C2, 16) and up_b (C2, 16): the transposed
 * convolution, octant (i, j, k) last, twice (a lane per octant of each of two parents); point_w (C2 in, C2 out);
 * cls_w (C2, K) -> labels and round(255 p(label)), both (2 X1, 2 Y1, 2 Z1) uint8: each octant written at its fine
 * voxel */
void octant_labels(const parent_t *restrict parents, int64_t y1, int64_t z1, int64_t start, int64_t end,
                   const f16u *restrict up_w, const f16u *restrict up_b, const float *restrict point_w,
                   const float *restrict point_b, const float *restrict cls_w, const float *restrict cls_b,
                   uint8_t *restrict labels, uint8_t *restrict confidence) {
  for (int64_t p = start; p < end; p += 2) {
    const int64_t pair[2] = {p, p + 1 < end ? p + 1 : p};  /* an odd share's last parent fills both halves */
    const parent_t *xa = parents + pair[0] * C1, *xb = parents + pair[1] * C1;
    f16 h[C2], g[C2], logits[K];
    for (int j = 0; j < C2; ++j) h[j] = up_b[j];
    for (int c = 0; c < C1; ++c) {
      const float a = parent_value(xa[c]), b = parent_value(xb[c]);
      const f16 xc = {a, a, a, a, a, a, a, a, b, b, b, b, b, b, b, b};
      for (int j = 0; j < C2; ++j) h[j] += xc * up_w[c * C2 + j];
    }
    for (int d = 0; d < C2; ++d) g[d] = (f16){0} + point_b[d];
    for (int c = 0; c < C2; ++c) {
      f16 r = relu(h[c]);
      for (int d = 0; d < C2; ++d) g[d] += r * point_w[c * C2 + d];
    }
    for (int q = 0; q < K; ++q) logits[q] = (f16){0} + cls_b[q];
    for (int d = 0; d < C2; ++d) {
      f16 r = relu(g[d]);
      for (int q = 0; q < K; ++q) logits[q] += r * cls_w[d * K + q];
    }
    f16 best = logits[0];
    i16 label = {0};
    for (int q = 1; q < K; ++q) {
      i16 better = logits[q] > best;  /* strictly: the first maximum wins, as in torch's argmax */
      label = (better & q) | (~better & label);
      best = select(better, logits[q], best);
    }
    f16 total = {0};
    for (int q = 0; q < K; ++q) total += exp_nonpositive(logits[q] - best);
    f16 conf = 255.0f / total + 0.5f;  /* total >= 1, so conf in [0.5, 255.5] */
    for (int half = 0; half < 2; ++half) {
      const int64_t q = pair[half], px = q / (y1 * z1), py = (q / z1) % y1, pz = q % z1;
      for (int o = 0; o < 8; ++o) {
        const int64_t fine = ((2 * px + (o >> 2)) * 2 * y1 + 2 * py + ((o >> 1) & 1)) * 2 * z1 + 2 * pz + (o & 1);
        labels[fine] = (uint8_t)label[8 * half + o];
        confidence[fine] = (uint8_t)(int)conf[8 * half + o];
      }
    }
  }
}
