/* The voxel sensor's stages 1 and 2 per object, and stage 3 as a per-voxel maximum of label ranks: the compiled
 * path of co3sop_nodes/sim/voxel_sensor.py. Overlap tests use the thresholds Python computed (sim/shapes.py) and
 * the same float64 operations in the same order as the NumPy tests (built with -ffp-contract=off), so a voxel
 * overlaps here exactly when it does there.
 *
 * Threads share the object list through an atomic counter (objects differ in cost by orders of magnitude: a road
 * against a pole), and the rank grid through an atomic maximum: labels do not depend on the thread count.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#define STRIDE 96
enum { BOX = 0, CYLINDER = 1, SPHERE = 2 };
/* Box: centre 0-2, separating axes 3-47 (15 x 3), |axis| sums 48-62, the box's reach per axis 63-77 (inf: no
 * axis), half sizes 78-80, rotation 81-89 (row-major). Cylinder: x, y, z0 + EPS, z1 - EPS, (r - EPS)^2, r^2, z1.
 * Sphere: centre 0-2, (r - EPS)^2, r^2. */

static int overlaps(int32_t kind, const double *p, double cx, double cy, double cz, double half, double eps) {
  if (kind == BOX) {
    const double d0 = p[0] - cx, d1 = p[1] - cy, d2 = p[2] - cz;
    for (int k = 0; k < 15; ++k) {
      const double *a = p + 3 + 3 * k;
      const double reach = half * p[48 + k] + p[63 + k] - eps;
      if (!(fabs(d0 * a[0] + d1 * a[1] + d2 * a[2]) < reach)) return 0;
    }
    return 1;
  }
  if (kind == CYLINDER) {
    if (!(cz + half > p[2] && cz - half < p[3])) return 0;
    const double dx = fmax(fabs(cx - p[0]) - half, 0.0), dy = fmax(fabs(cy - p[1]) - half, 0.0);
    return dx * dx + dy * dy < p[4];
  }
  const double g0 = fmax(fabs(cx - p[0]) - half, 0.0), g1 = fmax(fabs(cy - p[1]) - half, 0.0),
               g2 = fmax(fabs(cz - p[2]) - half, 0.0);
  return g0 * g0 + g1 * g1 + g2 * g2 < p[3];
}

/* z where a downward vertical ray at (x, y) first enters the primitive; NaN where it misses */
static double vertical_entry(int32_t kind, const double *p, double x, double y) {
  if (kind == CYLINDER) return (x - p[0]) * (x - p[0]) + (y - p[1]) * (y - p[1]) < p[5] ? p[6] : NAN;
  if (kind == SPHERE) {
    const double d2 = (x - p[0]) * (x - p[0]) + (y - p[1]) * (y - p[1]);
    return d2 < p[4] ? p[2] + sqrt(p[4] - d2) : NAN;
  }
  const double *h = p + 78, *r = p + 81, o0 = x - p[0], o1 = y - p[1], o2 = -p[2];
  double t_in = -INFINITY, t_out = INFINITY;
  for (int j = 0; j < 3; ++j) {  /* slabs in the box's axes: origin o @ rot, direction +z = row 2 of rot */
    const double o = o0 * r[j] + o1 * r[3 + j] + o2 * r[6 + j], d = r[6 + j];
    if (fabs(d) < 1e-12) {
      if (!(fabs(o) < h[j])) return NAN;
      continue;
    }
    const double t1 = (-h[j] - o) / d, t2 = (h[j] - o) / d;
    t_in = fmax(t_in, fmin(t1, t2));
    t_out = fmin(t_out, fmax(t1, t2));
  }
  return t_in < t_out ? t_out : NAN;  /* rays start at z = 0: t is z */
}

typedef struct {
  const double *origin; double v, eps;
  int64_t nx, ny, nz;
  const int64_t *region;  /* lo x, y, z, hi x, y, z in grid indices */
  int64_t sx, sy, sz;
  uint8_t *visited;
  int64_t *queue, len, cap;
} Object;

static int push(Object *o, int64_t local) {
  if (o->len == o->cap) {
    int64_t cap = o->cap ? 2 * o->cap : 4096;
    int64_t *q = realloc(o->queue, (size_t)cap * sizeof *q);
    if (!q) return 0;
    o->queue = q, o->cap = cap;
  }
  o->queue[o->len++] = local;
  return 1;
}

static double centre(const Object *o, int axis, int64_t i) { return o->origin[axis] + ((double)i + 0.5) * o->v; }

static int object_overlaps(const Object *o, const int32_t *kind, const double *params, int64_t first, int64_t last,
                           int64_t i, int64_t j, int64_t k) {
  const double cx = centre(o, 0, i), cy = centre(o, 1, j), cz = centre(o, 2, k), half = o->v / 2;
  for (int64_t q = first; q < last; ++q)
    if (overlaps(kind[q], params + q * STRIDE, cx, cy, cz, half, o->eps)) return 1;
  return 0;
}

/* a seed (grid indices) of the object if new: marked visited and queued; 0 only when out of memory */
static int seed(Object *o, int64_t i, int64_t j, int64_t k) {
  const int64_t *lo = o->region;
  if (i < lo[0] || i >= lo[3] || j < lo[1] || j >= lo[4] || k < lo[2] || k >= lo[5]) return 1;
  const int64_t local = ((i - lo[0]) * o->sy + (j - lo[1])) * o->sz + (k - lo[2]);
  if (o->visited[local]) return 1;
  o->visited[local] = 1;
  return push(o, local);
}

/* stage 1 for one primitive: the impact voxels of downward traces through the column centres that overlap it;
 * a primitive no trace finds (thinner than a column) is seeded from every voxel of its own box */
static int seed_primitive(Object *o, int32_t kind, const double *p, const int64_t *box) {
  const double half = o->v / 2, z_top = o->origin[2] + o->nz * o->v;
  int64_t found = 0;
  for (int64_t i = box[0]; i < box[3]; ++i)
    for (int64_t j = box[1]; j < box[4]; ++j) {
      const double entry = vertical_entry(kind, p, centre(o, 0, i), centre(o, 1, j));
      if (!(isfinite(entry) && entry > o->origin[2])) continue;
      int64_t k = (int64_t)floor((fmin(entry, z_top) - 1e-4 - o->origin[2]) / o->v);
      k = k < 0 ? 0 : (k >= o->nz ? o->nz - 1 : k);
      if (!overlaps(kind, p, centre(o, 0, i), centre(o, 1, j), centre(o, 2, k), half, o->eps)) continue;
      ++found;
      if (!seed(o, i, j, k)) return 0;
    }
  if (found) return 1;
  for (int64_t i = box[0]; i < box[3]; ++i)
    for (int64_t j = box[1]; j < box[4]; ++j)
      for (int64_t k = box[2]; k < box[5]; ++k)
        if (overlaps(kind, p, centre(o, 0, i), centre(o, 1, j), centre(o, 2, k), half, o->eps) && !seed(o, i, j, k)) return 0;
  return 1;
}

/* stages 1 and 2 for one object, its voxels' ranks raised to `rank`; 0 only when out of memory */
static int grow(Object *o, const int32_t *kind, const double *params, const int64_t *prim_box, int64_t first, int64_t last,
                uint8_t rank, uint8_t *ranks) {
  for (int64_t q = first; q < last; ++q)
    if (!seed_primitive(o, kind[q], params + q * STRIDE, prim_box + 6 * q)) return 0;
  static const int64_t step[6][3] = {{1, 0, 0}, {-1, 0, 0}, {0, 1, 0}, {0, -1, 0}, {0, 0, 1}, {0, 0, -1}};
  for (int64_t head = 0; head < o->len; ++head) {  /* breadth first: the queue is every voxel found, in order */
    const int64_t u = o->queue[head], a = u / (o->sy * o->sz), b = (u / o->sz) % o->sy, c = u % o->sz;
    for (int n = 0; n < 6; ++n) {
      const int64_t x = a + step[n][0], y = b + step[n][1], z = c + step[n][2];
      if (x < 0 || x >= o->sx || y < 0 || y >= o->sy || z < 0 || z >= o->sz) continue;
      const int64_t local = (x * o->sy + y) * o->sz + z;
      if (o->visited[local]) continue;
      o->visited[local] = 1;  /* each voxel is checked once */
      if (object_overlaps(o, kind, params, first, last, x + o->region[0], y + o->region[1], z + o->region[2]) && !push(o, local))
        return 0;
    }
  }
  for (int64_t q = 0; q < o->len; ++q) {
    const int64_t u = o->queue[q], a = u / (o->sy * o->sz), b = (u / o->sz) % o->sy, c = u % o->sz;
    uint8_t *cell = ranks + ((a + o->region[0]) * o->ny + (b + o->region[1])) * o->nz + (c + o->region[2]);
    uint8_t seen = __atomic_load_n(cell, __ATOMIC_RELAXED);
    while (seen < rank && !__atomic_compare_exchange_n(cell, &seen, rank, 1, __ATOMIC_RELAXED, __ATOMIC_RELAXED)) {}
  }
  return 1;
}

/* One worker: objects taken from *next until none is left. grid: origin x, y, z, voxel size, EPS; dims: nx, ny,
 * nz; objects n: primitives [first[i], first[i + 1]), index box region (n, 6), rank; primitives: kind, params
 * (P, STRIDE), index box (P, 6). ranks (nx * ny * nz) holds, per voxel, the highest rank of an object on it (0:
 * none). Returns 0, or -1 when out of memory. */
int annotate_objects(const double *grid, const int64_t *dims, int64_t n, const int64_t *order, const int64_t *first,
                     const int64_t *region, const uint8_t *rank, const int32_t *kind, const double *params,
                     const int64_t *prim_box, uint8_t *ranks, int64_t *next) {
  Object o = {.origin = grid, .v = grid[3], .eps = grid[4], .nx = dims[0], .ny = dims[1], .nz = dims[2]};
  int status = 0;
  for (;;) {
    const int64_t t = __atomic_fetch_add(next, 1, __ATOMIC_RELAXED);
    if (t >= n) break;
    const int64_t i = order[t];
    o.region = region + 6 * i;
    o.sx = o.region[3] - o.region[0], o.sy = o.region[4] - o.region[1], o.sz = o.region[5] - o.region[2];
    if (o.sx <= 0 || o.sy <= 0 || o.sz <= 0) continue;
    o.visited = calloc((size_t)(o.sx * o.sy * o.sz), 1);
    o.len = 0;
    const int ok = o.visited && grow(&o, kind, params, prim_box, first[i], first[i + 1], rank[i], ranks);
    free(o.visited);
    if (!ok) {
      status = -1;
      break;
    }
  }
  free(o.queue);
  return status;
}

/* stage 3's last step: ranks to labels in place, [start, end) */
void ranks_to_labels(uint8_t *grid, const uint8_t *label_of_rank, int64_t start, int64_t end) {
  for (int64_t v = start; v < end; ++v) grid[v] = label_of_rank[grid[v]];
}
