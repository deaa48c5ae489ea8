/* The voxels of a label grid a viewer can see, as coloured points: see co3sop_nodes/kernels/visible_voxels.py.
 *
 * A voxel is shown when its label is neither EMPTY nor IGNORE, and seen when it is shown and at least one of its six
 * face neighbours is not (outside the grid counts as not shown). One pass over the x-planes: the shown flags of
 * three planes (x - 1, x, x + 1), each padded by one voxel of zeros, rotate through a scratch of a few tens of
 * kilobytes that stays in cache, so a 51.2 m grid's 1.6 million voxels are read once, not through copies of it.
 * Marking runs over a plane as one flat range with branch-free byte operations (vectorised), then each marked
 * voxel's 20-byte record is written, in C order.
 */
#include <stdint.h>
#include <string.h>

#include "nonzero.h"

struct point { /* LABEL_POINTS: x, y, z, rgb (packed 0x00RRGGBB read as a float32), label, 3 bytes of zeros */
  float x, y, z;
  uint32_t rgb;
  uint8_t label, pad[3];
};
_Static_assert(sizeof(struct point) == 20, "LABEL_POINTS' itemsize");

/* plane x of labels (X, Y, Z) -> its shown flags in `shown` ((Y+2) x (Z+2), border zero), or all zeros outside;
 * `flat` (Y x Z) scratch: the flags are computed over the plane as one flat range (vectorised), then placed */
static void shown_plane(const uint8_t *restrict labels, int64_t x, int64_t nx, int64_t ny, int64_t nz,
                        uint8_t *restrict flat, uint8_t *restrict shown) {
  const int64_t sy = nz + 2;
  if (x < 0 || x >= nx) {
    memset(shown, 0, (size_t)((ny + 2) * sy));
    return;
  }
  const uint8_t *l = labels + x * ny * nz;
  for (int64_t v = 0; v < ny * nz; ++v) flat[v] = (uint8_t)((l[v] != EMPTY) & (l[v] != IGNORE));
  for (int64_t j = 0; j < ny; ++j) memcpy(shown + (j + 1) * sy + 1, flat + j * nz, (size_t)nz);
}

/* labels (X, Y, Z) -> the seen voxels as points (room for X * Y * Z of them), their count returned; scratch: 5 x
 * (Y+2) x (Z+2) bytes, zeroed by the caller (three planes' shown flags, one plane's marks, one plane's flags); centres
 * cx (X,), cy (Y,), cz (Z,) in float64 (rounded to float32 as NumPy assigns them), colours rgb (256,) per label
 * value */
int64_t visible_points(const uint8_t *restrict labels, int64_t nx, int64_t ny, int64_t nz, uint8_t *restrict scratch,
                       const double *restrict cx, const double *restrict cy, const double *restrict cz,
                       const uint32_t *restrict rgb, struct point *restrict points) {
  const int64_t sy = nz + 2, plane = (ny + 2) * sy;
  uint8_t *planes[3] = {scratch, scratch + plane, scratch + 2 * plane}, *mask = scratch + 3 * plane;
  uint8_t *flat = scratch + 4 * plane;
  shown_plane(labels, -1, nx, ny, nz, flat, planes[0]);
  shown_plane(labels, 0, nx, ny, nz, flat, planes[1]);
  int64_t n = 0;
  for (int64_t i = 0; i < nx; ++i) {
    const uint8_t *before = planes[i % 3], *here = planes[(i + 1) % 3];
    uint8_t *after = planes[(i + 2) % 3];
    shown_plane(labels, i + 1, nx, ny, nz, flat, after);
    /* rows y = 1..Y of the plane, border columns included (never shown, so never marked) */
    for (int64_t v = sy; v < (ny + 1) * sy; ++v) {
      const uint8_t enclosed = here[v - 1] & here[v + 1] & here[v - sy] & here[v + sy] & before[v] & after[v];
      mask[v] = here[v] & (uint8_t)~enclosed;
    }
    const float x = (float)cx[i];
    for (int64_t j = 0; j < ny; ++j) {
      const float y = (float)cy[j];
      const uint8_t *m = mask + (j + 1) * sy + 1;
      const uint8_t *l = labels + (i * ny + j) * nz;
      for (int64_t k = next_nonzero(m, 0, nz); k < nz; k = next_nonzero(m, k + 1, nz)) { /* most are hidden */
        struct point *p = points + n++;
        p->x = x, p->y = y, p->z = (float)cz[k], p->rgb = rgb[l[k]], p->label = l[k];
        memset(p->pad, 0, sizeof p->pad);
      }
    }
  }
  return n;
}
