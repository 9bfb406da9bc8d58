// The population-control statistics of one view (core/train/strategy.py: `_Strategy.accumulate`, its
// readable torch twin) in one pass over the primitives: the frustum test of `in_frustum` and the
// kind's densification signal, added into the accumulators in place:
//
//   visible_p = min_j n_j·p_p ≥ −r_p  and  z_p + r_p > near,   p_p = R μ_p + t (camera space),
//               r_p = radius_scale · exp(max ℓ_p), n_j the unit inward normals of the 4 side planes
//   grad_p  += visible_p ? signal_p : 0,   count_p += visible_p
//
//   Gaussian signal (3DGS's screen-space gradient, in NDC units): with g = R ∂L/∂μ_p and z_p
//       the depth, hypot(g_x z_p / fx · W/2, g_y z_p / fy · H/2)
//   neural signal (Splat the Net): ‖∂L/∂W1‖ + ‖∂L/∂b1‖ + ‖∂L/∂W2‖ + |∂L/∂b2| of the primitive's MLP
//
// In torch these are some twenty small ops over (P, …) tensors a view. Threads: OpenMP over
// primitives (each accumulator row is its primitive's own).

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>

#include "pair_kernels.h"

namespace {

using radfield::check_params;

template <typename T>
struct Frustum {
  T R[3][3], t[3];   // world to camera
  T n[4][3];         // the side planes' unit inward normals (camera space)
  T radius_scale, near;
};

template <typename T>
Frustum<T> read_frustum(const at::Tensor& w2c, const at::Tensor& normals, double radius_scale, double near) {
  TORCH_CHECK(w2c.sizes() == at::IntArrayRef({3, 4}) && normals.sizes() == at::IntArrayRef({4, 3}),
              "w2c must be (3, 4) and normals (4, 3)");
  Frustum<T> f;
  const T *w = w2c.data_ptr<T>(), *n = normals.data_ptr<T>();
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) f.R[r][c] = w[4 * r + c];
    f.t[r] = w[4 * r + 3];
  }
  for (int j = 0; j < 4; ++j)
    for (int c = 0; c < 3; ++c) f.n[j][c] = n[3 * j + c];
  f.radius_scale = T(radius_scale), f.near = T(near);
  return f;
}

// camera-space position p of mean m, and whether the sphere of radius r around it meets the frustum
template <typename T>
bool visible(const Frustum<T>& f, const T* m, T radius, T* p) {
  for (int r = 0; r < 3; ++r) p[r] = m[0] * f.R[r][0] + m[1] * f.R[r][1] + m[2] * f.R[r][2] + f.t[r];
  T nearest = p[0] * f.n[0][0] + p[1] * f.n[0][1] + p[2] * f.n[0][2];
  for (int j = 1; j < 4; ++j) nearest = std::min(nearest, p[0] * f.n[j][0] + p[1] * f.n[j][1] + p[2] * f.n[j][2]);
  return nearest >= -radius && p[2] + radius > f.near;
}

constexpr int64_t kBlock = 256;   // primitives per SIMD pass of exp (the radii) and of the signal

void check_accumulators(const at::Tensor& grad_acc, const at::Tensor& count_acc, const at::Tensor& means,
                        const at::Tensor& log_scales) {
  check_params({grad_acc, count_acc, means, log_scales});
  const int64_t P = means.size(0);
  TORCH_CHECK(means.sizes() == at::IntArrayRef({P, 3}) && log_scales.sizes() == at::IntArrayRef({P, 3}),
              "means and log_scales must be (P, 3)");
  TORCH_CHECK(grad_acc.sizes() == at::IntArrayRef({P}) && count_acc.sizes() == at::IntArrayRef({P}),
              "the accumulators must be (P,)");
}

// signal(i, p, aux) -> T for visible primitive i at camera-space p (aux: a second value the kind
// may set), then finish(values, auxes, n): SIMD post-processing of a block's signals in place
template <typename T, typename Signal, typename Finish>
void accumulate(at::Tensor& grad_acc, at::Tensor& count_acc, const at::Tensor& means, const at::Tensor& log_scales,
                const Frustum<T>& f, Signal&& signal, Finish&& finish) {
  const T *m = means.data_ptr<T>(), *ls = log_scales.data_ptr<T>();
  T *acc = grad_acc.data_ptr<T>(), *count = count_acc.data_ptr<T>();
  at::parallel_for(0, means.size(0), 2048, [&](int64_t p0, int64_t p1) {
    T radius[kBlock], value[kBlock], aux[kBlock];
    bool seen[kBlock];
    for (int64_t b0 = p0; b0 < p1; b0 += kBlock) {
      const int64_t n = std::min(kBlock, p1 - b0);
      for (int64_t j = 0; j < n; ++j) {
        const T* l = ls + 3 * (b0 + j);
        radius[j] = std::max(std::max(l[0], l[1]), l[2]);
      }
      radfield::simd_exp(radius, radius, n);   // torch.exp's Sleef routine: the same radii as the twin
      for (int64_t j = 0; j < n; ++j) {
        T p[3];
        seen[j] = visible(f, m + 3 * (b0 + j), f.radius_scale * radius[j], p);
        aux[j] = T(0);
        value[j] = seen[j] ? signal(b0 + j, p, aux[j]) : T(0);
      }
      finish(value, aux, n);
      for (int64_t j = 0; j < n; ++j)
        if (seen[j]) acc[b0 + j] += value[j], count[b0 + j] += T(1);
    }
  });
}

void gaussian_accumulate(at::Tensor& grad_acc, at::Tensor& count_acc, const at::Tensor& means, const at::Tensor& log_scales,
                         const at::Tensor& grad_means, const at::Tensor& w2c, const at::Tensor& normals,
                         double radius_scale, double near, double fx, double fy, double width, double height) {
  check_accumulators(grad_acc, count_acc, means, log_scales);
  check_params({means, grad_means, w2c, normals});
  TORCH_CHECK(grad_means.sizes() == means.sizes(), "grad_means must be (P, 3)");
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "gaussian_accumulate", [&] {
    using T = scalar_t;
    const Frustum<T> f = read_frustum<T>(w2c, normals, radius_scale, near);
    const T* g = grad_means.data_ptr<T>();
    const T sx = T(fx), sy = T(fy), hw = T(width / 2), hh = T(height / 2);
    // the NDC gradient's x component as the value and its y component as aux, then hypot
    accumulate<T>(grad_acc, count_acc, means, log_scales, f, [&](int64_t i, const T* p, T& ndc_y) {
      const T* gi = g + 3 * i;
      const T gx = gi[0] * f.R[0][0] + gi[1] * f.R[0][1] + gi[2] * f.R[0][2];
      const T gy = gi[0] * f.R[1][0] + gi[1] * f.R[1][1] + gi[2] * f.R[1][2];
      ndc_y = gy * p[2] / sy * hh;
      return gx * p[2] / sx * hw;
    }, [](T* value, const T* ndc_y, int64_t n) {
      at::vec::map2([](at::vec::Vectorized<T> x, at::vec::Vectorized<T> y) { return x.hypot(y); }, value, value, ndc_y, n);
    });
  });
}

void neural_accumulate(at::Tensor& grad_acc, at::Tensor& count_acc, const at::Tensor& means, const at::Tensor& log_scales,
                       const at::Tensor& g_w1, const at::Tensor& g_b1, const at::Tensor& g_w2, const at::Tensor& g_b2,
                       const at::Tensor& w2c, const at::Tensor& normals, double radius_scale, double near) {
  check_accumulators(grad_acc, count_acc, means, log_scales);
  check_params({means, g_w1, g_b1, g_w2, g_b2, w2c, normals});
  const int64_t P = means.size(0), N = g_b1.size(1);
  TORCH_CHECK(g_w1.sizes() == at::IntArrayRef({P, N, 3}) && g_b1.sizes() == at::IntArrayRef({P, N}) &&
                  g_w2.sizes() == at::IntArrayRef({P, N}) && g_b2.sizes() == at::IntArrayRef({P}),
              "the MLP gradients must be (P, N, 3), (P, N), (P, N), (P,)");
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "neural_accumulate", [&] {
    using T = scalar_t;
    const Frustum<T> f = read_frustum<T>(w2c, normals, radius_scale, near);
    const T *w1 = g_w1.data_ptr<T>(), *b1 = g_b1.data_ptr<T>(), *w2 = g_w2.data_ptr<T>(), *b2 = g_b2.data_ptr<T>();
    const auto norm = [](const T* x, int64_t n) {
      T sum = T(0);
      for (int64_t e = 0; e < n; ++e) sum += x[e] * x[e];
      return std::sqrt(sum);
    };
    accumulate<T>(grad_acc, count_acc, means, log_scales, f, [&](int64_t i, const T*, T&) {
      return norm(w1 + 3 * N * i, 3 * N) + norm(b1 + N * i, N) + norm(w2 + N * i, N) + std::abs(b2[i]);
    }, [](T*, const T*, int64_t) {});
  });
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(radfield, m) {
  // the accumulators are updated in place (declared mutable: Tensor(a!))
  m.def("gaussian_accumulate(Tensor(a!) grad_acc, Tensor(b!) count_acc, Tensor means, Tensor log_scales, "
        "Tensor grad_means, Tensor w2c, Tensor normals, float radius_scale, float near, float fx, float fy, "
        "float width, float height) -> ()", &gaussian_accumulate);
  m.def("neural_accumulate(Tensor(a!) grad_acc, Tensor(b!) count_acc, Tensor means, Tensor log_scales, "
        "Tensor g_w1, Tensor g_b1, Tensor g_w2, Tensor g_b2, Tensor w2c, Tensor normals, float radius_scale, "
        "float near) -> ()", &neural_accumulate);
}
