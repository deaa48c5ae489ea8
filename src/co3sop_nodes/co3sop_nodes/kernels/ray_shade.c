/* The ray casts and the work around them: rays prepared for Embree, cast, first hits located, camera pixels
 * shaded (see co3sop_nodes/sim/ray_kernel.py).
 *
 * The reference is NumPy on trimesh's intersector (sim/raycast.py `RayScene.cast`, sim/camera.py `render` and
 * `shade`); every value here is the same float64 operation in the same order (compiled without FMA contraction),
 * and Embree gets the same float32 rays on a scene built as trimesh builds its own, so hits and images are
 * bit-identical to it: tests compare both on fixed and random scenes.
 *
 * Embree is the library embreex loaded (the one trimesh's intersector uses); its entry point is passed in as a
 * function pointer, so this file needs no Embree header or link flag. Rays are set up as embreex's
 * EmbreeScene.run sets them (tnear 0, tfar 1e37, every mask bit, no flags), 8 neighbouring rays per call
 * (rtcIntersect8) where embreex casts one at a time: the same triangle is hit (tested).
 *
 * Exported functions take [start, end) ranges, or a part of `parts` interleaved blocks, so that threads can split
 * the rays (ctypes releases the GIL).
 */
#include <math.h>
#include <stdint.h>

/* Python's floor division and modulo (numpy's for int64 and float64): the result has the divisor's sign */
static inline int64_t py_mod_i(int64_t a, int64_t m) { int64_t r = a % m; return r < 0 ? r + m : r; }
static inline double py_mod_f(double a, double m) { double r = fmod(a, m); return (r != 0 && r < 0) ? r + m : r; }
static inline double clip01(double x) { return x < 0 ? 0 : (x > 1 ? 1 : x); }

/* direction d -> unit u as trimesh.util.unitize computes it (norm from a dot with ones, times its reciprocal);
 * the float32 ray Embree casts: origin o shifted and scaled into the BVH's frame, unit direction */
static inline void prepare_ray(const double *o, const double *d, const double *shift, double scale, double *u,
                               float *org32, float *dir32) {
  double norm = sqrt((d[0] * d[0] + d[1] * d[1]) + d[2] * d[2]);
  if (norm > 1e-13) norm = 1.0 / norm;
  for (int k = 0; k < 3; ++k) {
    u[k] = d[k] * norm;
    dir32[k] = (float)u[k];
    org32[k] = (float)((o[k] - shift[k]) * scale);
  }
}

/* origins advance by o_stride doubles per ray (0: one origin for every ray) */
void prepare(const double *restrict origins, int64_t o_stride, const double *restrict dirs, const double *restrict shift,
             double scale, double *restrict unit, float *restrict org32, float *restrict dir32, int64_t start, int64_t end) {
  for (int64_t i = start; i < end; ++i)
    prepare_ray(origins + o_stride * i, dirs + 3 * i, shift, scale, unit + 3 * i, org32 + 3 * i, dir32 + 3 * i);
}

/* Embree's triangle p (-1: none) for the ray from o along d (unit u) -> the hit as trimesh locates it (the ray's
 * plane intersection with the triangle's plane, unit direction; near-parallel rays miss) and RayScene.cast
 * reports it: distance along d (inf: none or beyond max_distance), owner object (-1), normal facing the ray (0),
 * point (origin) */
static inline void finish_ray(const double *o, const double *d, const double *u, int32_t p, const double *plane_o,
                              const double *plane_n, const int64_t *face_owner, double max_distance, double *distance,
                              int64_t *owner, double *normal, double *point) {
  double dist = INFINITY, n[3] = {0, 0, 0};
  int64_t who = -1;
  if (p >= 0) {
    const double *po = plane_o + 3 * (int64_t)p, *pn = plane_n + 3 * (int64_t)p;
    const double ori = ((po[0] - o[0]) * pn[0] + (po[1] - o[1]) * pn[1]) + (po[2] - o[2]) * pn[2];
    const double den = (u[0] * pn[0] + u[1] * pn[1]) + u[2] * pn[2];
    if (fabs(den) > 1e-5) {
      const double t = ori / den;
      double loc[3];
      for (int k = 0; k < 3; ++k) loc[k] = u[k] * t + o[k];
      dist = ((loc[0] - o[0]) * d[0] + (loc[2] - o[2]) * d[2]) + (loc[1] - o[1]) * d[1];  /* np.einsum's order */
      const int flip = ((pn[0] * d[0] + pn[2] * d[2]) + pn[1] * d[1]) > 0;
      for (int k = 0; k < 3; ++k) n[k] = flip ? -pn[k] : pn[k];
      who = face_owner[p];
      if (dist > max_distance) { dist = INFINITY; who = -1; n[0] = n[1] = n[2] = 0; }
    }
  }
  *distance = dist;
  *owner = who;
  const double along = isfinite(dist) ? dist : 0;
  for (int k = 0; k < 3; ++k) {
    normal[k] = n[k];
    point[k] = o[k] + along * d[k];
  }
}

void finish(const double *restrict origins, int64_t o_stride, const double *restrict dirs, const double *restrict unit,
            const int32_t *restrict prim, const double *restrict plane_o, const double *restrict plane_n,
            const int64_t *restrict face_owner, double max_distance, double *restrict distance, int64_t *restrict owner,
            double *restrict normal, double *restrict point, int64_t start, int64_t end) {
  for (int64_t i = start; i < end; ++i)
    finish_ray(origins + o_stride * i, dirs + 3 * i, unit + 3 * i, prim[i], plane_o, plane_n, face_owner, max_distance,
               distance + i, owner + i, normal + 3 * i, point + 3 * i);
}

/* Embree 4's RTCRayHit8 (include/embree4/rtcore_ray.h) up to the geometry ids; the instance ids that follow have
 * as many levels as the library was built with, so room for far more than any build uses is left */
typedef struct __attribute__((aligned(32))) {
  float org_x[8], org_y[8], org_z[8], tnear[8], dir_x[8], dir_y[8], dir_z[8], time[8], tfar[8];
  uint32_t mask[8], id[8], flags[8];
  float ng_x[8], ng_y[8], ng_z[8], u[8], v[8];
  uint32_t prim_id[8], geom_id[8];
  uint32_t instance[64][8];
} RayHit8;

typedef void (*Intersect8)(const int *valid, void *scene, RayHit8 *rayhit, void *args);

#define INVALID 0xFFFFFFFFu

/* n float32 rays (origins org, directions dir: 3 per ray, in the scene's units) -> prim: the triangle each hits
 * first, -1 for none */
static void cast_rays(void *scene, Intersect8 intersect, const float *org, const float *dir, int32_t *prim, int64_t n) {
  RayHit8 rh;
  int valid[8];
  for (int64_t first = 0; first < n; first += 8) {
    const int64_t m = n - first < 8 ? n - first : 8;
    for (int k = 0; k < 8; ++k) {
      const int64_t i = first + (k < m ? k : 0);  /* lanes past the end repeat a ray, masked off */
      const float *o = org + 3 * i, *d = dir + 3 * i;
      valid[k] = k < m ? -1 : 0;
      rh.org_x[k] = o[0], rh.org_y[k] = o[1], rh.org_z[k] = o[2], rh.tnear[k] = 0.0f;
      rh.dir_x[k] = d[0], rh.dir_y[k] = d[1], rh.dir_z[k] = d[2], rh.time[k] = 0.0f;
      rh.tfar[k] = 1e37f, rh.mask[k] = INVALID, rh.id[k] = 0, rh.flags[k] = 0;
      rh.geom_id[k] = rh.prim_id[k] = rh.instance[0][k] = INVALID;
    }
    intersect(valid, scene, &rh, 0);
    for (int64_t k = 0; k < m; ++k) prim[first + k] = rh.prim_id[k] == INVALID ? -1 : (int32_t)rh.prim_id[k];
  }
}

/* Threads take interleaved blocks of rays, so that none gets only a camera's sky rows (cheap misses) */
#define BLOCK 256

/* n float32 rays -> prim, the blocks part, part + parts, ... of them */
void cast(void *scene, void *intersect, const float *org32, const float *dir32, int32_t *prim, int64_t n, int64_t part,
          int64_t parts) {
  for (int64_t start = part * BLOCK; start < n; start += parts * BLOCK) {
    const int64_t m = n - start < BLOCK ? n - start : BLOCK;
    cast_rays(scene, (Intersect8)intersect, org32 + 3 * start, dir32 + 3 * start, prim + start, m);
  }
}

/* sim/camera.py `_hash`: int64 arithmetic wrapping as numpy's does, then a value in [0, 1) */
static inline double cell_hash(int64_t a, int64_t b, int64_t c) {
  const uint64_t h = ((uint64_t)a * 73856093u) ^ ((uint64_t)b * 19349663u) ^ ((uint64_t)c * 83492791u);
  return (double)py_mod_i((int64_t)(h * 2654435761u), 4294967296) / 4294967296.0;
}

enum { PLAIN = 0, BRICKS = 1, STRIPES = 2, NOISE = 3 };

/* sim/camera.py `_texture` for one hit */
static double texture(int kind, const double *p, const double *n) {
  if (kind == BRICKS) {
    const int horizontal = fabs(n[2]) > 0.7;
    const double along = fabs(n[0]) > fabs(n[1]) ? p[1] : p[0];
    const double w = horizontal ? p[1] / 0.5 : p[2] / 0.3;
    const double u = (horizontal ? p[0] / 0.5 : along / 0.6) + 0.5 * py_mod_f(floor(w), 2);
    if (fabs(u - nearbyint(u)) < 0.06 || fabs(w - nearbyint(w)) < 0.08) return 0.7;
    return 0.9 + 0.2 * cell_hash((int64_t)floor(u), (int64_t)floor(w), 0);
  }
  if (kind == STRIPES) return py_mod_f(floor((p[0] + p[1]) / 0.25), 2) == 0 ? 1.0 : 0.75;
  if (kind == NOISE) {
    const double fine = cell_hash((int64_t)floor(p[0] / 0.15), (int64_t)floor(p[1] / 0.15), (int64_t)floor(p[2] / 0.15));
    const double coarse = cell_hash((int64_t)floor(p[0] / 1.3) + 7, (int64_t)floor(p[1] / 1.3) + 7, (int64_t)floor(p[2] / 1.3) + 7);
    return 0.8 + 0.25 * fine * 0.6 + 0.25 * coarse * 0.4;
  }
  return 1.0;
}

/* sim/camera.py `shade` and the uint8 conversion of `render` for one pixel: sky by the ray's elevation; a hit by its
 * object's albedo (O, 3, already / 255) and texture kind (O,), Lambert sun light where `lit` (its shadow ray found
 * nothing), sky light and haze */
static inline void shade_pixel(const double *d, double distance, int64_t owner, const double *n, const double *point,
                               int lit, const double *albedo, const int32_t *kind, const double *sun, uint8_t *rgb) {
  static const double horizon[3] = {0.78, 0.85, 0.93}, zenith[3] = {0.35, 0.55, 0.85}, haze_colour[3] = {0.75, 0.8, 0.88};
  double colour[3];
  if (owner < 0) {
    const double up = clip01(d[2]);
    for (int k = 0; k < 3; ++k) colour[k] = (1 - up) * horizon[k] + up * zenith[k];
  } else {
    const double *a = albedo + 3 * owner;
    const double factor = texture(kind[owner], point, n);
    const double diffuse = clip01((n[0] * sun[0] + n[1] * sun[1]) + n[2] * sun[2]) * (lit ? 1.0 : 0.0);
    const double ambient = 0.35 + 0.15 * clip01(n[2]);
    const double haze = 1 - exp(-distance / 400.0);
    for (int k = 0; k < 3; ++k) {
      const double c = a[k] * factor * (ambient + 0.75 * diffuse);
      colour[k] = (1 - haze) * c + haze * haze_colour[k];
    }
  }
  for (int k = 0; k < 3; ++k) rgb[k] = (uint8_t)(clip01(colour[k]) * 255 + 0.5);
}

/* A whole camera, block by block, as sim/camera.py `render` composes the stages: the n pixel rays from `origin`
 * along `dirs` (first hits within 1000 m), a shadow ray from each hit (its point moved 0.02 m along the normal,
 * towards the sun, hits within 300 m), the shading -> distance, owner (as RayScene.cast reports them) and rgb;
 * the blocks part, part + parts, ... of the pixels */
void camera(void *scene, void *intersect, const double *restrict origin, const double *restrict dirs,
            const double *restrict shift, double scale, const double *restrict plane_o, const double *restrict plane_n,
            const int64_t *restrict face_owner, const double *restrict albedo, const int32_t *restrict kind,
            const double *restrict sun, double *restrict distance, int64_t *restrict owner, uint8_t *restrict rgb,
            int64_t n, int64_t part, int64_t parts) {
  double unit[3 * BLOCK], normal[3 * BLOCK], point[3 * BLOCK], s_org[3 * BLOCK], s_unit[3 * BLOCK], s_normal[3], s_point[3];
  float org32[3 * BLOCK], dir32[3 * BLOCK];
  int32_t prim[BLOCK], hit[BLOCK];
  for (int64_t start = part * BLOCK; start < n; start += parts * BLOCK) {
    const int64_t m = n - start < BLOCK ? n - start : BLOCK;
    const double *d = dirs + 3 * start;
    for (int64_t i = 0; i < m; ++i) prepare_ray(origin, d + 3 * i, shift, scale, unit + 3 * i, org32 + 3 * i, dir32 + 3 * i);
    cast_rays(scene, (Intersect8)intersect, org32, dir32, prim, m);
    int64_t hits = 0;
    for (int64_t i = 0; i < m; ++i) {
      finish_ray(origin, d + 3 * i, unit + 3 * i, prim[i], plane_o, plane_n, face_owner, 1000.0, distance + start + i,
                 owner + start + i, normal + 3 * i, point + 3 * i);
      if (owner[start + i] < 0) continue;
      double *o = s_org + 3 * hits;
      for (int k = 0; k < 3; ++k) o[k] = point[3 * i + k] + normal[3 * i + k] * 0.02;
      prepare_ray(o, sun, shift, scale, s_unit + 3 * hits, org32 + 3 * hits, dir32 + 3 * hits);
      hit[hits++] = (int32_t)i;
    }
    cast_rays(scene, (Intersect8)intersect, org32, dir32, prim, hits);
    for (int64_t h = 0, j = 0; j < m; ++j) {
      int lit = 0;
      if (h < hits && hit[h] == j) {
        double s_distance;
        int64_t s_owner;
        finish_ray(s_org + 3 * h, sun, s_unit + 3 * h, prim[h], plane_o, plane_n, face_owner, 300.0, &s_distance,
                   &s_owner, s_normal, s_point);
        lit = s_owner < 0;
        ++h;
      }
      shade_pixel(d + 3 * j, distance[start + j], owner[start + j], normal + 3 * j, point + 3 * j, lit, albedo, kind, sun,
                  rgb + 3 * (start + j));
    }
  }
}
