/* The voxels of a label grid a viewer can see, as coloured points: see co3sop_nodes/kernels/visible_voxels.py.
 *
 * A voxel is shown when its label is neither EMPTY nor IGNORE, and seen when it is shown and at least one of its six
 * face neighbours is not (outside the grid counts as not shown). `visible_mask` marks them with branch-free byte
 * operations over whole rows (the compiler vectorises them), through a copy of the shown flags padded by one voxel
 * of zeros on every side; `visible_points` then writes one 20-byte record per marked voxel, in C order.
 */
#include <stdint.h>
#include <string.h>

#include "nonzero.h"

/* labels (X, Y, Z); shown and mask: (X+2, Y+2, Z+2) scratch, shown's border zero -> mask's voxels marked (its
 * border too: zero), their count returned. Marking runs over each x-plane as one flat range, the border columns
 * included (a border voxel is not shown, so never marked): long runs the compiler vectorises. */
int64_t visible_mask(const uint8_t *restrict labels, int64_t nx, int64_t ny, int64_t nz, uint8_t *restrict shown,
                     uint8_t *restrict mask) {
  const int64_t sy = nz + 2, sx = (ny + 2) * sy;
  for (int64_t i = 0; i < nx; ++i)
    for (int64_t j = 0; j < ny; ++j) {
      const uint8_t *l = labels + (i * ny + j) * nz;
      uint8_t *s = shown + (i + 1) * sx + (j + 1) * sy + 1;
      for (int64_t k = 0; k < nz; ++k) s[k] = (uint8_t)((l[k] != EMPTY) & (l[k] != IGNORE));
    }
  memset(mask, 0, (size_t)sx);
  memset(mask + (nx + 1) * sx, 0, (size_t)sx);
  int64_t count = 0;
  for (int64_t i = 1; i <= nx; ++i) {
    const int64_t first = i * sx + sy, last = i * sx + (ny + 1) * sy;  /* rows y = 1..ny of the plane */
    memset(mask + i * sx, 0, (size_t)sy);
    memset(mask + last, 0, (size_t)sy);
    uint32_t plane = 0;
    for (int64_t v = first; v < last; ++v) {
      const uint8_t enclosed = shown[v - 1] & shown[v + 1] & shown[v - sy] & shown[v + sy] & shown[v - sx] &
                               shown[v + sx];
      mask[v] = shown[v] & (uint8_t)~enclosed;
      plane += mask[v];
    }
    count += plane;
  }
  return count;
}

struct point {  /* LABEL_POINTS: x, y, z, rgb (packed 0x00RRGGBB read as a float32), label, 3 bytes of zeros */
  float x, y, z;
  uint32_t rgb;
  uint8_t label, pad[3];
};
_Static_assert(sizeof(struct point) == 20, "LABEL_POINTS' itemsize");

/* the marked voxels of `mask` (padded, from visible_mask) -> points (count,): centres cx (X,), cy (Y,), cz (Z,) in
 * float64 (rounded to float32 as NumPy assigns them), colours rgb (256,) per label value */
void visible_points(const uint8_t *restrict labels, const uint8_t *restrict mask, int64_t nx, int64_t ny, int64_t nz,
                    const double *restrict cx, const double *restrict cy, const double *restrict cz,
                    const uint32_t *restrict rgb, struct point *restrict points) {
  const int64_t sy = nz + 2, sx = (ny + 2) * sy;
  int64_t n = 0;
  for (int64_t i = 0; i < nx; ++i)
    for (int64_t j = 0; j < ny; ++j) {
      const uint8_t *m = mask + (i + 1) * sx + (j + 1) * sy + 1;
      const uint8_t *l = labels + (i * ny + j) * nz;
      for (int64_t k = next_nonzero(m, 0, nz); k < nz; k = next_nonzero(m, k + 1, nz)) {  /* most are hidden */
        struct point p = {(float)cx[i], (float)cy[j], (float)cz[k], rgb[l[k]], l[k], {0, 0, 0}};
        memcpy(points + n++, &p, sizeof p);
      }
    }
}
