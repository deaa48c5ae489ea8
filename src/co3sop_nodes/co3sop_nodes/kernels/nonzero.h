/* Shared by the kernels that follow the set bytes of a sparse voxel row (included, compiled into each). */
#include <stdint.h>
#include <string.h>

/* The index of the first nonzero byte of row[k, n), or n: eight bytes at a time while they are all zero (a row of
 * a scan's occupancy, about 1 % set, or of a label grid's visible voxels is mostly such words). */
static inline int64_t next_nonzero(const uint8_t *row, int64_t k, int64_t n) {
  for (; k + 8 <= n; k += 8) {
    uint64_t word;
    memcpy(&word, row + k, 8);
    if (word) break;
  }
  while (k < n && !row[k]) ++k;
  return k;
}
