/* Deformable sampling for inference: image to voxel (queries over the cameras' feature maps) and voxel to voxel (the
 * ego's queries over the warped agents' volumes); see co3sop_nodes/kernels/deform.py. The definitions are the
 * attentions' PyTorch paths (deform_attn.sample_2d / sample_3d: grid_sample, zeros outside, align_corners=False,
 * after the softmax of the attention's logits).
 *
 * Values are channels-last, a head's CH channels at a pixel or voxel CH/W contiguous W-lane vectors: each sample
 * is 2^dims corners x CH/W vector multiply-adds into registers, with the attention weight folded into the corner
 * weights. Locations are computed here as the references compute them; the softmax is taken here too, per query
 * and head over at most MAX_TERMS logits: PyTorch's softmax over rows of 8 or 16 costs more than the sampling.
 * Offsets and logits are read as the projections wrote them, float32 or bfloat16 (widened exactly), in one function
 * for each; the agents' volumes too, in the voxel-to-voxel sampler's bfloat16 function (a reduced path's value
 * projection writes them so). CH (channels per head, a multiple of 4) is defined on the command line.
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

/* W = 8 lanes where CH is a multiple of 8, else 4 (CH = 12: `small`'s heads); the sums are the same per channel */
#if CH % 8 == 0
typedef float fv __attribute__((vector_size(32)));
#define NV (CH / 8)
#elif CH % 4 == 0
typedef float fv __attribute__((vector_size(16)));
#define NV (CH / 4)
#else
#error "CH must be a multiple of 4"
#endif
typedef fv fvu __attribute__((aligned(4)));  /* loads and stores at float alignment */
/* a vector's lanes as int32 and as bfloat16 bits (a bfloat16 value's vector widened exactly: its bits << 16) */
typedef int32_t iv __attribute__((vector_size(sizeof(fv))));
typedef uint16_t hv __attribute__((vector_size(sizeof(fv) / 2)));
typedef hv hvu __attribute__((aligned(2), may_alias));

#define MAX_TERMS 256
#define INLINE static inline __attribute__((always_inline))

/* element i of a float32 (bf16 = 0) or bfloat16 (bf16 = 1) array; bf16 is a constant in every inlined copy */
INLINE float load(const void *p, int64_t i, int bf16) {
  if (!bf16) return ((const float *)p)[i];
  const uint32_t bits = (uint32_t)((const uint16_t *)p)[i] << 16;
  float f;
  memcpy(&f, &bits, sizeof f);
  return f;
}

typedef float f8 __attribute__((vector_size(32)));
typedef int32_t i8 __attribute__((vector_size(32)));
/* unaligned views of the kernels' inputs (their elements' alignment; they alias the arrays they read) */
typedef f8 f8u __attribute__((aligned(4), may_alias));
typedef i8 i8u __attribute__((aligned(4), may_alias));
typedef uint16_t u16x8 __attribute__((vector_size(16)));
typedef u16x8 u16x8u __attribute__((aligned(2), may_alias));

/* elements i..i+7 of a float32 or bfloat16 array, as load() widens them */
INLINE f8 load8(const void *p, int64_t i, int bf16) {
  if (!bf16) return *(const f8u *)((const float *)p + i);
  return (f8)(__builtin_convertvector(*(const u16x8u *)((const uint16_t *)p + i), i8) << 16);
}

/* the (x, y) pairs i..i+7 of a float32 or bfloat16 array of pairs, split into their x and their y */
INLINE void load8_pairs(const void *p, int64_t i, int bf16, f8 *x, f8 *y) {
  if (bf16) {  /* a pair's two bfloat16 as one int32: x in its low half */
    const i8 both = *(const i8u *)((const uint16_t *)p + 2 * i);
    *x = (f8)(both << 16), *y = (f8)(both & -65536);
    return;
  }
  const f8 a = *(const f8u *)((const float *)p + 2 * i), b = *(const f8u *)((const float *)p + 2 * i + 8);
  *x = __builtin_shufflevector(a, b, 0, 2, 4, 6, 8, 10, 12, 14);
  *y = __builtin_shufflevector(a, b, 1, 3, 5, 7, 9, 11, 13, 15);
}

/* the (x, y, z) triples i..i+7 of a float32 or bfloat16 array of triples, split into their x, y and z */
INLINE void load8_triples(const void *p, int64_t i, int bf16, f8 *x, f8 *y, f8 *z) {
  const f8 a = load8(p, 3 * i, bf16), b = load8(p, 3 * i + 8, bf16), c = load8(p, 3 * i + 16, bf16);
  *x = __builtin_shufflevector(__builtin_shufflevector(a, b, 0, 3, 6, 9, 12, 15, 0, 0), c, 0, 1, 2, 3, 4, 5, 10, 13);
  *y = __builtin_shufflevector(__builtin_shufflevector(a, b, 1, 4, 7, 10, 13, 0, 0, 0), c, 0, 1, 2, 3, 4, 8, 11, 14);
  *z = __builtin_shufflevector(__builtin_shufflevector(a, b, 2, 5, 8, 11, 14, 0, 0, 0), c, 0, 1, 2, 3, 4, 9, 12, 15);
}

/* floor of 8 lanes in (-1, 2^31): truncation toward zero, less one where that rounded up (negative fractions) */
INLINE i8 floor8(f8 x) {
  const i8 t = __builtin_convertvector(x, i8);
  return t + (__builtin_convertvector(t, f8) > x);  /* a true comparison is -1 */
}

/* exp for x <= 0 (logits minus their maximum), 8 lanes, as Cephes computes expf: x = n ln2 + r with |r| <= ln2 / 2,
 * e^r by its degree-7 polynomial (relative error about 2e-7), times 2^n built in the exponent bits; below -87 (where
 * 2^n leaves the normal floats), -inf and NaN 0, as the reference's underflow. libm's expf, a call per term, cost
 * more than the sampling. */
INLINE f8 exp8(f8 x) {
  const i8 keep = x >= -87.0f;                  /* all ones where x is in range (a vector cast keeps the bits) */
  const f8 lo = (f8)(keep & (i8)x);             /* lanes out of range as 0 here, so their n stays small */
  const f8 round = (f8){0} + 12582912.0f;       /* 1.5 * 2^23: adding and subtracting it rounds to an integer */
  const f8 n = (lo * 1.44269504088896341f + round) - round;
  const f8 r = (lo - n * 0.693359375f) - n * -2.12194440e-4f;
  f8 q = (f8){0} + 1.9875691500e-4f;
  q = q * r + 1.3981999507e-3f;
  q = q * r + 8.3334519073e-3f;
  q = q * r + 4.1665795894e-2f;
  q = q * r + 1.6666665459e-1f;
  q = q * r + 5.0000001201e-1f;
  const f8 e = q * r * r + r + 1.0f;
  const f8 scale = (f8)((__builtin_convertvector(n, i8) + 127) << 23);
  return (f8)(keep & (i8)(e * scale));
}

typedef uint32_t u32x8 __attribute__((vector_size(32)));  /* 8 lanes of uint32: a mask's shift counts */

/* the larger of a and b per lane (b where they are equal or either is NaN) */
INLINE f8 max8(f8 a, f8 b) {
  const i8 more = a > b;
  return (f8)((more & (i8)a) | (~more & (i8)b));
}

/* the attention weights of one query and head into `weights` (MAX_TERMS + 8 floats, 32-byte aligned): softmax over
 * `terms` logits, where `may` (per group of `group` terms; NULL: all) allows, each weight the term's exp times the
 * sum's reciprocal as PyTorch's softmax computes it; returns the sum, 0 where nothing is allowed. group_of: each
 * term's group, 8 to a vector (where terms % 8 == 0 and there are at most 32 groups; else NULL) */
INLINE float softmax(const void *logits, int64_t at, int64_t terms, const uint8_t *may, int64_t group,
                     const u32x8 *group_of, int bf16, float *weights) {
  const int64_t vectors = (terms + 7) / 8;
  f8 *w = (f8 *)weights;
  if (!may && terms % 8 == 0) {  /* a vector at a time: a vector read of scalar writes would wait for them */
    for (int64_t v = 0; v < vectors; ++v) w[v] = load8(logits, at + 8 * v, bf16);
  } else if (group_of) {  /* likewise, each lane allowed by its group's bit of a mask built in a register */
    uint32_t bits = 0;
    for (int64_t g = 0; g < terms / group; ++g) bits |= (uint32_t)(may[g] != 0) << g;
    for (int64_t v = 0; v < vectors; ++v) {
      const i8 allowed = -(i8)((((u32x8){0} + bits) >> group_of[v]) & 1u);
      w[v] = (f8)((allowed & (i8)load8(logits, at + 8 * v, bf16)) | (~allowed & (i8)((f8){0} - INFINITY)));
    }
  } else {
    for (int64_t t = 0; t < terms; ++t) weights[t] = (!may || may[t / group]) ? load(logits, at + t, bf16) : -INFINITY;
    for (int64_t t = terms; t < 8 * vectors; ++t) weights[t] = -INFINITY;
  }
  f8 top = w[0];
  for (int64_t v = 1; v < vectors; ++v) top = max8(w[v], top);
  /* the lanes' maximum in every lane, by halves (exact in any order) */
  top = max8(__builtin_shufflevector(top, top, 4, 5, 6, 7, 0, 1, 2, 3), top);
  top = max8(__builtin_shufflevector(top, top, 2, 3, 0, 1, 6, 7, 4, 5), top);
  top = max8(__builtin_shufflevector(top, top, 1, 0, 3, 2, 5, 4, 7, 6), top);
  const float most = top[0];
  f8 sum = {0};
  for (int64_t v = 0; v < vectors; ++v) {
    w[v] = exp8(w[v] - most);  /* everything disallowed: -inf - -inf, NaN, exp 0 */
    sum += w[v];
  }
  float total = 0.0f;
  for (int j = 0; j < 8; ++j) total += sum[j];
  if (total > 0.0f) {
    const float inverse = 1.0f / total;
    for (int64_t v = 0; v < vectors; ++v) w[v] *= inverse;
  }
  return total;
}

/* values[camera * levels + l]: (Hl, Wl, heads * CH); shapes: (levels, 2) as Hl, Wl; uv: (cameras, Q, 2), each
 * query's projection (x, y in [0, 1]) in each camera; visible: (cameras, Q), nonzero where the camera sees the query;
 * per query: offsets (heads, levels, points, 2) in pixels of the level, logits (heads, levels * points)
 * -> out: (Q, heads * CH), the mean over the cameras that see the query of its samples in each (zeros where none).
 * A query's terms (levels x points) are laid out 8 to a vector: their locations, corners and corner weights are
 * computed a vector at a time, then each corner inside its map adds its CH channels (a map's elements fit int32:
 * deform.py checks). */
INLINE void sample_2d(const float *const *values, const int64_t *shapes, int64_t cameras, int64_t levels,
                      int64_t heads, int64_t points, int64_t queries, const float *restrict uv,
                      const uint8_t *restrict visible, const void *restrict offsets, const void *restrict logits,
                      float *restrict out, int64_t start, int64_t end, int bf16) {
  const int64_t c = heads * CH, terms = levels * points, vectors = (terms + 7) / 8;
  float weights[MAX_TERMS + 8] __attribute__((aligned(32)));  /* terms rounded up to whole vectors */
  /* per term: its level's width and height (as floats and as integers), its offset in pixels */
  f8 cols[MAX_TERMS / 8 + 1], rows[MAX_TERMS / 8 + 1], ox[MAX_TERMS / 8 + 1], oy[MAX_TERMS / 8 + 1];
  i8 icols[MAX_TERMS / 8 + 1], irows[MAX_TERMS / 8 + 1];
  for (int64_t t = 0; t < 8 * vectors; ++t) {
    const int64_t l = t < terms ? t / points : 0;  /* padding: a real level's size, weight 0 */
    icols[t / 8][t % 8] = (int32_t)shapes[2 * l + 1], irows[t / 8][t % 8] = (int32_t)shapes[2 * l];
    cols[t / 8][t % 8] = (float)shapes[2 * l + 1], rows[t / 8][t % 8] = (float)shapes[2 * l];
    ox[t / 8][t % 8] = oy[t / 8][t % 8] = 0.0f;
  }
  /* per term and corner (x0 y0, x0+1 y0, x0 y0+1, x0+1 y0+1): its weight (0 outside its map) and element */
  float cw[4][MAX_TERMS + 8] __attribute__((aligned(32)));
  int32_t at[4][MAX_TERMS + 8] __attribute__((aligned(32)));
  for (int64_t q = start; q < end; ++q) {
    int64_t seen = 0;
    for (int64_t n = 0; n < cameras; ++n) seen += visible[n * queries + q] != 0;
    for (int64_t h = 0; h < heads; ++h) {
      fv acc[NV];
      for (int j = 0; j < NV; ++j) acc[j] = (fv){0};
      if (seen) {
        softmax(logits, (q * heads + h) * terms, terms, NULL, 1, NULL, bf16, weights);
        const int64_t first = (q * heads + h) * terms;
        if (terms % 8 == 0)
          for (int64_t k = 0; k < vectors; ++k) load8_pairs(offsets, first + 8 * k, bf16, &ox[k], &oy[k]);
        else
          for (int64_t t = 0; t < terms; ++t)
            ox[t / 8][t % 8] = load(offsets, 2 * (first + t), bf16), oy[t / 8][t % 8] = load(offsets, 2 * (first + t) + 1, bf16);
      }
      for (int64_t n = 0; n < cameras && seen; ++n) {
        if (!visible[n * queries + q]) continue;
        const float u = uv[2 * (n * queries + q)], v = uv[2 * (n * queries + q) + 1];
        for (int64_t k = 0; k < vectors; ++k) {
          /* the reference's (u + offset / cols) * cols - 0.5 without its division (pixel centres at i + 0.5): the
           * same location up to float rounding */
          const f8 x = (u * cols[k] - 0.5f) + ox[k], y = (v * rows[k] - 0.5f) + oy[k];
          const i8 inside = (x > -1.0f) & (x < cols[k]) & (y > -1.0f) & (y < rows[k]);  /* NaN: outside */
          const f8 sx = (f8)(inside & (i8)x), sy = (f8)(inside & (i8)y);  /* in (-1, size), 0 outside */
          const i8 x0 = floor8(sx), y0 = floor8(sy);
          const f8 ax = sx - __builtin_convertvector(x0, f8), ay = sy - __builtin_convertvector(y0, f8);
          const f8 w = (f8)(inside & (i8)((f8 *)weights)[k]);
          const i8 left = x0 >= 0, right = x0 + 1 < icols[k], top = y0 >= 0, bottom = y0 + 1 < irows[k];
          const i8 row0 = y0 * icols[k] + x0;
          const f8 bx = 1.0f - ax, by = 1.0f - ay;
          *(f8 *)&cw[0][8 * k] = (f8)(left & top & (i8)(w * (bx * by)));
          *(f8 *)&cw[1][8 * k] = (f8)(right & top & (i8)(w * (ax * by)));
          *(f8 *)&cw[2][8 * k] = (f8)(left & bottom & (i8)(w * (bx * ay)));
          *(f8 *)&cw[3][8 * k] = (f8)(right & bottom & (i8)(w * (ax * ay)));
          *(i8 *)&at[0][8 * k] = left & top & (row0 * (int32_t)c);
          *(i8 *)&at[1][8 * k] = right & top & ((row0 + 1) * (int32_t)c);
          *(i8 *)&at[2][8 * k] = left & bottom & ((row0 + icols[k]) * (int32_t)c);
          *(i8 *)&at[3][8 * k] = right & bottom & ((row0 + icols[k] + 1) * (int32_t)c);
        }
        for (int64_t l = 0; l < levels; ++l) {
          const float *map = values[n * levels + l] + h * CH;
          for (int64_t t = l * points; t < (l + 1) * points; ++t)
            for (int k = 0; k < 4; ++k) {
              /* a corner outside the map adds its first pixel times 0: no branch (half the samples of the coarse
               * levels fall outside, unpredictably) */
              const float s = cw[k][t];
              const fvu *src = (const fvu *)(map + at[k][t]);
              for (int j = 0; j < NV; ++j) acc[j] += s * src[j];
            }
        }
      }
      fvu *dst = (fvu *)(out + q * c + h * CH);
      const float mean = seen ? (float)seen : 1.0f;
      for (int j = 0; j < NV; ++j) dst[j] = acc[j] / mean;
    }
  }
}

#define SAMPLE_2D_ARGS                                                                                               \
  const float *const *values, const int64_t *shapes, int64_t cameras, int64_t levels, int64_t heads, int64_t points, \
      int64_t queries, const float *uv, const uint8_t *visible, const void *offsets, const void *logits, float *out,  \
      int64_t start, int64_t end
#define SAMPLE_2D_CALL values, shapes, cameras, levels, heads, points, queries, uv, visible, offsets, logits, out, start, end
void deform_sample_2d(SAMPLE_2D_ARGS) { sample_2d(SAMPLE_2D_CALL, 0); }
void deform_sample_2d_bf16(SAMPLE_2D_ARGS) { sample_2d(SAMPLE_2D_CALL, 1); }

/* The ego's queries over the warped agents' volumes, for queries [start, end); the softmax over a query's allowed
 * agents and points per head.
 *
 * values[a]: (X, Y, Z, heads * CH) channels-last per agent, float32 or (with the projections) bfloat16; dims: X,
 * Y, Z; reference: (Q, 3) in [0, 1];
 * offsets: (Q, heads, agents, points, 3) in voxels; logits: (Q, heads, agents, points)
 * of the attention weights; allowed: (Q, agents), nonzero where the query may attend to the agent (none: it reads
 * nothing) -> out: (Q, heads * CH).
 * As the image sampler: a query's terms (agents x points) 8 to a vector for their locations, corners and weights,
 * a corner outside its volume adding the volume's first voxel times 0 (a volume's elements fit int32: deform.py
 * checks); most of the volumes' few z-layers' samples have a corner outside, unpredictably. A head's samples are
 * one chain of dependent multiply-adds (its sum's order), so HB heads of a query are sampled together, their
 * chains interleaved. */
#define HB 4

/* one query's head h: its terms' attention weights, and per term and corner (x, y, z the bits of the corner's
 * number, z lowest) the corner's weight (0 outside) and element, into cw and at; returns the softmax's sum (0:
 * nothing allowed, cw and at then 0) */
INLINE float head_corners(int64_t q, int64_t h, int64_t heads, int64_t terms, int64_t points, const int64_t *dims,
                          const int32_t *step, int64_t c, const float *restrict reference,
                          const void *restrict offsets, const void *restrict logits, const uint8_t *may,
                          const u32x8 *by_agent, int bf16, float *weights, f8 *ox, f8 *oy, f8 *oz,
                          float cw[8][MAX_TERMS + 8], int32_t at[8][MAX_TERMS + 8]) {
  const int64_t vectors = (terms + 7) / 8;
  const int32_t nx = (int32_t)dims[0], ny = (int32_t)dims[1], nz = (int32_t)dims[2];
  const float total = softmax(logits, (q * heads + h) * terms, terms, may, points, by_agent, bf16, weights);
  if (!(total > 0.0f)) {
    for (int n = 0; n < 8; ++n)
      for (int64_t k = 0; k < vectors; ++k) *(f8 *)&cw[n][8 * k] = (f8){0}, *(i8 *)&at[n][8 * k] = (i8){0};
    return 0.0f;
  }
  /* the reference's (reference + offset / dims) * dims - 0.5 as the query's voxel position plus the offset in
   * voxels: the same location up to float rounding */
  float centre[3];
  for (int d = 0; d < 3; ++d) centre[d] = reference[3 * q + d] * dims[d] - 0.5f;
  const int64_t first = (q * heads + h) * terms;
  if (terms % 8 == 0)
    for (int64_t k = 0; k < vectors; ++k) load8_triples(offsets, first + 8 * k, bf16, &ox[k], &oy[k], &oz[k]);
  else
    for (int64_t t = 0; t < terms; ++t) {
      ox[t / 8][t % 8] = load(offsets, 3 * (first + t), bf16);
      oy[t / 8][t % 8] = load(offsets, 3 * (first + t) + 1, bf16);
      oz[t / 8][t % 8] = load(offsets, 3 * (first + t) + 2, bf16);
    }
  for (int64_t k = 0; k < vectors; ++k) {
    const f8 px = centre[0] + ox[k], py = centre[1] + oy[k], pz = centre[2] + oz[k];
    const i8 inside = (px > -1.0f) & (px < (float)nx) & (py > -1.0f) & (py < (float)ny) & (pz > -1.0f) &
                      (pz < (float)nz);  /* NaN: outside */
    const f8 sx = (f8)(inside & (i8)px), sy = (f8)(inside & (i8)py), sz = (f8)(inside & (i8)pz);
    const i8 x0 = floor8(sx), y0 = floor8(sy), z0 = floor8(sz);  /* sx, sy, sz in (-1, size), 0 outside */
    const f8 ax = sx - __builtin_convertvector(x0, f8), ay = sy - __builtin_convertvector(y0, f8);
    const f8 az = sz - __builtin_convertvector(z0, f8);
    const f8 w = (f8)(inside & (i8)((f8 *)weights)[k]);
    const f8 wx[2] = {w * (1.0f - ax), w * ax}, wy[2] = {1.0f - ay, ay}, wz[2] = {1.0f - az, az};
    const i8 vx[2] = {x0 >= 0, x0 + 1 < nx}, vy[2] = {y0 >= 0, y0 + 1 < ny}, vz[2] = {z0 >= 0, z0 + 1 < nz};
    const i8 base = ((x0 * ny + y0) * nz + z0) * (int32_t)c;
#pragma GCC unroll 8
    for (int n = 0; n < 8; ++n) {
      const int i = n >> 2, j = (n >> 1) & 1, l = n & 1;
      const i8 valid = vx[i] & vy[j] & vz[l];
      *(f8 *)&cw[n][8 * k] = (f8)(valid & (i8)(wx[i] * wy[j] * wz[l]));
      *(i8 *)&at[n][8 * k] = valid & (base + (i * step[0] + j * step[1] + l * step[2]));
    }
  }
  return total;
}

/* heads h0 .. h0 + hb - 1 of every query (hb a constant in each inlined copy: HB where the heads divide by it, else
 * 1); a head whose softmax allowed nothing adds its terms' zero weights times the volume's first voxel, 0 */
INLINE void sample_3d(const void *const *values, const int64_t *dims, int64_t agents, int64_t heads, int64_t points,
                      const float *restrict reference, const void *restrict offsets, const void *restrict logits,
                      const uint8_t *restrict allowed, float *restrict out, int64_t start, int64_t end, int bf16,
                      const int hb) {
  const int64_t c = heads * CH, terms = agents * points;
  const int32_t ny = (int32_t)dims[1], nz = (int32_t)dims[2];
  const int32_t step[3] = {ny * nz * (int32_t)c, nz * (int32_t)c, (int32_t)c};  /* elements per x, y, z */
  float weights[MAX_TERMS + 8] __attribute__((aligned(32)));  /* terms rounded up to whole vectors */
  f8 ox[MAX_TERMS / 8 + 1], oy[MAX_TERMS / 8 + 1], oz[MAX_TERMS / 8 + 1];  /* per term: its offset in voxels */
  for (int64_t k = 0; k <= MAX_TERMS / 8; ++k) ox[k] = oy[k] = oz[k] = (f8){0};
  float cw[HB][8][MAX_TERMS + 8] __attribute__((aligned(32)));  /* per head of the hb: head_corners' */
  int32_t at[HB][8][MAX_TERMS + 8] __attribute__((aligned(32)));
  u32x8 agent_of[MAX_TERMS / 8];  /* each term's agent, for the softmax's mask */
  const u32x8 *by_agent = terms % 8 == 0 && agents <= 32 ? agent_of : NULL;
  for (int64_t t = 0; t < terms; ++t) agent_of[t / 8][t % 8] = (uint32_t)(t / points);
  for (int64_t q = start; q < end; ++q) {
    const uint8_t *may = allowed + q * agents;
    for (int64_t h0 = 0; h0 < heads; h0 += hb) {
      fv acc[HB][NV];
      int any = 0;
      for (int b = 0; b < hb; ++b) {
        for (int j = 0; j < NV; ++j) acc[b][j] = (fv){0};
        any |= head_corners(q, h0 + b, heads, terms, points, dims, step, c, reference, offsets, logits, may,
                            by_agent, bf16, weights, ox, oy, oz, cw[b], at[b]) > 0.0f;
      }
      if (any)
        for (int64_t a = 0; a < agents; ++a) {
          if (!may[a]) continue;
          for (int64_t t = a * points; t < (a + 1) * points; ++t)
#pragma GCC unroll 8
            for (int n = 0; n < 8; ++n)
              for (int b = 0; b < hb; ++b) {
                const float s = cw[b][n][t];
                if (!bf16) {
                  const fvu *src = (const fvu *)((const float *)values[a] + (h0 + b) * CH + at[b][n][t]);
                  for (int j = 0; j < NV; ++j) acc[b][j] += s * src[j];
                } else {
                  const hvu *src = (const hvu *)((const uint16_t *)values[a] + (h0 + b) * CH + at[b][n][t]);
                  for (int j = 0; j < NV; ++j) acc[b][j] += s * (fv)(__builtin_convertvector(src[j], iv) << 16);
                }
              }
        }
      for (int b = 0; b < hb; ++b) {
        fvu *dst = (fvu *)(out + q * c + (h0 + b) * CH);
        for (int j = 0; j < NV; ++j) dst[j] = acc[b][j];
      }
    }
  }
}

#define SAMPLE_3D_ARGS                                                                                                \
  const void *const *values, const int64_t *dims, int64_t agents, int64_t heads, int64_t points,                    \
      const float *reference, const void *offsets, const void *logits, const uint8_t *allowed, float *out,            \
      int64_t start, int64_t end
#define SAMPLE_3D_CALL values, dims, agents, heads, points, reference, offsets, logits, allowed, out, start, end
void deform_sample_3d(SAMPLE_3D_ARGS) {
  if (heads % HB == 0)
    sample_3d(SAMPLE_3D_CALL, 0, HB);
  else
    sample_3d(SAMPLE_3D_CALL, 0, 1);
}
void deform_sample_3d_bf16(SAMPLE_3D_ARGS) {
  if (heads % HB == 0)
    sample_3d(SAMPLE_3D_CALL, 1, HB);
  else
    sample_3d(SAMPLE_3D_CALL, 1, 1);
}
