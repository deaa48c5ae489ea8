/* A residual sum and the layer norm of each row, for inference: out = LayerNorm(x + y) over rows of C channels
 * (PyTorch's, with a weight and a bias); see co3sop_nodes/kernels/layer_norm.py. PyTorch's layer norm over rows
 * of 32 or 48 channels spends most of its time per row, not per channel: here a row is C/8 vectors in registers,
 * summed, centred, scaled and written once. x and y are float32 or bfloat16 (widened exactly), the sums float32,
 * the variance that of the centred values (two passes over the registers, as the definition reads). Rows go in
 * blocks of B, whose chains of sums, square root and division are independent (a row at a time waits on each).
 * C (a multiple of 8) is defined on the command line.
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#if C % 8
#error "C must be a multiple of 8"
#endif
#define NV (C / 8)
#define B 8

typedef float fv __attribute__((vector_size(32)));
typedef int32_t iv __attribute__((vector_size(32)));
typedef uint16_t hv __attribute__((vector_size(16)));
typedef fv fvu __attribute__((aligned(4))); /* loads and stores at the element's alignment */
typedef hv hvu __attribute__((aligned(2)));

#define INLINE static inline __attribute__((always_inline))

/* 8 elements from i of a float32 (bf16 = 0) or bfloat16 (bf16 = 1) array; bf16 is a constant in every copy */
INLINE fv load8(const void *p, int64_t i, int bf16) {
  if (!bf16) return *(const fvu *)((const float *)p + i);
  const iv bits = __builtin_convertvector(*(const hvu *)((const uint16_t *)p + i), iv) << 16;
  fv f;
  memcpy(&f, &bits, sizeof f);
  return f;
}

INLINE float lanes_sum(fv s) { return ((s[0] + s[4]) + (s[1] + s[5])) + ((s[2] + s[6]) + (s[3] + s[7])); }

/* rows r0 .. r0 + n - 1 (n at most B) */
INLINE void block(const void *x, int xb, const void *y, int yb, const fv *weight, const fv *bias, float eps,
                  float *out, int64_t r0, const int n) {
  fv v[B][NV];
  float mean[B], rstd[B];
  for (int i = 0; i < n; i++) {
    const int64_t r = (r0 + i) * C;
    fv s = {0};
    for (int k = 0; k < NV; k++) {
      v[i][k] = load8(x, r + 8 * k, xb) + load8(y, r + 8 * k, yb);
      s += v[i][k];
    }
    mean[i] = lanes_sum(s) / C;
  }
  for (int i = 0; i < n; i++) {
    fv s = {0};
    for (int k = 0; k < NV; k++) {
      v[i][k] -= mean[i];
      s += v[i][k] * v[i][k];
    }
    rstd[i] = 1.0f / sqrtf(lanes_sum(s) / C + eps);
  }
  for (int i = 0; i < n; i++) {
    float *o = out + (r0 + i) * C;
    for (int k = 0; k < NV; k++) *(fvu *)(o + 8 * k) = v[i][k] * rstd[i] * weight[k] + bias[k];
  }
}

INLINE void rows(const void *x, int xb, const void *y, int yb, const float *weight, const float *bias, float eps,
                 float *out, int64_t start, int64_t end) {
  fv w[NV], b[NV];
  for (int k = 0; k < NV; k++) {
    w[k] = *(const fvu *)(weight + 8 * k);
    b[k] = *(const fvu *)(bias + 8 * k);
  }
  int64_t r = start;
  for (; r + B <= end; r += B) block(x, xb, y, yb, w, b, eps, out, r, B);
  for (; r < end; r++) block(x, xb, y, yb, w, b, eps, out, r, 1);
}

/* rows [start, end) of x, y (R, C) row-major, float32 or bfloat16 as x_bf16, y_bf16 say -> out (R, C) float32 */
void add_layer_norm(const void *x, int64_t x_bf16, const void *y, int64_t y_bf16, const float *weight,
                    const float *bias, float eps, float *out, int64_t start, int64_t end) {
  if (!x_bf16 && !y_bf16) rows(x, 0, y, 0, weight, bias, eps, out, start, end);
  else if (!x_bf16) rows(x, 0, y, 1, weight, bias, eps, out, start, end);
  else if (!y_bf16) rows(x, 1, y, 0, weight, bias, eps, out, start, end);
  else rows(x, 1, y, 1, weight, bias, eps, out, start, end);
}
