/* Around the ray casts: first-hit geometry and camera shading, see co3sop_nodes/sim/ray_kernel.py.
 *
 * The reference is NumPy (sim/raycast.py `RayScene.cast` on trimesh's intersector, sim/camera.py `shade`);
 * every value here is the same float64 operation in the same order (compiled without FMA contraction), so
 * hits and images are bit-identical to it: tests compare both on fixed and random scenes.
 * Functions take [start, end) ranges of rays so that threads can split them (ctypes releases the GIL).
 */
#include <math.h>
#include <stdint.h>

/* Python's floor division and modulo (numpy's for int64 and float64): the result has the divisor's sign */
static inline int64_t py_mod_i(int64_t a, int64_t m) { int64_t r = a % m; return r < 0 ? r + m : r; }
static inline double py_mod_f(double a, double m) { double r = fmod(a, m); return (r != 0 && r < 0) ? r + m : r; }
static inline double clip01(double x) { return x < 0 ? 0 : (x > 1 ? 1 : x); }

/* directions (n, 3) -> unit (n, 3) as trimesh.util.unitize computes them (norm from a dot with ones, times its
 * reciprocal); the float32 rays Embree casts: origins shifted and scaled into the BVH's frame, unit directions.
 * origins advance by o_stride doubles per ray (0: one origin for every ray) */
void prepare(const double *restrict origins, int64_t o_stride, const double *restrict dirs, const double *restrict shift,
             double scale, double *restrict unit, float *restrict org32, float *restrict dir32, int64_t start, int64_t end) {
  for (int64_t i = start; i < end; ++i) {
    const double *d = dirs + 3 * i, *o = origins + o_stride * i;
    double norm = sqrt((d[0] * d[0] + d[1] * d[1]) + d[2] * d[2]);
    if (norm > 1e-13) norm = 1.0 / norm;
    for (int k = 0; k < 3; ++k) {
      unit[3 * i + k] = d[k] * norm;
      dir32[3 * i + k] = (float)unit[3 * i + k];
      org32[3 * i + k] = (float)((o[k] - shift[k]) * scale);
    }
  }
}

/* Embree's triangle per ray (-1: none) -> the hit as trimesh locates it (the ray's plane intersection with the
 * triangle's plane, unit direction; near-parallel rays miss) and RayScene.cast reports it: distance along
 * `dirs` (inf: none or beyond max_distance), owner object (-1), normal facing the ray (0), point (origin) */
void finish(const double *restrict origins, int64_t o_stride, const double *restrict dirs, const double *restrict unit,
            const int32_t *restrict prim, const double *restrict plane_o, const double *restrict plane_n,
            const int64_t *restrict face_owner, double max_distance, double *restrict distance, int64_t *restrict owner,
            double *restrict normal, double *restrict point, int64_t start, int64_t end) {
  for (int64_t i = start; i < end; ++i) {
    const double *o = origins + o_stride * i, *d = dirs + 3 * i, *u = unit + 3 * i;
    double dist = INFINITY, n[3] = {0, 0, 0};
    int64_t who = -1;
    const int32_t p = prim[i];
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
    distance[i] = dist;
    owner[i] = who;
    const double along = isfinite(dist) ? dist : 0;
    for (int k = 0; k < 3; ++k) {
      normal[3 * i + k] = n[k];
      point[3 * i + k] = o[k] + along * d[k];
    }
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

/* sim/camera.py `shade` and the uint8 conversion of `render`: sky by the ray's elevation; a hit by its object's
 * albedo (O, 3, already / 255) and texture kind (O,), Lambert sun light where `lit` (its shadow ray found
 * nothing), sky light and haze */
void shade(const double *restrict dirs, const double *restrict distance, const int64_t *restrict owner,
           const double *restrict normal, const double *restrict point, const uint8_t *restrict lit,
           const double *restrict albedo, const int32_t *restrict kind, const double *restrict sun,
           uint8_t *restrict rgb, int64_t start, int64_t end) {
  static const double horizon[3] = {0.78, 0.85, 0.93}, zenith[3] = {0.35, 0.55, 0.85}, haze_colour[3] = {0.75, 0.8, 0.88};
  for (int64_t i = start; i < end; ++i) {
    double colour[3];
    const double *d = dirs + 3 * i;
    if (owner[i] < 0) {
      const double up = clip01(d[2]);
      for (int k = 0; k < 3; ++k) colour[k] = (1 - up) * horizon[k] + up * zenith[k];
    } else {
      const double *n = normal + 3 * i, *a = albedo + 3 * owner[i];
      const double factor = texture(kind[owner[i]], point + 3 * i, n);
      const double diffuse = clip01((n[0] * sun[0] + n[1] * sun[1]) + n[2] * sun[2]) * (lit[i] ? 1.0 : 0.0);
      const double ambient = 0.35 + 0.15 * clip01(n[2]);
      const double haze = 1 - exp(-distance[i] / 400.0);
      for (int k = 0; k < 3; ++k) {
        const double c = a[k] * factor * (ambient + 0.75 * diffuse);
        colour[k] = (1 - haze) * c + haze * haze_colour[k];
      }
    }
    for (int k = 0; k < 3; ++k) rgb[3 * i + k] = (uint8_t)(clip01(colour[k]) * 255 + 0.5);
  }
}
