// The relightable kinds' colour of a view in C++, forward and backward: one fused op for what
// core/kinds/relight.py: view_sh computes in torch (its readable twin; tests/test_relight_fused.py
// compares them and gradchecks this op in float64). In torch it is some forty small ops over
// (P, …) tensors and their autograd, which cost a training step at 64×64 as much as the static
// kind's whole step.
//
//   relight_view_dc: per primitive p, for the SH of degree 0 (the kinds train degree 0),
//     d = normalise(μ − o),  R = R(q̂),  x = [Rᵀd, Rᵀd_l]           (the primitive's own frame)
//     d_l = normalise(p_l − μ), E = I / |p_l − μ|²   (point light)
//     d_l = −direction,         E = I                (directional light)
//     h = softplus(W1 x + b1),  c = (C0 sh_0 + 0.5 + W2 h + b2) · E    (Splat the Net eq. 14)
//     DC = (c − 0.5) / C0        (the degree-0 SH that core/splat/sh.py draws as c)
//   The forward also returns the hidden units and their softplus slopes (P, H each), so that the
//   backward computes no transcendental function (it recomputes the geometry: square roots only).
//
// Threads: OpenMP over primitives (each primitive's gradient is its own).

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <vector>

#include "pair_kernels.h"

namespace {

using radfield::check_params;
using radfield::rotmat;
using radfield::rotmat_backward;

constexpr double C0 = 0.28209479177387814;   // Y_0 (core/splat/sh.py)
constexpr double SOFTPLUS_THRESHOLD = 20;    // torch's softplus is the identity above it

// out = v / max(|v|, 1e-12) (torch.nn.functional.normalize) of an n-vector; returns the divisor
template <typename T, int n>
T normalise(const T* v, T* out) {
  T sq = 0;
  for (int i = 0; i < n; ++i) sq += v[i] * v[i];
  const T norm = std::max(std::sqrt(sq), T(1e-12));
  for (int i = 0; i < n; ++i) out[i] = v[i] / norm;
  return norm;
}

// g_v += ∂L/∂v of out = normalise(v), from g_out: (g − out (out·g)) / |v| (g / 1e-12 where clamped)
template <typename T, int n>
void normalise_backward(const T* out, T norm, bool clamped, const T* g, T* g_v) {
  T dot = 0;
  for (int i = 0; i < n; ++i) dot += out[i] * g[i];
  for (int i = 0; i < n; ++i) g_v[i] += clamped ? g[i] / norm : (g[i] - out[i] * dot) / norm;
}

template <typename T>
struct RelightInputs {
  const T *means, *quats, *sh, *w1, *b1, *w2, *b2, *campos, *light;   // light: position or direction
  bool point;
  T intensity;
  int64_t H;
};

// The geometry of one primitive in this view and light, which the forward computes and the
// backward computes again (square roots only: cheaper than reading it back).
template <typename T>
struct RelightFrame {
  T qnorm, qn[4], R[9];
  T vnorm, d[3];        // d = normalise(μ − o)
  T to_light[3], r2, r, d_l[3], E;
  T x[6];               // [Rᵀd, Rᵀd_l]: the network's input
};

template <typename T>
void relight_frame(const RelightInputs<T>& in, int64_t p, RelightFrame<T>& f) {
  f.qnorm = normalise<T, 4>(in.quats + 4 * p, f.qn);
  rotmat(f.qn, f.R);
  const T* mu = in.means + 3 * p;
  const T v[3] = {mu[0] - in.campos[0], mu[1] - in.campos[1], mu[2] - in.campos[2]};
  f.vnorm = normalise<T, 3>(v, f.d);
  if (in.point) {
    for (int i = 0; i < 3; ++i) f.to_light[i] = in.light[i] - mu[i];
    f.r2 = f.to_light[0] * f.to_light[0] + f.to_light[1] * f.to_light[1] + f.to_light[2] * f.to_light[2];
    f.r = std::sqrt(f.r2);
    for (int i = 0; i < 3; ++i) f.d_l[i] = f.to_light[i] / f.r;
    f.E = in.intensity / f.r2;   // 1/r² falloff
  } else {
    for (int i = 0; i < 3; ++i) f.d_l[i] = -in.light[i];   // the light shines along `direction`
    f.E = in.intensity;
  }
  for (int i = 0; i < 3; ++i) {   // Rᵀ: the primitive's own frame
    f.x[i] = f.R[i] * f.d[0] + f.R[3 + i] * f.d[1] + f.R[6 + i] * f.d[2];
    f.x[3 + i] = f.R[i] * f.d_l[0] + f.R[3 + i] * f.d_l[1] + f.R[6 + i] * f.d_l[2];
  }
}

// pre (H,) = W1 x + b1 of primitive p
template <typename T>
void pre_activations(const RelightInputs<T>& in, int64_t p, const RelightFrame<T>& f, T* pre) {
  const T *W1 = in.w1 + p * in.H * 6, *B1 = in.b1 + p * in.H;
  for (int64_t k = 0; k < in.H; ++k) {
    T z = 0;
    for (int c = 0; c < 6; ++c) z += W1[6 * k + c] * f.x[c];
    pre[k] = z + B1[k];
  }
}

// hidden = softplus(pre) and slope = its derivative σ(pre) over n values in SIMD (Sleef exp and
// log1p, as torch's softplus: log1p(e^x), and x above the threshold; its backward's e^x/(e^x + 1))
template <typename T>
void simd_softplus(const T* pre, T* hidden, T* slope, int64_t n) {
  using V = at::vec::Vectorized<T>;
  const V threshold = V(T(SOFTPLUS_THRESHOLD)), one = V(T(1));
  for (int64_t i = 0; i < n; i += V::size()) {
    const int64_t count = std::min<int64_t>(V::size(), n - i);
    const V x = V::loadu(pre + i, count), z = x.exp();
    const V above = x > threshold;
    V::blendv(z.log1p(), x, above).store(hidden + i, count);
    V::blendv(z / (z + one), one, above).store(slope + i, count);
  }
}

// c_dc + c_θ = C0 sh_0 + 0.5 + W2 h + b2 (eq. 14), before the irradiance
template <typename T>
void base_colour(const RelightInputs<T>& in, int64_t p, const T* hidden, T* base) {
  const T *W2 = in.w2 + p * 3 * in.H, *B2 = in.b2 + 3 * p;
  for (int ch = 0; ch < 3; ++ch) {
    T net = 0;
    for (int64_t k = 0; k < in.H; ++k) net += W2[ch * in.H + k] * hidden[k];
    base[ch] = (in.sh[3 * p + ch] * T(C0) + T(0.5)) + (net + B2[ch]);
  }
}

template <typename T>
RelightInputs<T> relight_inputs(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& sh,
                                const at::Tensor& w1, const at::Tensor& b1, const at::Tensor& w2, const at::Tensor& b2,
                                const at::Tensor& campos, const at::Tensor& light, bool point, double intensity) {
  return {means.data_ptr<T>(), quats.data_ptr<T>(), sh.data_ptr<T>(), w1.data_ptr<T>(), b1.data_ptr<T>(),
          w2.data_ptr<T>(), b2.data_ptr<T>(), campos.data_ptr<T>(), light.data_ptr<T>(), point, T(intensity),
          b1.size(1)};
}

void check_relight(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& sh, const at::Tensor& w1,
                   const at::Tensor& b1, const at::Tensor& w2, const at::Tensor& b2, const at::Tensor& campos,
                   const at::Tensor& light) {
  check_params({means, quats, sh, w1, b1, w2, b2, campos, light});
  const int64_t P = means.size(0), H = b1.size(1);
  TORCH_CHECK(means.sizes() == at::IntArrayRef({P, 3}) && quats.sizes() == at::IntArrayRef({P, 4}) &&
                  sh.sizes() == at::IntArrayRef({P, 1, 3}) && w1.sizes() == at::IntArrayRef({P, H, 6}) &&
                  b1.sizes() == at::IntArrayRef({P, H}) && w2.sizes() == at::IntArrayRef({P, 3, H}) &&
                  b2.sizes() == at::IntArrayRef({P, 3}) && campos.numel() == 3 && light.numel() == 3,
              "relight_view_dc: bad shapes (sh must be degree 0: (P, 1, 3))");
}

constexpr int64_t BLOCK = 64;   // primitives whose hidden units go through the SIMD softplus at once

// (the degree-0 SH (P, 1, 3) of each primitive's colour in this view, and for the backward the
// hidden units (P, H) and their softplus slopes (P, H))
std::vector<at::Tensor> relight_view_dc_forward(const at::Tensor& means, const at::Tensor& quats,
                                                const at::Tensor& sh, const at::Tensor& w1, const at::Tensor& b1,
                                                const at::Tensor& w2, const at::Tensor& b2, const at::Tensor& campos,
                                                const at::Tensor& light, bool point, double intensity) {
  check_relight(means, quats, sh, w1, b1, w2, b2, campos, light);
  const int64_t P = means.size(0), H = b1.size(1);
  at::Tensor out = at::empty({P, 1, 3}, means.options());
  at::Tensor hidden = at::empty({P, H}, means.options()), slope = at::empty({P, H}, means.options());
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "relight_view_dc_forward", [&] {
    using T = scalar_t;
    const auto in = relight_inputs<T>(means, quats, sh, w1, b1, w2, b2, campos, light, point, intensity);
    T *o = out.data_ptr<T>(), *hid = hidden.data_ptr<T>(), *slo = slope.data_ptr<T>();
    at::parallel_for(0, P, 256, [&](int64_t p0, int64_t p1) {
      std::vector<T> pre(BLOCK * H);
      std::vector<T> irradiance(BLOCK);
      RelightFrame<T> f;
      for (int64_t b0 = p0; b0 < p1; b0 += BLOCK) {
        const int64_t b1_ = std::min(b0 + BLOCK, p1);
        for (int64_t p = b0; p < b1_; ++p) {
          relight_frame(in, p, f);
          pre_activations(in, p, f, pre.data() + (p - b0) * H);
          irradiance[p - b0] = f.E;
        }
        simd_softplus(pre.data(), hid + b0 * H, slo + b0 * H, (b1_ - b0) * H);
        for (int64_t p = b0; p < b1_; ++p) {
          T base[3];
          base_colour(in, p, hid + p * H, base);
          for (int ch = 0; ch < 3; ++ch) o[3 * p + ch] = (base[ch] * irradiance[p - b0] - T(0.5)) / T(C0);   // DC
        }
      }
    });
  });
  return {out, hidden, slope};
}

// Gradients for (means, quats, sh, w1, b1, w2, b2), and with want_view the part of the means'
// gradient that comes through d (∂L/∂v, v = μ − o: the camera centre's is its negated sum), from
// the forward's hidden units and slopes.
std::vector<at::Tensor> relight_view_dc_backward(const at::Tensor& grad, const at::Tensor& means,
                                                 const at::Tensor& quats, const at::Tensor& sh, const at::Tensor& w1,
                                                 const at::Tensor& b1, const at::Tensor& w2, const at::Tensor& b2,
                                                 const at::Tensor& campos, const at::Tensor& light,
                                                 const at::Tensor& hidden, const at::Tensor& slope, bool point,
                                                 double intensity, bool want_view) {
  check_relight(means, quats, sh, w1, b1, w2, b2, campos, light);
  check_params({grad, means, hidden, slope});
  const int64_t P = means.size(0), H = b1.size(1);
  TORCH_CHECK(grad.sizes() == at::IntArrayRef({P, 1, 3}) && hidden.sizes() == b1.sizes() &&
                  slope.sizes() == b1.sizes(), "relight_view_dc: grad must be (P, 1, 3), hidden and slope (P, H)");
  at::Tensor g_means = at::empty_like(means), g_quats = at::empty_like(quats), g_sh = at::empty_like(sh);
  at::Tensor g_w1 = at::empty_like(w1), g_b1 = at::empty_like(b1), g_w2 = at::empty_like(w2), g_b2 = at::empty_like(b2);
  at::Tensor g_view = want_view ? at::empty_like(means) : at::empty({0, 3}, means.options());
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "relight_view_dc_backward", [&] {
    using T = scalar_t;
    const auto in = relight_inputs<T>(means, quats, sh, w1, b1, w2, b2, campos, light, point, intensity);
    const T *g = grad.data_ptr<T>(), *hid = hidden.data_ptr<T>(), *slo = slope.data_ptr<T>();
    T *gm = g_means.data_ptr<T>(), *gq = g_quats.data_ptr<T>(), *gs = g_sh.data_ptr<T>();
    T *gw1 = g_w1.data_ptr<T>(), *gb1 = g_b1.data_ptr<T>(), *gw2 = g_w2.data_ptr<T>(), *gb2 = g_b2.data_ptr<T>();
    T* gv_out = want_view ? g_view.data_ptr<T>() : nullptr;
    at::parallel_for(0, P, 256, [&](int64_t p0, int64_t p1) {
      RelightFrame<T> f;
      for (int64_t p = p0; p < p1; ++p) {
        relight_frame(in, p, f);
        const T *W1 = in.w1 + p * H * 6, *W2 = in.w2 + p * 3 * H, *h = hid + p * H, *s = slo + p * H;
        T base[3];
        base_colour(in, p, h, base);
        // DC = (base · E − 0.5) / C0
        T g_base[3], g_E = 0;
        for (int ch = 0; ch < 3; ++ch) {
          const T g_colour = g[3 * p + ch] / T(C0);
          g_base[ch] = g_colour * f.E;
          g_E += g_colour * base[ch];
          gs[3 * p + ch] = g_base[ch] * T(C0);
          gb2[3 * p + ch] = g_base[ch];
        }
        // the network: W2 h, softplus, W1 x
        T g_x[6] = {0, 0, 0, 0, 0, 0};
        for (int64_t k = 0; k < H; ++k) {
          T g_h = 0;
          for (int ch = 0; ch < 3; ++ch) {
            gw2[(p * 3 + ch) * H + k] = g_base[ch] * h[k];
            g_h += W2[ch * H + k] * g_base[ch];
          }
          const T g_pre = g_h * s[k];
          gb1[p * H + k] = g_pre;
          for (int c = 0; c < 6; ++c) {
            gw1[(p * H + k) * 6 + c] = g_pre * f.x[c];
            g_x[c] += W1[6 * k + c] * g_pre;
          }
        }
        // x = [Rᵀd, Rᵀd_l]
        T g_R[9], g_d[3], g_dl[3];
        for (int j = 0; j < 3; ++j) {
          for (int i = 0; i < 3; ++i) g_R[3 * j + i] = g_x[i] * f.d[j] + g_x[3 + i] * f.d_l[j];
          g_d[j] = f.R[3 * j] * g_x[0] + f.R[3 * j + 1] * g_x[1] + f.R[3 * j + 2] * g_x[2];
          g_dl[j] = f.R[3 * j] * g_x[3] + f.R[3 * j + 1] * g_x[4] + f.R[3 * j + 2] * g_x[5];
        }
        T g_qn[4], g_q[4] = {0, 0, 0, 0};
        rotmat_backward(f.qn, g_R, g_qn);
        normalise_backward<T, 4>(f.qn, f.qnorm, f.qnorm == T(1e-12), g_qn, g_q);
        for (int i = 0; i < 4; ++i) gq[4 * p + i] = g_q[i];
        // d = normalise(μ − o)
        T g_v[3] = {0, 0, 0};
        normalise_backward<T, 3>(f.d, f.vnorm, f.vnorm == T(1e-12), g_d, g_v);
        for (int i = 0; i < 3; ++i) gm[3 * p + i] = g_v[i];
        if (gv_out != nullptr)
          for (int i = 0; i < 3; ++i) gv_out[3 * p + i] = g_v[i];
        if (in.point) {   // d_l = t / r, E = I / r², t = p_l − μ
          T g_t[3] = {0, 0, 0};
          normalise_backward<T, 3>(f.d_l, f.r, false, g_dl, g_t);
          const T g_r2 = -g_E * f.E / f.r2;   // ∂(I/r²)/∂r² = −E/r²
          for (int i = 0; i < 3; ++i) gm[3 * p + i] -= g_t[i] + g_r2 * 2 * f.to_light[i];
        }
      }
    });
  });
  return {g_means, g_quats, g_sh, g_w1, g_b1, g_w2, g_b2, g_view};
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(radfield, m) {
  m.def("relight_view_dc_forward", &relight_view_dc_forward);
  m.def("relight_view_dc_backward", &relight_view_dc_backward);
}
