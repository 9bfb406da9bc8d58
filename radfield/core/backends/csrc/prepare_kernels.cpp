// Per-view, per-primitive preparation in C++, forward and backward: what rasterize.py computes
// once per primitive per view before compositing, as two fused ops whose readable torch twins
// stay in core/render/rasterize.py and core/splat/sh.py (tests/test_fused.py compares them, and gradchecks
// these ops in float64). In torch they are some hundred small ops over (P, …) tensors, forward
// and backward, which cost a training step at 64×64 more than the whole tile rasteriser.
//
//   sh_color:    colour = max(Σ_k Y_k(d̂) sh_k + 0.5, 0), d̂ = v/|v|, v = μ − o   (core/splat/sh.py)
//   neural_prep: M = S⁻¹Rᵀ, m_cam = M R_cam, o' = M (o − μ), w_cam = ω0 W1 R_cam,
//                c_k = ω0 (W1_k·(o − μ)/max(s) + b1_k), 1/max(s)           (rasterize._neural_view)
//   gaussian_prep: EWA splatting (rasterize._gaussian_view): 2D mean, the 2D covariance
//                J W Σ Wᵀ Jᵀ + 0.3 I (a, b, c) and its conic, from the camera-space mean
//   neural_bounds, gaussian_bounds: (no gradient) the pixel bounds of every primitive and the
//                visible ones front to back, stable by centre depth   (rasterize._neural_bounds,
//                rasterize._gaussian_bounds, and the depth sort of rasterize.render)
//
// Threads: OpenMP over primitives (each primitive's gradient is its own).

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>
#include <type_traits>
#include <utility>
#include <vector>

#include "pair_kernels.h"

namespace {

using radfield::check_params;
using radfield::rotmat;
using radfield::rotmat_backward;

// --- SH colour (3DGS's real SH basis and order, core/splat/sh.py) -----------------------------------

constexpr double C0 = 0.28209479177387814;
constexpr double C1 = 0.4886025119029199;
constexpr double C2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
                          0.5462742152960396};
constexpr double C3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
                          -0.4570457994644658, 1.445305721320277, -0.5900435899266435};

// basis values b[0..count) at unit direction (x, y, z), and with grad != nullptr their gradients
// (always inlined: with a constant degree and grad the branches fold away and b, grad stay in registers)
template <typename T>
__attribute__((always_inline)) inline int sh_basis(int degree, T x, T y, T z, T* b, T (*grad)[3]) {
  int n = 0;
  auto put = [&](T value, T gx, T gy, T gz) {
    b[n] = value;
    if (grad != nullptr) grad[n][0] = gx, grad[n][1] = gy, grad[n][2] = gz;
    ++n;
  };
  put(T(C0), 0, 0, 0);
  if (degree >= 1) {
    put(T(-C1) * y, 0, T(-C1), 0);
    put(T(C1) * z, 0, 0, T(C1));
    put(T(-C1) * x, T(-C1), 0, 0);
  }
  if (degree >= 2) {
    const T xx = x * x, yy = y * y, zz = z * z;
    put(T(C2[0]) * x * y, T(C2[0]) * y, T(C2[0]) * x, 0);
    put(T(C2[1]) * y * z, 0, T(C2[1]) * z, T(C2[1]) * y);
    put(T(C2[2]) * (T(2) * zz - xx - yy), T(C2[2]) * T(-2) * x, T(C2[2]) * T(-2) * y, T(C2[2]) * T(4) * z);
    put(T(C2[3]) * x * z, T(C2[3]) * z, 0, T(C2[3]) * x);
    put(T(C2[4]) * (xx - yy), T(C2[4]) * T(2) * x, T(C2[4]) * T(-2) * y, 0);
  }
  if (degree >= 3) {
    const T xx = x * x, yy = y * y, zz = z * z;
    put(T(C3[0]) * y * (T(3) * xx - yy), T(C3[0]) * T(6) * x * y, T(C3[0]) * (T(3) * xx - T(3) * yy), 0);
    put(T(C3[1]) * x * y * z, T(C3[1]) * y * z, T(C3[1]) * x * z, T(C3[1]) * x * y);
    put(T(C3[2]) * y * (T(4) * zz - xx - yy), T(C3[2]) * T(-2) * x * y, T(C3[2]) * (T(4) * zz - xx - T(3) * yy),
        T(C3[2]) * T(8) * y * z);
    put(T(C3[3]) * z * (T(2) * zz - T(3) * xx - T(3) * yy), T(C3[3]) * T(-6) * x * z, T(C3[3]) * T(-6) * y * z,
        T(C3[3]) * (T(6) * zz - T(3) * xx - T(3) * yy));
    put(T(C3[4]) * x * (T(4) * zz - xx - yy), T(C3[4]) * (T(4) * zz - T(3) * xx - yy), T(C3[4]) * T(-2) * x * y,
        T(C3[4]) * T(8) * x * z);
    put(T(C3[5]) * z * (xx - yy), T(C3[5]) * T(2) * x * z, T(C3[5]) * T(-2) * y * z, T(C3[5]) * (xx - yy));
    put(T(C3[6]) * x * (xx - T(3) * yy), T(C3[6]) * (T(3) * xx - T(3) * yy), T(C3[6]) * T(-6) * x * y, 0);
  }
  return n;
}

// g_d += Σ_k g_b[k] ∇b_k(x, y, z) over the first (degree + 1)² basis functions: sh_basis's
// gradients with their zero components left out (x · 0 cannot be folded away without
// -ffast-math), the same expressions added in the same order of k, so the same sums bit for bit.
template <typename T>
__attribute__((always_inline)) inline void sh_basis_grad(int degree, T x, T y, T z, const T* g_b, T* g_d) {
  if (degree >= 1) {
    g_d[1] += g_b[1] * T(-C1);
    g_d[2] += g_b[2] * T(C1);
    g_d[0] += g_b[3] * T(-C1);
  }
  if (degree >= 2) {
    g_d[0] += g_b[4] * (T(C2[0]) * y), g_d[1] += g_b[4] * (T(C2[0]) * x);
    g_d[1] += g_b[5] * (T(C2[1]) * z), g_d[2] += g_b[5] * (T(C2[1]) * y);
    g_d[0] += g_b[6] * (T(C2[2]) * T(-2) * x), g_d[1] += g_b[6] * (T(C2[2]) * T(-2) * y);
    g_d[2] += g_b[6] * (T(C2[2]) * T(4) * z);
    g_d[0] += g_b[7] * (T(C2[3]) * z), g_d[2] += g_b[7] * (T(C2[3]) * x);
    g_d[0] += g_b[8] * (T(C2[4]) * T(2) * x), g_d[1] += g_b[8] * (T(C2[4]) * T(-2) * y);
  }
  if (degree >= 3) {
    const T xx = x * x, yy = y * y, zz = z * z;
    g_d[0] += g_b[9] * (T(C3[0]) * T(6) * x * y), g_d[1] += g_b[9] * (T(C3[0]) * (T(3) * xx - T(3) * yy));
    g_d[0] += g_b[10] * (T(C3[1]) * y * z), g_d[1] += g_b[10] * (T(C3[1]) * x * z);
    g_d[2] += g_b[10] * (T(C3[1]) * x * y);
    g_d[0] += g_b[11] * (T(C3[2]) * T(-2) * x * y), g_d[1] += g_b[11] * (T(C3[2]) * (T(4) * zz - xx - T(3) * yy));
    g_d[2] += g_b[11] * (T(C3[2]) * T(8) * y * z);
    g_d[0] += g_b[12] * (T(C3[3]) * T(-6) * x * z), g_d[1] += g_b[12] * (T(C3[3]) * T(-6) * y * z);
    g_d[2] += g_b[12] * (T(C3[3]) * (T(6) * zz - T(3) * xx - T(3) * yy));
    g_d[0] += g_b[13] * (T(C3[4]) * (T(4) * zz - T(3) * xx - yy)), g_d[1] += g_b[13] * (T(C3[4]) * T(-2) * x * y);
    g_d[2] += g_b[13] * (T(C3[4]) * T(8) * x * z);
    g_d[0] += g_b[14] * (T(C3[5]) * T(2) * x * z), g_d[1] += g_b[14] * (T(C3[5]) * T(-2) * y * z);
    g_d[2] += g_b[14] * (T(C3[5]) * (xx - yy));
    g_d[0] += g_b[15] * (T(C3[6]) * (T(3) * xx - T(3) * yy)), g_d[1] += g_b[15] * (T(C3[6]) * T(-6) * x * y);
  }
}

// d̂ = v / max(|v|, 1e-12) as torch.nn.functional.normalize
template <typename T>
T unit(const T* v, T* d) {
  const T norm = std::max(std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]), T(1e-12));
  d[0] = v[0] / norm, d[1] = v[1] / norm, d[2] = v[2] / norm;
  return norm;
}

at::Tensor sh_color_forward(const at::Tensor& sh, const at::Tensor& v, int64_t degree) {
  check_params({sh, v});
  TORCH_CHECK(sh.dim() == 3 && sh.size(2) == 3 && (degree + 1) * (degree + 1) <= sh.size(1) && degree >= 0 && degree <= 3,
              "sh must be (P, K, 3) with K ≥ (degree + 1)², degree in 0..3");
  const int64_t P = sh.size(0), K = sh.size(1);
  TORCH_CHECK(v.sizes() == at::IntArrayRef({P, 3}), "v must be (P, 3)");
  at::Tensor out = at::empty({P, 3}, sh.options());
  AT_DISPATCH_FLOATING_TYPES(sh.scalar_type(), "sh_color_forward", [&] {
    using T = scalar_t;
    const T *s = sh.data_ptr<T>(), *vp = v.data_ptr<T>();
    T* o = out.data_ptr<T>();
    at::parallel_for(0, P, 256, [&](int64_t p0, int64_t p1) {
      T b[16], d[3];
      for (int64_t p = p0; p < p1; ++p) {
        unit(vp + 3 * p, d);
        const int n = sh_basis<T>(int(degree), d[0], d[1], d[2], b, nullptr);
        for (int ch = 0; ch < 3; ++ch) {
          T raw = T(0);
          for (int k = 0; k < n; ++k) raw += b[k] * s[(p * K + k) * 3 + ch];
          o[3 * p + ch] = std::max(raw + T(0.5), T(0));
        }
      }
    });
  });
  return out;
}

// Gradients for (sh, v).
std::vector<at::Tensor> sh_color_backward(const at::Tensor& grad, const at::Tensor& sh, const at::Tensor& v,
                                          int64_t degree) {
  check_params({grad, sh, v});
  const int64_t P = sh.size(0), K = sh.size(1);
  // the coefficients above the degree get zeros, the others are written: no zero pass over all
  at::Tensor g_sh = at::empty_like(sh), g_v = at::empty_like(v);
  AT_DISPATCH_FLOATING_TYPES(sh.scalar_type(), "sh_color_backward", [&] {
    using T = scalar_t;
    const T *s = sh.data_ptr<T>(), *vp = v.data_ptr<T>(), *g = grad.data_ptr<T>();
    T *gs = g_sh.data_ptr<T>(), *gv = g_v.data_ptr<T>();
    at::parallel_for(0, P, 256, [&](int64_t p0, int64_t p1) {
      T b[16], db[16][3], d[3];
      for (int64_t p = p0; p < p1; ++p) {
        const T norm = unit(vp + 3 * p, d);
        const int n = sh_basis<T>(int(degree), d[0], d[1], d[2], b, db);
        T g_raw[3];
        for (int ch = 0; ch < 3; ++ch) {
          T raw = T(0);
          for (int k = 0; k < n; ++k) raw += b[k] * s[(p * K + k) * 3 + ch];
          g_raw[ch] = raw + T(0.5) >= T(0) ? g[3 * p + ch] : T(0);  // clamp_min passes at equality
        }
        T g_d[3] = {0, 0, 0};
        std::fill(gs + (p * K + n) * 3, gs + (p + 1) * K * 3, T(0));
        for (int k = 0; k < n; ++k) {
          const T* sk = s + (p * K + k) * 3;
          T* gsk = gs + (p * K + k) * 3;
          for (int ch = 0; ch < 3; ++ch) gsk[ch] = b[k] * g_raw[ch];
          const T g_b = sk[0] * g_raw[0] + sk[1] * g_raw[1] + sk[2] * g_raw[2];
          for (int r = 0; r < 3; ++r) g_d[r] += g_b * db[k][r];
        }
        // d̂ = v/|v|: ∂/∂v = (g − d̂ (d̂·g)) / |v|
        const T dot = d[0] * g_d[0] + d[1] * g_d[1] + d[2] * g_d[2];
        for (int r = 0; r < 3; ++r) gv[3 * p + r] = (g_d[r] - d[r] * dot) / norm;
      }
    });
  });
  return {g_sh, g_v};
}

// The same colour from the two SH tensors the trainer optimises, (dc (P, 1, 3), rest (P, K − 1, 3)),
// and from the means and the camera centre (v = μ − o): no concatenation of the coefficients
// and no v tensor, forward or backward (the backward writes the gradients of dc, rest and μ
// directly). The degree is a template constant, so the basis and the sums over it unroll.
template <typename T>
struct SHParts {
  const T *dc, *rest, *means, *campos;
  int64_t rest_rows;  // K − 1
  const T* coef(int64_t p, int k) const { return k == 0 ? dc + 3 * p : rest + (p * rest_rows + k - 1) * 3; }
};

template <typename T, int kDegree>
void sh_parts_forward(const SHParts<T>& in, T* out, int64_t P) {
  constexpr int n = (kDegree + 1) * (kDegree + 1);
  at::parallel_for(0, P, 512, [&](int64_t p0, int64_t p1) {
    T b[16], d[3], v[3];
    for (int64_t p = p0; p < p1; ++p) {
      for (int r = 0; r < 3; ++r) v[r] = in.means[3 * p + r] - in.campos[r];
      unit(v, d);
      sh_basis<T>(kDegree, d[0], d[1], d[2], b, nullptr);
      T raw[3] = {0, 0, 0};   // the order of sh_color_forward: k = 0, 1, … per channel
      for (int k = 0; k < n; ++k) {
        const T* s = in.coef(p, k);
        for (int ch = 0; ch < 3; ++ch) raw[ch] += b[k] * s[ch];
      }
      for (int ch = 0; ch < 3; ++ch) out[3 * p + ch] = std::max(raw[ch] + T(0.5), T(0));
    }
  });
}

template <typename T, int kDegree>
void sh_parts_backward(const SHParts<T>& in, const T* g, T* g_dc, T* g_rest, T* g_means, int64_t P) {
  constexpr int n = (kDegree + 1) * (kDegree + 1);
  at::parallel_for(0, P, 512, [&](int64_t p0, int64_t p1) {
    T b[16], g_b[16], d[3], v[3];
    for (int64_t p = p0; p < p1; ++p) {
      for (int r = 0; r < 3; ++r) v[r] = in.means[3 * p + r] - in.campos[r];
      const T norm = unit(v, d);
      sh_basis<T>(kDegree, d[0], d[1], d[2], b, nullptr);
      T raw[3] = {0, 0, 0};
      for (int k = 0; k < n; ++k) {
        const T* s = in.coef(p, k);
        for (int ch = 0; ch < 3; ++ch) raw[ch] += b[k] * s[ch];
      }
      T g_raw[3];
      for (int ch = 0; ch < 3; ++ch) g_raw[ch] = raw[ch] + T(0.5) >= T(0) ? g[3 * p + ch] : T(0);  // clamp_min passes at equality
      T g_d[3] = {0, 0, 0};
      T* gr = g_rest + p * in.rest_rows * 3;
      std::fill(gr + (n - 1) * 3, gr + in.rest_rows * 3, T(0));   // the bands above the degree
      for (int k = 0; k < n; ++k) {
        const T* s = in.coef(p, k);
        T* gs = k == 0 ? g_dc + 3 * p : gr + (k - 1) * 3;
        for (int ch = 0; ch < 3; ++ch) gs[ch] = b[k] * g_raw[ch];
        g_b[k] = s[0] * g_raw[0] + s[1] * g_raw[1] + s[2] * g_raw[2];
      }
      sh_basis_grad<T>(kDegree, d[0], d[1], d[2], g_b, g_d);
      // d̂ = v/|v|: ∂/∂v = (g − d̂ (d̂·g)) / |v|, and ∂v/∂μ = I
      const T dot = d[0] * g_d[0] + d[1] * g_d[1] + d[2] * g_d[2];
      for (int r = 0; r < 3; ++r) g_means[3 * p + r] = (g_d[r] - d[r] * dot) / norm;
    }
  });
}

template <typename T, typename Run>
void with_degree(int64_t degree, Run&& run) {
  switch (degree) {
    case 0: return run(std::integral_constant<int, 0>());
    case 1: return run(std::integral_constant<int, 1>());
    case 2: return run(std::integral_constant<int, 2>());
    default: return run(std::integral_constant<int, 3>());
  }
}

void check_sh_parts(const at::Tensor& dc, const at::Tensor& rest, const at::Tensor& means, const at::Tensor& campos,
                    int64_t degree) {
  check_params({dc, rest, means, campos});
  const int64_t P = dc.size(0);
  TORCH_CHECK(dc.dim() == 3 && dc.size(1) == 1 && dc.size(2) == 3, "sh_dc must be (P, 1, 3)");
  TORCH_CHECK(rest.dim() == 3 && rest.size(0) == P && rest.size(2) == 3, "sh_rest must be (P, K − 1, 3)");
  TORCH_CHECK(degree >= 0 && degree <= 3 && (degree + 1) * (degree + 1) <= rest.size(1) + 1,
              "the degree needs (degree + 1)² ≤ K coefficients, degree in 0..3");
  TORCH_CHECK(means.sizes() == at::IntArrayRef({P, 3}) && campos.numel() == 3, "means must be (P, 3), campos (3,)");
}

at::Tensor sh_parts_color_forward(const at::Tensor& dc, const at::Tensor& rest, const at::Tensor& means,
                                  const at::Tensor& campos, int64_t degree) {
  check_sh_parts(dc, rest, means, campos, degree);
  const int64_t P = dc.size(0);
  at::Tensor out = at::empty({P, 3}, dc.options());
  AT_DISPATCH_FLOATING_TYPES(dc.scalar_type(), "sh_parts_color_forward", [&] {
    using T = scalar_t;
    const SHParts<T> in{dc.data_ptr<T>(), rest.data_ptr<T>(), means.data_ptr<T>(), campos.data_ptr<T>(), rest.size(1)};
    with_degree<T>(degree, [&](auto d) { sh_parts_forward<T, decltype(d)::value>(in, out.data_ptr<T>(), P); });
  });
  return out;
}

// Gradients for (dc, rest, means); the camera centre's is −Σ_p ∂L/∂μ_p (core/backends/fused.py).
std::vector<at::Tensor> sh_parts_color_backward(const at::Tensor& grad, const at::Tensor& dc, const at::Tensor& rest,
                                                const at::Tensor& means, const at::Tensor& campos, int64_t degree) {
  check_sh_parts(dc, rest, means, campos, degree);
  check_params({grad, dc});
  const int64_t P = dc.size(0);
  TORCH_CHECK(grad.sizes() == at::IntArrayRef({P, 3}), "grad must be (P, 3)");
  at::Tensor g_dc = at::empty_like(dc), g_rest = at::empty_like(rest), g_means = at::empty_like(means);
  AT_DISPATCH_FLOATING_TYPES(dc.scalar_type(), "sh_parts_color_backward", [&] {
    using T = scalar_t;
    const SHParts<T> in{dc.data_ptr<T>(), rest.data_ptr<T>(), means.data_ptr<T>(), campos.data_ptr<T>(), rest.size(1)};
    with_degree<T>(degree, [&](auto d) {
      sh_parts_backward<T, decltype(d)::value>(in, grad.data_ptr<T>(), g_dc.data_ptr<T>(), g_rest.data_ptr<T>(),
                                               g_means.data_ptr<T>(), P);
    });
  });
  return {g_dc, g_rest, g_means};
}

// --- neural primitives: ellipsoid frame and MLP phases ----------------------------------------

template <typename T>
struct NeuralFrame {  // what the forward computes for one primitive, and the backward needs again
  T qn[4], qnorm, R[9], inv_s[3], smax, rel[3], M[9];
};

template <typename T>
void neural_frame(const T* means, const T* log_scales, const T* quats, const T* campos, int64_t p, NeuralFrame<T>& f) {
  const T* q = quats + 4 * p;
  f.qnorm = std::max(std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]), T(1e-12));
  for (int i = 0; i < 4; ++i) f.qn[i] = q[i] / f.qnorm;
  rotmat(f.qn, f.R);
  const T* ls = log_scales + 3 * p;
  for (int i = 0; i < 3; ++i) f.inv_s[i] = std::exp(-ls[i]);
  f.smax = std::exp(std::max({ls[0], ls[1], ls[2]}));
  for (int i = 0; i < 3; ++i) f.rel[i] = campos[i] - means[3 * p + i];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) f.M[3 * i + j] = f.R[3 * j + i] * f.inv_s[i];  // M = S⁻¹Rᵀ
}

// Outputs m_cam (P,3,3), o_ell (P,3), w_cam (P,N,3), c (P,N), inv_smax (P,).
std::vector<at::Tensor> neural_prep_forward(const at::Tensor& means, const at::Tensor& log_scales,
                                            const at::Tensor& quats, const at::Tensor& w1, const at::Tensor& b1,
                                            const at::Tensor& campos, const at::Tensor& cam_rot, double omega0) {
  check_params({means, log_scales, quats, w1, b1, campos, cam_rot});
  const int64_t P = means.size(0), N = b1.size(1);
  TORCH_CHECK(means.sizes() == at::IntArrayRef({P, 3}) && log_scales.sizes() == at::IntArrayRef({P, 3}) &&
                  quats.sizes() == at::IntArrayRef({P, 4}) && w1.sizes() == at::IntArrayRef({P, N, 3}) &&
                  b1.sizes() == at::IntArrayRef({P, N}) && campos.numel() == 3 && cam_rot.numel() == 9,
              "neural_prep: bad shapes");
  at::Tensor m_cam = at::empty({P, 3, 3}, means.options()), o_ell = at::empty({P, 3}, means.options());
  at::Tensor w_cam = at::empty({P, N, 3}, means.options()), c = at::empty({P, N}, means.options());
  at::Tensor inv_smax = at::empty({P}, means.options());
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "neural_prep_forward", [&] {
    using T = scalar_t;
    const T *mu = means.data_ptr<T>(), *ls = log_scales.data_ptr<T>(), *qs = quats.data_ptr<T>();
    const T *W1 = w1.data_ptr<T>(), *B1 = b1.data_ptr<T>(), *o = campos.data_ptr<T>(), *Rc = cam_rot.data_ptr<T>();
    T *mc = m_cam.data_ptr<T>(), *oe = o_ell.data_ptr<T>(), *wc = w_cam.data_ptr<T>(), *cc = c.data_ptr<T>();
    T* is = inv_smax.data_ptr<T>();
    const T om = T(omega0);
    at::parallel_for(0, P, 256, [&](int64_t p0, int64_t p1) {
      NeuralFrame<T> f;
      for (int64_t p = p0; p < p1; ++p) {
        neural_frame(mu, ls, qs, o, p, f);
        for (int i = 0; i < 3; ++i) {
          for (int j = 0; j < 3; ++j)
            mc[9 * p + 3 * i + j] = f.M[3 * i] * Rc[j] + f.M[3 * i + 1] * Rc[3 + j] + f.M[3 * i + 2] * Rc[6 + j];
          oe[3 * p + i] = f.M[3 * i] * f.rel[0] + f.M[3 * i + 1] * f.rel[1] + f.M[3 * i + 2] * f.rel[2];
        }
        const T u0[3] = {f.rel[0] / f.smax, f.rel[1] / f.smax, f.rel[2] / f.smax};
        for (int64_t k = 0; k < N; ++k) {
          const T* wk = W1 + (p * N + k) * 3;
          const T w[3] = {om * wk[0], om * wk[1], om * wk[2]};
          for (int j = 0; j < 3; ++j) wc[(p * N + k) * 3 + j] = w[0] * Rc[j] + w[1] * Rc[3 + j] + w[2] * Rc[6 + j];
          cc[p * N + k] = (w[0] * u0[0] + w[1] * u0[1] + w[2] * u0[2]) + om * B1[p * N + k];
        }
        is[p] = T(1) / f.smax;
      }
    });
  });
  return {m_cam, o_ell, w_cam, c, inv_smax};
}

// Gradients for (means, log_scales, quats, w1, b1) from those of (m_cam, o_ell, w_cam, c, inv_smax).
std::vector<at::Tensor> neural_prep_backward(const at::Tensor& g_m_cam, const at::Tensor& g_o_ell,
                                             const at::Tensor& g_w_cam, const at::Tensor& g_c,
                                             const at::Tensor& g_inv_smax, const at::Tensor& means,
                                             const at::Tensor& log_scales, const at::Tensor& quats,
                                             const at::Tensor& w1, const at::Tensor& b1, const at::Tensor& campos,
                                             const at::Tensor& cam_rot, double omega0) {
  check_params({g_m_cam, g_o_ell, g_w_cam, g_c, g_inv_smax, means, log_scales, quats, w1, b1, campos, cam_rot});
  const int64_t P = means.size(0), N = b1.size(1);
  at::Tensor g_means = at::empty_like(means), g_ls = at::empty_like(log_scales), g_q = at::empty_like(quats);
  at::Tensor g_w1 = at::empty_like(w1), g_b1 = at::empty_like(b1);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "neural_prep_backward", [&] {
    using T = scalar_t;
    const T *mu = means.data_ptr<T>(), *ls = log_scales.data_ptr<T>(), *qs = quats.data_ptr<T>();
    const T *W1 = w1.data_ptr<T>(), *o = campos.data_ptr<T>(), *Rc = cam_rot.data_ptr<T>();
    const T *gmc = g_m_cam.data_ptr<T>(), *goe = g_o_ell.data_ptr<T>(), *gwc = g_w_cam.data_ptr<T>();
    const T *gc = g_c.data_ptr<T>(), *gis = g_inv_smax.data_ptr<T>();
    T *gmu = g_means.data_ptr<T>(), *gls = g_ls.data_ptr<T>(), *gq = g_q.data_ptr<T>();
    T *gw1 = g_w1.data_ptr<T>(), *gb1 = g_b1.data_ptr<T>();
    const T om = T(omega0);
    at::parallel_for(0, P, 256, [&](int64_t p0, int64_t p1) {
      NeuralFrame<T> f;
      for (int64_t p = p0; p < p1; ++p) {
        neural_frame(mu, ls, qs, o, p, f);
        const T* ge = goe + 3 * p;
        // m_cam = M R_cam, o' = M rel
        T gM[9], g_rel[3] = {0, 0, 0};
        for (int i = 0; i < 3; ++i)
          for (int j = 0; j < 3; ++j) {
            const T* gm = gmc + 9 * p + 3 * i;
            gM[3 * i + j] = gm[0] * Rc[3 * j] + gm[1] * Rc[3 * j + 1] + gm[2] * Rc[3 * j + 2] + ge[i] * f.rel[j];
            g_rel[j] += f.M[3 * i + j] * ge[i];
          }
        // w_cam_k = ω0 W1_k R_cam, c_k = ω0 W1_k·rel/smax + ω0 b1_k
        T g_smax = -gis[p] / (f.smax * f.smax);
        for (int64_t k = 0; k < N; ++k) {
          const T* wk = W1 + (p * N + k) * 3;
          const T* gw = gwc + (p * N + k) * 3;
          const T gck = gc[p * N + k];
          T wr = T(0);
          for (int j = 0; j < 3; ++j) {
            const T g_w = gw[0] * Rc[3 * j] + gw[1] * Rc[3 * j + 1] + gw[2] * Rc[3 * j + 2] + gck * f.rel[j] / f.smax;
            gw1[(p * N + k) * 3 + j] = om * g_w;
            g_rel[j] += gck * om * wk[j] / f.smax;
            wr += om * wk[j] * f.rel[j];
          }
          g_smax -= gck * wr / (f.smax * f.smax);
          gb1[p * N + k] = om * gck;
        }
        // M[i][j] = R[j][i] / s_i; s_i = exp(ℓ_i), smax = exp(max ℓ) (amax splits a tie evenly)
        T gR[9];
        const T* l = ls + 3 * p;
        const T lmax = std::max({l[0], l[1], l[2]});
        const int ties = int(l[0] == lmax) + int(l[1] == lmax) + int(l[2] == lmax);
        for (int i = 0; i < 3; ++i) {
          T g_inv = T(0);
          for (int j = 0; j < 3; ++j) {
            gR[3 * j + i] = gM[3 * i + j] * f.inv_s[i];
            g_inv += gM[3 * i + j] * f.R[3 * j + i];
          }
          gls[3 * p + i] = -g_inv * f.inv_s[i] + (l[i] == lmax ? g_smax * f.smax / T(ties) : T(0));
        }
        // R(q̂), q̂ = q/|q|
        T gqn[4];
        rotmat_backward(f.qn, gR, gqn);
        const T dot = gqn[0] * f.qn[0] + gqn[1] * f.qn[1] + gqn[2] * f.qn[2] + gqn[3] * f.qn[3];
        for (int i = 0; i < 4; ++i) gq[4 * p + i] = (gqn[i] - f.qn[i] * dot) / f.qnorm;
        for (int j = 0; j < 3; ++j) gmu[3 * p + j] = -g_rel[j];  // rel = o − μ
      }
    });
  });
  return {g_means, g_ls, g_q, g_w1, g_b1};
}

// --- Gaussians: EWA projection ---------------------------------------------------------------

constexpr double kEwaBlur = 0.3;  // rasterize.EWA_BLUR

template <typename T>
struct EwaCamera {
  T fx, fy, cx, cy, near, lo_x, hi_x, lo_y, hi_y;
  const T* W;  // world-to-camera rotation (3, 3)
};

template <typename T>
EwaCamera<T> ewa_camera(const at::Tensor& w2c_rot, const at::Tensor& intrinsics, int64_t width, int64_t height,
                        double near) {
  const T* k = intrinsics.data_ptr<T>();
  const double fx = double(k[0]), fy = double(k[1]), cx = double(k[2]), cy = double(k[3]);
  // as 3DGS/gsplat: the Jacobian's point is clamped to 1.3× the field of view (rasterize.py)
  const double mx = 0.15 * double(width) / fx, my = 0.15 * double(height) / fy;
  return {k[0], k[1], k[2], k[3], T(near), T(-cx / fx - mx), T((double(width) - cx) / fx + mx),
          T(-cy / fy - my), T((double(height) - cy) / fy + my), w2c_rot.data_ptr<T>()};
}

template <typename T>
struct Ewa {  // one splat's forward quantities, kept for its backward
  T zs, r_x, r_y, tx, ty, J[4], qn[4], qnorm, R[9], rot[9], s[3], rs[9], t[6], a, b, c, det;
};

template <typename T>
void ewa_forward(const EwaCamera<T>& cam, const T* m, const T* ls, const T* q, Ewa<T>& e) {
  e.zs = m[2] > cam.near ? m[2] : T(1);
  e.r_x = m[0] / e.zs, e.r_y = m[1] / e.zs;
  e.tx = e.zs * std::min(std::max(e.r_x, cam.lo_x), cam.hi_x);
  e.ty = e.zs * std::min(std::max(e.r_y, cam.lo_y), cam.hi_y);
  const T zz = e.zs * e.zs;
  e.J[0] = cam.fx / e.zs, e.J[1] = -cam.fx * e.tx / zz, e.J[2] = cam.fy / e.zs, e.J[3] = -cam.fy * e.ty / zz;
  e.qnorm = std::max(std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]), T(1e-12));
  for (int i = 0; i < 4; ++i) e.qn[i] = q[i] / e.qnorm;
  rotmat(e.qn, e.R);
  for (int j = 0; j < 3; ++j) e.s[j] = std::exp(ls[j]);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      e.rot[3 * i + j] = cam.W[3 * i] * e.R[j] + cam.W[3 * i + 1] * e.R[3 + j] + cam.W[3 * i + 2] * e.R[6 + j];
      e.rs[3 * i + j] = e.rot[3 * i + j] * e.s[j];
    }
  // t = J rs with J = [[J0, 0, J1], [0, J2, J3]]
  for (int k = 0; k < 3; ++k) {
    e.t[k] = e.J[0] * e.rs[k] + e.J[1] * e.rs[6 + k];
    e.t[3 + k] = e.J[2] * e.rs[3 + k] + e.J[3] * e.rs[6 + k];
  }
  e.a = e.t[0] * e.t[0] + e.t[1] * e.t[1] + e.t[2] * e.t[2] + T(kEwaBlur);
  e.b = e.t[0] * e.t[3] + e.t[1] * e.t[4] + e.t[2] * e.t[5];
  e.c = e.t[3] * e.t[3] + e.t[4] * e.t[4] + e.t[5] * e.t[5] + T(kEwaBlur);
  e.det = e.a * e.c - e.b * e.b;
}

// Outputs mean2d (P, 2), conic (P, 3), cov (a, b, c) (P, 3).
std::vector<at::Tensor> gaussian_prep_forward(const at::Tensor& means_cam, const at::Tensor& log_scales,
                                              const at::Tensor& quats, const at::Tensor& w2c_rot,
                                              const at::Tensor& intrinsics, int64_t width, int64_t height, double near) {
  check_params({means_cam, log_scales, quats, w2c_rot, intrinsics});
  const int64_t P = means_cam.size(0);
  TORCH_CHECK(means_cam.sizes() == at::IntArrayRef({P, 3}) && log_scales.sizes() == at::IntArrayRef({P, 3}) &&
                  quats.sizes() == at::IntArrayRef({P, 4}) && w2c_rot.numel() == 9 && intrinsics.numel() >= 4,
              "gaussian_prep: bad shapes");
  at::Tensor mean2d = at::empty({P, 2}, means_cam.options()), conic = at::empty({P, 3}, means_cam.options());
  at::Tensor cov = at::empty({P, 3}, means_cam.options());
  AT_DISPATCH_FLOATING_TYPES(means_cam.scalar_type(), "gaussian_prep_forward", [&] {
    using T = scalar_t;
    const EwaCamera<T> cam = ewa_camera<T>(w2c_rot, intrinsics, width, height, near);
    const T *mc = means_cam.data_ptr<T>(), *ls = log_scales.data_ptr<T>(), *qs = quats.data_ptr<T>();
    T *m2 = mean2d.data_ptr<T>(), *cn = conic.data_ptr<T>(), *cv = cov.data_ptr<T>();
    at::parallel_for(0, P, 512, [&](int64_t p0, int64_t p1) {
      Ewa<T> e;
      for (int64_t p = p0; p < p1; ++p) {
        const T* m = mc + 3 * p;
        ewa_forward(cam, m, ls + 3 * p, qs + 4 * p, e);
        cn[3 * p] = e.c / e.det, cn[3 * p + 1] = -e.b / e.det, cn[3 * p + 2] = e.a / e.det;
        cv[3 * p] = e.a, cv[3 * p + 1] = e.b, cv[3 * p + 2] = e.c;
        m2[2 * p] = cam.fx * m[0] / e.zs + cam.cx, m2[2 * p + 1] = cam.fy * m[1] / e.zs + cam.cy;
      }
    });
  });
  return {mean2d, conic, cov};
}

// Gradients for (means_cam, log_scales, quats) from those of (mean2d, conic).
std::vector<at::Tensor> gaussian_prep_backward(const at::Tensor& g_mean2d, const at::Tensor& g_conic,
                                               const at::Tensor& means_cam, const at::Tensor& log_scales,
                                               const at::Tensor& quats, const at::Tensor& w2c_rot,
                                               const at::Tensor& intrinsics, int64_t width, int64_t height,
                                               double near) {
  check_params({g_mean2d, g_conic, means_cam, log_scales, quats, w2c_rot, intrinsics});
  const int64_t P = means_cam.size(0);
  at::Tensor g_m = at::empty_like(means_cam), g_ls = at::empty_like(log_scales), g_q = at::empty_like(quats);
  AT_DISPATCH_FLOATING_TYPES(means_cam.scalar_type(), "gaussian_prep_backward", [&] {
    using T = scalar_t;
    const EwaCamera<T> cam = ewa_camera<T>(w2c_rot, intrinsics, width, height, near);
    const T *mc = means_cam.data_ptr<T>(), *ls = log_scales.data_ptr<T>(), *qs = quats.data_ptr<T>();
    const T *gm2 = g_mean2d.data_ptr<T>(), *gcn = g_conic.data_ptr<T>();
    T *gmc = g_m.data_ptr<T>(), *gls = g_ls.data_ptr<T>(), *gq = g_q.data_ptr<T>();
    at::parallel_for(0, P, 512, [&](int64_t p0, int64_t p1) {
      Ewa<T> e;
      for (int64_t p = p0; p < p1; ++p) {
        const T* m = mc + 3 * p;
        ewa_forward(cam, m, ls + 3 * p, qs + 4 * p, e);
        const T* gc = gcn + 3 * p;
        // conic = (c, −b, a) / det, det = a c − b²
        const T d2 = e.det * e.det;
        const T g_det = -(gc[0] * e.c - gc[1] * e.b + gc[2] * e.a) / d2;
        const T g_a = gc[2] / e.det + g_det * e.c, g_c = gc[0] / e.det + g_det * e.a;
        const T g_b = -gc[1] / e.det - T(2) * e.b * g_det;
        // cov = t tᵀ, read at (0,0), (0,1), (1,1)
        T g_t[6];
        for (int k = 0; k < 3; ++k) {
          g_t[k] = T(2) * g_a * e.t[k] + g_b * e.t[3 + k];
          g_t[3 + k] = g_b * e.t[k] + T(2) * g_c * e.t[3 + k];
        }
        // t = J rs
        T g_J[4] = {0, 0, 0, 0}, g_rs[9];
        for (int k = 0; k < 3; ++k) {
          g_J[0] += g_t[k] * e.rs[k];
          g_J[1] += g_t[k] * e.rs[6 + k];
          g_J[2] += g_t[3 + k] * e.rs[3 + k];
          g_J[3] += g_t[3 + k] * e.rs[6 + k];
          g_rs[k] = e.J[0] * g_t[k];
          g_rs[3 + k] = e.J[2] * g_t[3 + k];
          g_rs[6 + k] = e.J[1] * g_t[k] + e.J[3] * g_t[3 + k];
        }
        // rs = rot diag(s), rot = W R(q̂), s = exp(ℓ)
        T g_R[9];
        for (int j = 0; j < 3; ++j) {
          T g_s = T(0);
          for (int i = 0; i < 3; ++i) g_s += g_rs[3 * i + j] * e.rot[3 * i + j];
          gls[3 * p + j] = g_s * e.s[j];
          for (int i = 0; i < 3; ++i)  // (Wᵀ g_rot)_ij, g_rot = g_rs diag(s)
            g_R[3 * i + j] = (cam.W[i] * g_rs[j] + cam.W[3 + i] * g_rs[3 + j] + cam.W[6 + i] * g_rs[6 + j]) * e.s[j];
        }
        T gqn[4];
        rotmat_backward(e.qn, g_R, gqn);
        const T dot = gqn[0] * e.qn[0] + gqn[1] * e.qn[1] + gqn[2] * e.qn[2] + gqn[3] * e.qn[3];
        for (int i = 0; i < 4; ++i) gq[4 * p + i] = (gqn[i] - e.qn[i] * dot) / e.qnorm;
        // J = [[fx/zs, 0, −fx tx/zs²], [0, fy/zs, −fy ty/zs²]], tx = zs clamp(x/zs), mean2d = f x/zs + c
        const T zs = e.zs, zz = zs * zs, zzz = zz * zs;
        const T* g2 = gm2 + 2 * p;
        const T g_tx = -cam.fx * g_J[1] / zz, g_ty = -cam.fy * g_J[3] / zz;
        T g_zs = -cam.fx * g_J[0] / zz + T(2) * cam.fx * e.tx * g_J[1] / zzz - cam.fy * g_J[2] / zz +
                 T(2) * cam.fy * e.ty * g_J[3] / zzz;
        const T cl_x = std::min(std::max(e.r_x, cam.lo_x), cam.hi_x), cl_y = std::min(std::max(e.r_y, cam.lo_y), cam.hi_y);
        g_zs += cl_x * g_tx + cl_y * g_ty;
        const T g_rx = (e.r_x >= cam.lo_x && e.r_x <= cam.hi_x) ? zs * g_tx : T(0);  // clamp passes at equality
        const T g_ry = (e.r_y >= cam.lo_y && e.r_y <= cam.hi_y) ? zs * g_ty : T(0);
        const T g_x = g_rx / zs + cam.fx * g2[0] / zs, g_y = g_ry / zs + cam.fy * g2[1] / zs;
        g_zs -= (g_rx * m[0] + cam.fx * m[0] * g2[0] + g_ry * m[1] + cam.fy * m[1] * g2[1]) / zz;
        gmc[3 * p] = g_x, gmc[3 * p + 1] = g_y, gmc[3 * p + 2] = m[2] > cam.near ? g_zs : T(0);
      }
    });
  });
  return {g_m, g_ls, g_q};
}

// --- pixel bounds and depth order (no gradient) ---------------------------------------------

// Integer pixel box (x0, y0, x1, y1) of the centres inside [lo_u, hi_u] × [lo_v, hi_v] as
// rasterize._conic_box: first/last centres j + 0.5 inside, NaN → −1, clamped to ±(max(W, H) + 1).
template <typename T>
void pixel_box(T u0, T v0, T u1, T v1, int64_t width, int64_t height, int64_t* box) {
  const T big = T(std::max(width, height) + 1);
  const T raw[4] = {std::ceil(u0 - T(0.5)), std::ceil(v0 - T(0.5)), std::floor(u1 - T(0.5)), std::floor(v1 - T(0.5))};
  for (int i = 0; i < 4; ++i) box[i] = int64_t(std::isnan(raw[i]) ? T(-1) : std::min(std::max(raw[i], -big), big));
}

// Clip a box to the image (rasterize._clip_bounds); false when nothing is left.
inline bool clip_box(int64_t* b, int64_t width, int64_t height) {
  b[0] = std::max<int64_t>(b[0], 0), b[1] = std::max<int64_t>(b[1], 0);
  b[2] = std::min<int64_t>(b[2], width - 1), b[3] = std::min<int64_t>(b[3], height - 1);
  return b[2] >= b[0] && b[3] >= b[1];
}

// An unsigned key with the order of the float's value: flip every bit of a negative number, only
// the sign bit of a positive one (−0 is made +0 first, as < sees them equal). Not for NaN (the
// visible primitives' depths are finite: NaN fails every visibility test).
inline uint32_t order_key(float x) {
  uint32_t bits;
  x = x == 0.0f ? 0.0f : x;
  std::memcpy(&bits, &x, sizeof bits);
  return bits & 0x80000000u ? ~bits : bits | 0x80000000u;
}

inline uint64_t order_key(double x) {
  uint64_t bits;
  x = x == 0.0 ? 0.0 : x;
  std::memcpy(&bits, &x, sizeof bits);
  return bits & 0x8000000000000000ull ? ~bits : bits | 0x8000000000000000ull;
}

// The visible primitives' indices sorted by depth, ties in index order (torch.argsort(stable=True)):
// a least-significant-digit radix sort of the depth keys, 8 bits a pass, which is stable and, with
// the indices entering in increasing order, breaks ties by index (a comparison sort of 10k
// indirect keys cost ~1 ms a view). Passes whose digit is the same for every key are skipped.
template <typename T>
at::Tensor depth_order(const std::vector<uint8_t>& visible, const T* depth, const at::TensorOptions& options) {
  using Key = decltype(order_key(T(0)));
  std::vector<std::pair<Key, int64_t>> items, spare;
  for (int64_t p = 0; p < int64_t(visible.size()); ++p)
    if (visible[p]) items.emplace_back(order_key(depth[p]), p);
  spare.resize(items.size());
  for (int shift = 0; shift < int(8 * sizeof(Key)); shift += 8) {
    std::array<int64_t, 257> start{};
    for (const auto& item : items) ++start[((item.first >> shift) & 0xFF) + 1];
    if (std::any_of(start.begin() + 1, start.end(), [&](int64_t n) { return n == int64_t(items.size()); })) continue;
    for (int d = 0; d < 256; ++d) start[d + 1] += start[d];
    for (const auto& item : items) spare[start[(item.first >> shift) & 0xFF]++] = item;
    items.swap(spare);
  }
  at::Tensor order = at::empty({int64_t(items.size())}, options.dtype(at::kLong));
  int64_t* out = order.data_ptr<int64_t>();
  for (size_t i = 0; i < items.size(); ++i) out[i] = items[i].second;
  return order;
}

// Neural primitives: bounds of the projected bounding ellipsoid from its dual conic
// C* = K (μμᵀ − Σ) Kᵀ (camera frame, Σ = R S² Rᵀ); the whole image for one straddling the near
// plane; visible when some of it lies beyond the near plane and its box meets the image.
// Returns bounds (P, 4) int64 and order (V,) int64.
std::vector<at::Tensor> neural_bounds(const at::Tensor& means_cam, const at::Tensor& log_scales, const at::Tensor& quats,
                                      const at::Tensor& w2c_rot, const at::Tensor& intrinsics, int64_t width,
                                      int64_t height, double near) {
  check_params({means_cam, log_scales, quats, w2c_rot, intrinsics});
  const int64_t P = means_cam.size(0);
  TORCH_CHECK(means_cam.sizes() == at::IntArrayRef({P, 3}) && log_scales.sizes() == at::IntArrayRef({P, 3}) &&
                  quats.sizes() == at::IntArrayRef({P, 4}) && w2c_rot.numel() == 9 && intrinsics.numel() >= 4,
              "neural_bounds: bad shapes");
  at::Tensor bounds = at::empty({P, 4}, means_cam.options().dtype(at::kLong));
  std::vector<uint8_t> visible(P);
  at::Tensor order;
  AT_DISPATCH_FLOATING_TYPES(means_cam.scalar_type(), "neural_bounds", [&] {
    using T = scalar_t;
    const T *mc = means_cam.data_ptr<T>(), *ls = log_scales.data_ptr<T>(), *qs = quats.data_ptr<T>();
    const T *W = w2c_rot.data_ptr<T>(), *k = intrinsics.data_ptr<T>();
    const T fx = k[0], fy = k[1], cx = k[2], cy = k[3];
    int64_t* bp = bounds.data_ptr<int64_t>();
    at::parallel_for(0, P, 1024, [&](int64_t p0, int64_t p1) {
      for (int64_t p = p0; p < p1; ++p) {
        const T* q = qs + 4 * p;
        const T qn = std::max(std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]), T(1e-12));
        const T unit[4] = {q[0] / qn, q[1] / qn, q[2] / qn, q[3] / qn};
        T R[9], rs[9], S[9];
        rotmat(unit, R);
        for (int i = 0; i < 3; ++i)  // rs = (W2C R) diag(s)
          for (int j = 0; j < 3; ++j) rs[3 * i + j] = (W[3 * i] * R[j] + W[3 * i + 1] * R[3 + j] + W[3 * i + 2] * R[6 + j]) * std::exp(ls[3 * p + j]);
        for (int i = 0; i < 3; ++i)
          for (int j = 0; j < 3; ++j) S[3 * i + j] = rs[3 * i] * rs[3 * j] + rs[3 * i + 1] * rs[3 * j + 1] + rs[3 * i + 2] * rs[3 * j + 2];
        const T* m = mc + 3 * p;
        const T z_ext = std::sqrt(S[8]), z = m[2];
        const bool in_front = z - z_ext > T(near);
        bool vis = z + z_ext > T(near);
        int64_t* b = bp + 4 * p;
        if (in_front) {
          T A[9], D[9];  // A = μμᵀ − Σ, D = K A Kᵀ
          for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) A[3 * i + j] = m[i] * m[j] - S[3 * i + j];
          const T K[9] = {fx, 0, cx, 0, fy, cy, 0, 0, 1};
          T KA[9];
          for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) KA[3 * i + j] = K[3 * i] * A[j] + K[3 * i + 1] * A[3 + j] + K[3 * i + 2] * A[6 + j];
          for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) D[3 * i + j] = KA[3 * i] * K[3 * j] + KA[3 * i + 1] * K[3 * j + 1] + KA[3 * i + 2] * K[3 * j + 2];
          // tangent lines u = const: C*_00 − 2u C*_02 + u² C*_22 = 0 (likewise v)
          T lo[2], hi[2];
          for (int i = 0; i < 2; ++i) {
            const T cii = D[4 * i], ci2 = D[3 * i + 2], c22 = D[8];
            const T root = std::sqrt(std::max(ci2 * ci2 - cii * c22, T(0)));
            const T a = (ci2 + root) / c22, c = (ci2 - root) / c22;
            lo[i] = std::isnan(a) || std::isnan(c) ? a + c : std::min(a, c);
            hi[i] = std::isnan(a) || std::isnan(c) ? a + c : std::max(a, c);
          }
          pixel_box(lo[0], lo[1], hi[0], hi[1], width, height, b);
        } else {
          b[0] = 0, b[1] = 0, b[2] = width - 1, b[3] = height - 1;
        }
        visible[p] = vis && clip_box(b, width, height);
      }
    });
    std::vector<T> z(P);
    for (int64_t p = 0; p < P; ++p) z[p] = mc[3 * p + 2];
    order = depth_order(visible, z.data(), means_cam.options());
  });
  return {bounds, order};
}

// Gaussians: the 3σ box of the EWA splat (the largest eigenvalue of its 2D covariance (a, b, c),
// blur included), visible when in front of the near plane with det > 0 and its box meets the
// image; the same float operations in the same order as rasterize._gaussian_view.
std::vector<at::Tensor> gaussian_bounds(const at::Tensor& mean2d, const at::Tensor& cov, const at::Tensor& depth,
                                        int64_t width, int64_t height, double near) {
  check_params({mean2d, cov, depth});
  const int64_t P = mean2d.size(0);
  TORCH_CHECK(mean2d.sizes() == at::IntArrayRef({P, 2}) && cov.sizes() == at::IntArrayRef({P, 3}) &&
                  depth.sizes() == at::IntArrayRef({P}),
              "gaussian_bounds: mean2d (P, 2), cov (P, 3), depth (P,)");
  at::Tensor bounds = at::empty({P, 4}, mean2d.options().dtype(at::kLong));
  std::vector<uint8_t> visible(P);
  at::Tensor order;
  AT_DISPATCH_FLOATING_TYPES(mean2d.scalar_type(), "gaussian_bounds", [&] {
    using T = scalar_t;
    const T *m = mean2d.data_ptr<T>(), *cv = cov.data_ptr<T>(), *z = depth.data_ptr<T>();
    int64_t* bp = bounds.data_ptr<int64_t>();
    at::parallel_for(0, P, 1024, [&](int64_t p0, int64_t p1) {
      for (int64_t p = p0; p < p1; ++p) {
        const T a = cv[3 * p], b = cv[3 * p + 1], c = cv[3 * p + 2];
        const T det = a * c - b * b;
        const T d = a - c;
        const T lam_max = T(0.5) * (a + c) + std::sqrt(std::max(T(0.25) * (d * d) + b * b, T(0)));
        const T radius = std::ceil(T(3) * std::sqrt(lam_max));
        const T u = m[2 * p], v = m[2 * p + 1];
        int64_t* box = bp + 4 * p;
        pixel_box(u - radius, v - radius, u + radius, v + radius, width, height, box);
        visible[p] = z[p] > T(near) && det > T(0) && clip_box(box, width, height);
      }
    });
    order = depth_order(visible, z, mean2d.options());
  });
  return {bounds, order};
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(radfield, m) {
  m.def("sh_color_forward", &sh_color_forward);
  m.def("sh_color_backward", &sh_color_backward);
  m.def("sh_parts_color_forward", &sh_parts_color_forward);
  m.def("sh_parts_color_backward", &sh_parts_color_backward);
  m.def("neural_prep_forward", &neural_prep_forward);
  m.def("neural_prep_backward", &neural_prep_backward);
  m.def("gaussian_prep_forward", &gaussian_prep_forward);
  m.def("gaussian_prep_backward", &gaussian_prep_backward);
  m.def("neural_bounds", &neural_bounds);
  m.def("gaussian_bounds", &gaussian_bounds);
}
