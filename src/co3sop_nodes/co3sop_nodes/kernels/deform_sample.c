/* Image-to-voxel deformable sampling for (camera, query) pairs [start, end): see co3sop_nodes/model/deform_kernel.py;
 * the definition is lifting.ImageCrossAttention's PyTorch path (deform_attn.sample_2d: grid_sample, bilinear,
 * zeros outside, align_corners=False).
 *
 * Values are channels-last, (Hl, Wl, heads * CH) per camera and level, so a head's CH channels at a pixel are
 * CH/W contiguous W-lane vectors: each sample is 4 corners x CH/W vector multiply-adds into registers, with the
 * attention weight folded into the corner weights. The sampling location is computed here as the reference
 * does (projected point + offset in pixels / level size). CH (channels per head, a multiple of 4) is defined
 * on the command line.
 */
#include <math.h>
#include <stdint.h>

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

/* values[camera * levels + l]: (Hl, Wl, heads * CH); shapes: (levels, 2) as Hl, Wl;
 * per pair: its camera, its query and the query's projection uv (x, y in [0, 1]) in that camera;
 * per query: offsets (heads, levels, points, 2) in pixels of the level, attention weights (heads, levels, points)
 * -> out: (pairs, heads * CH) */
void deform_sample_2d(const float *const *values, const int64_t *shapes, int64_t levels, int64_t heads, int64_t points,
                      const int64_t *restrict camera, const int64_t *restrict query, const float *restrict uv,
                      const float *restrict offsets, const float *restrict weights, float *restrict out,
                      int64_t start, int64_t end) {
  const int64_t c = heads * CH;
  for (int64_t pair = start; pair < end; ++pair) {
    const int64_t q = query[pair];
    const float u = uv[2 * pair], v = uv[2 * pair + 1];
    for (int64_t h = 0; h < heads; ++h) {
      fv acc[NV];
      for (int j = 0; j < NV; ++j) acc[j] = (fv){0};
      for (int64_t l = 0; l < levels; ++l) {
        const float *map = values[camera[pair] * levels + l] + h * CH;
        const int64_t rows = shapes[2 * l], cols = shapes[2 * l + 1];
        /* the reference's (u + offset / cols) * cols - 0.5 without its division (pixel centres at i + 0.5): the
         * same location up to float rounding */
        const float u0 = u * cols - 0.5f, v0 = v * rows - 0.5f;
        for (int64_t p = 0; p < points; ++p) {
          const int64_t i = ((q * heads + h) * levels + l) * points + p;
          const float x = u0 + offsets[2 * i], y = v0 + offsets[2 * i + 1];
          if (!(x > -1.0f && x < cols && y > -1.0f && y < rows)) continue;  /* every corner outside (or NaN): zeros */
          const float fx = floorf(x), fy = floorf(y), ax = x - fx, ay = y - fy, w = weights[i];
          const int64_t x0 = (int64_t)fx, y0 = (int64_t)fy;
          const int64_t cx[4] = {x0, x0 + 1, x0, x0 + 1}, cy[4] = {y0, y0, y0 + 1, y0 + 1};
          const float cw[4] = {(1 - ax) * (1 - ay), ax * (1 - ay), (1 - ax) * ay, ax * ay};
          for (int k = 0; k < 4; ++k) {
            if (cx[k] < 0 || cx[k] >= cols || cy[k] < 0 || cy[k] >= rows) continue;
            const fvu *src = (const fvu *)(map + (cy[k] * cols + cx[k]) * c);
            const float s = w * cw[k];
            for (int j = 0; j < NV; ++j) acc[j] += s * src[j];
          }
        }
      }
      fvu *dst = (fvu *)(out + pair * c + h * CH);
      for (int j = 0; j < NV; ++j) dst[j] = acc[j];
    }
  }
}

/* Voxel-to-voxel deformable sampling (the ego's queries over the warped agents' volumes) for queries [start, end);
 * the definition is deform_attn.DeformableAttention3d's PyTorch path (the softmax over a query's allowed agents and
 * points per head, then sample_3d: trilinear grid_sample, zeros outside, align_corners=False). The softmax is taken
 * here, per query and head over at most MAX_TERMS logits: PyTorch's softmax over rows of 8 costs more than the
 * sampling.
 *
 * values[a]: (X, Y, Z, heads * CH) channels-last per agent; dims: X, Y, Z; reference: (Q, 3) in [0, 1];
 * offsets: (Q, heads, agents, points, 3) in voxels; logits: (Q, heads, agents, points)
 * of the attention weights; allowed: (Q, agents), nonzero where the query may attend to the agent (none: it reads
 * nothing) -> out: (Q, heads * CH) */
#define MAX_TERMS 256
void deform_sample_3d(const float *const *values, const int64_t *dims, int64_t agents, int64_t heads, int64_t points,
                      const float *restrict reference, const float *restrict offsets,
                      const float *restrict logits, const uint8_t *restrict allowed, float *restrict out,
                      int64_t start, int64_t end) {
  const int64_t c = heads * CH, nx = dims[0], ny = dims[1], nz = dims[2], terms = agents * points;
  float weights[MAX_TERMS];
  for (int64_t q = start; q < end; ++q)
    for (int64_t h = 0; h < heads; ++h) {
      fv acc[NV];
      for (int j = 0; j < NV; ++j) acc[j] = (fv){0};
      /* the reference's (reference + offset / dims) * dims - 0.5 as the query's voxel position plus the offset in
       * voxels: the same location up to float rounding */
      float centre[3];
      for (int d = 0; d < 3; ++d) centre[d] = reference[3 * q + d] * dims[d] - 0.5f;
      const float *l = logits + (q * heads + h) * terms;
      const uint8_t *may = allowed + q * agents;
      float top = -INFINITY, total = 0.0f;
      for (int64_t a = 0; a < agents; ++a)
        for (int64_t p = 0; p < points && may[a]; ++p) top = fmaxf(top, l[a * points + p]);
      for (int64_t t = 0; t < terms; ++t) {
        weights[t] = may[t / points] ? expf(l[t] - top) : 0.0f;
        total += weights[t];
      }
      for (int64_t a = 0; a < agents && total > 0.0f; ++a) {
        if (!may[a]) continue;
        const float *map = values[a] + h * CH;
        for (int64_t p = 0; p < points; ++p) {
          const float w = weights[a * points + p] / total;
          if (w == 0.0f) continue;
          const float *o = offsets + (((q * heads + h) * agents + a) * points + p) * 3;
          float pos[3];
          for (int d = 0; d < 3; ++d) pos[d] = centre[d] + o[d];
          if (!(pos[0] > -1.0f && pos[0] < nx && pos[1] > -1.0f && pos[1] < ny && pos[2] > -1.0f && pos[2] < nz)) continue;
          const float fx = floorf(pos[0]), fy = floorf(pos[1]), fz = floorf(pos[2]);
          const float ax = pos[0] - fx, ay = pos[1] - fy, az = pos[2] - fz;
          const int64_t x0 = (int64_t)fx, y0 = (int64_t)fy, z0 = (int64_t)fz;
          if (x0 >= 0 && x0 + 1 < nx && y0 >= 0 && y0 + 1 < ny && z0 >= 0 && z0 + 1 < nz) {
            /* all 8 corners inside, most samples: the same sum without a bounds check per corner */
            const float *base = map + ((x0 * ny + y0) * nz + z0) * c;
            const int64_t sx = ny * nz * c, sy = nz * c;
            const float wx[2] = {w * (1 - ax), w * ax}, wy[2] = {1 - ay, ay}, wz[2] = {1 - az, az};
            for (int k = 0; k < 8; ++k) {
              const float s = wx[k >> 2] * wy[(k >> 1) & 1] * wz[k & 1];
              const fvu *src = (const fvu *)(base + (k >> 2) * sx + ((k >> 1) & 1) * sy + (k & 1) * c);
              for (int j = 0; j < NV; ++j) acc[j] += s * src[j];
            }
            continue;
          }
          for (int k = 0; k < 8; ++k) {
            const int64_t x = x0 + (k >> 2), y = y0 + ((k >> 1) & 1), z = z0 + (k & 1);
            if (x < 0 || x >= nx || y < 0 || y >= ny || z < 0 || z >= nz) continue;
            const float s = w * ((k >> 2) ? ax : 1 - ax) * (((k >> 1) & 1) ? ay : 1 - ay) * ((k & 1) ? az : 1 - az);
            const fvu *src = (const fvu *)(map + ((x * ny + y) * nz + z) * c);
            for (int j = 0; j < NV; ++j) acc[j] += s * src[j];
          }
        }
      }
      fvu *dst = (fvu *)(out + q * c + h * CH);
      for (int j = 0; j < NV; ++j) dst[j] = acc[j];
    }
}
