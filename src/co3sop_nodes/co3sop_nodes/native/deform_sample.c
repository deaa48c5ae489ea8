/* Image-to-voxel deformable sampling for (camera, query) pairs [start, end): see co3sop_nodes/model/deform_kernel.py;
 * the definition is lifting.ImageCrossAttention's PyTorch path (deform_attn.sample_2d: grid_sample, bilinear,
 * zeros outside, align_corners=False).
 *
 * Values are channels-last, (Hl, Wl, heads * CH) per camera and level, so a head's CH channels at a pixel are
 * CH/8 contiguous 8-lane vectors: each sample is 4 corners x CH/8 vector multiply-adds into registers, with the
 * attention weight folded into the corner weights. The sampling location is computed here as the reference
 * does (projected point + offset in pixels / level size). CH (channels per head, a multiple of 8) is defined
 * on the command line.
 */
#include <math.h>
#include <stdint.h>

typedef float f8 __attribute__((vector_size(32)));
typedef f8 f8u __attribute__((aligned(4)));  /* loads and stores at float alignment */
#define NV (CH / 8)

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
      f8 acc[NV];
      for (int j = 0; j < NV; ++j) acc[j] = (f8){0};
      for (int64_t l = 0; l < levels; ++l) {
        const float *map = values[camera[pair] * levels + l] + h * CH;
        const int64_t rows = shapes[2 * l], cols = shapes[2 * l + 1];
        for (int64_t p = 0; p < points; ++p) {
          const int64_t i = ((q * heads + h) * levels + l) * points + p;
          const float lx = u + offsets[2 * i] / (float)cols, ly = v + offsets[2 * i + 1] / (float)rows;
          const float x = lx * cols - 0.5f, y = ly * rows - 0.5f;  /* pixel centres at i + 0.5 */
          if (!(x > -1.0f && x < cols && y > -1.0f && y < rows)) continue;  /* every corner outside (or NaN): zeros */
          const float fx = floorf(x), fy = floorf(y), ax = x - fx, ay = y - fy, w = weights[i];
          const int64_t x0 = (int64_t)fx, y0 = (int64_t)fy;
          const int64_t cx[4] = {x0, x0 + 1, x0, x0 + 1}, cy[4] = {y0, y0, y0 + 1, y0 + 1};
          const float cw[4] = {(1 - ax) * (1 - ay), ax * (1 - ay), (1 - ax) * ay, ax * ay};
          for (int k = 0; k < 4; ++k) {
            if (cx[k] < 0 || cx[k] >= cols || cy[k] < 0 || cy[k] >= rows) continue;
            const f8u *src = (const f8u *)(map + (cy[k] * cols + cx[k]) * c);
            const float s = w * cw[k];
            for (int j = 0; j < NV; ++j) acc[j] += s * src[j];
          }
        }
      }
      f8u *dst = (f8u *)(out + pair * c + h * CH);
      for (int j = 0; j < NV; ++j) dst[j] = acc[j];
    }
  }
}
