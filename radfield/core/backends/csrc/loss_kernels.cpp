// The training loss's image term and regulariser in C++, forward and backward, whose readable
// torch twins stay in core/train/losses.py (tests/test_fused.py compares them and gradchecks these ops
// in float64). In torch, SSIM is 5 separable blurs (10 grouped convolutions) and some 30
// elementwise ops forward, twice that backward: more than a whole 256×256 render.
//
//   ssim_map: the SSIM map of Wang et al. 2004 with the 11-tap Gaussian window w (separable),
//     μ = w ∗ x, σ² = w ∗ x² − μ², σ_xy = w ∗ (x y) − μ_x μ_y,
//     S = (2 μ_x μ_y + C1)(2 σ_xy + C2) / ((μ_x² + μ_y² + C1)(σ_x² + σ_y² + C2)),
//   over images (B, H, W, C) channel-last, zero padding `pad` (0: "valid", 5: "same"), giving
//   (B, Ho, Wo, C). The backward differentiates w.r.t. x only (y is the photo) and uses the
//   adjoint of the blur: the same symmetric taps, scattered back from the output window.
//   photometric: the training step's image loss (1 − λ) L1 + λ D-SSIM ("same" map, no mask) in
//     one op, forward and backward (its twin: the composition in losses.photometric).
//   anisotropy: Splat the Net's std(s / min(s)) per primitive (Bessel-corrected), averaged.
//
// Threads: over image planes (b, c) for SSIM, over primitives for the regulariser.

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <vector>

#include "pair_kernels.h"

namespace {

using radfield::check_params;

constexpr int64_t kTaps = 11;

struct Plane {
  int64_t H, W, C, pad, Ho, Wo;
  int64_t at(int64_t r, int64_t col) const { return (r * W + col) * C; }  // channel-last offset, without c
};

Plane plane_of(const at::Tensor& x, int64_t pad) {
  const int64_t H = x.size(1), W = x.size(2);
  return {H, W, x.size(3), pad, H + 2 * pad - kTaps + 1, W + 2 * pad - kTaps + 1};
}

// The five blurred moments (μ_x, μ_y, w∗x², w∗y², w∗xy) of one plane at every output pixel:
// stats[q * Ho * Wo + r * Wo + j].
template <typename T>
void blur_moments(const T* x, const T* y, int64_t c, const Plane& g, const T* w, T* stats) {
  const int64_t padded = g.W + 2 * g.pad, n_out = g.Ho * g.Wo;
  std::vector<T> row(5 * padded, T(0)), h(5 * g.H * g.Wo);
  for (int64_t r = 0; r < g.H; ++r) {  // horizontal pass, every input row
    T *rx = row.data(), *ry = rx + padded, *rxx = ry + padded, *ryy = rxx + padded, *rxy = ryy + padded;
    for (int64_t col = 0; col < g.W; ++col) {
      const T a = x[g.at(r, col) + c], b = y[g.at(r, col) + c];
      rx[col + g.pad] = a, ry[col + g.pad] = b, rxx[col + g.pad] = a * a, ryy[col + g.pad] = b * b, rxy[col + g.pad] = a * b;
    }
    for (int q = 0; q < 5; ++q) {
      const T* src = row.data() + q * padded;
      T* dst = h.data() + (q * g.H + r) * g.Wo;
#pragma omp simd
      for (int64_t j = 0; j < g.Wo; ++j) {
        T sum = T(0);
        for (int64_t k = 0; k < kTaps; ++k) sum += w[k] * src[j + k];
        dst[j] = sum;
      }
    }
  }
  for (int q = 0; q < 5; ++q)  // vertical pass, every output row (rows outside the image are 0)
    for (int64_t r = 0; r < g.Ho; ++r) {
      T* dst = stats + q * n_out + r * g.Wo;
      std::fill(dst, dst + g.Wo, T(0));
      for (int64_t k = 0; k < kTaps; ++k) {
        const int64_t src_r = r + k - g.pad;
        if (src_r < 0 || src_r >= g.H) continue;
        const T* src = h.data() + (q * g.H + src_r) * g.Wo;
        const T wk = w[k];
#pragma omp simd
        for (int64_t j = 0; j < g.Wo; ++j) dst[j] += wk * src[j];
      }
    }
}

// SSIM at output pixel e from a plane's blurred moments s (5, n_out): w∗x, w∗y, w∗x², w∗y², w∗xy.
// One expression for ssim_map_forward and photometric_forward, so that both round alike.
template <typename T>
inline T ssim_at(const T* s, int64_t n_out, int64_t e, T C1, T C2) {
  const T mx = s[e], my = s[n_out + e];
  const T vx = s[2 * n_out + e] - mx * mx, vy = s[3 * n_out + e] - my * my, cxy = s[4 * n_out + e] - mx * my;
  return ((T(2) * mx * my + C1) * (T(2) * cxy + C2)) / ((mx * mx + my * my + C1) * (vx + vy + C2));
}

// Returns the map (B, Ho, Wo, C) and the moments (B, C, 5, Ho, Wo) the backward needs.
std::vector<at::Tensor> ssim_map_forward(const at::Tensor& x, const at::Tensor& y, const at::Tensor& taps,
                                         int64_t pad, double c1, double c2) {
  check_params({x, y, taps});
  TORCH_CHECK(x.dim() == 4 && x.sizes() == y.sizes() && taps.numel() == kTaps && (pad == 0 || pad == 5),
              "ssim_map: x and y (B, H, W, C), 11 taps, pad 0 or 5");
  const Plane g = plane_of(x, pad);
  TORCH_CHECK(g.Ho > 0 && g.Wo > 0, "ssim_map: the image is smaller than the window");
  const int64_t B = x.size(0);
  at::Tensor map = at::empty({B, g.Ho, g.Wo, g.C}, x.options());
  at::Tensor stats = at::empty({B, g.C, 5, g.Ho, g.Wo}, x.options());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ssim_map_forward", [&] {
    using T = scalar_t;
    const T *xp = x.data_ptr<T>(), *yp = y.data_ptr<T>(), *w = taps.data_ptr<T>();
    T *mp = map.data_ptr<T>(), *sp = stats.data_ptr<T>();
    const T C1 = T(c1), C2 = T(c2);
    const int64_t n_out = g.Ho * g.Wo;
    at::parallel_for(0, B * g.C, 1, [&](int64_t i0, int64_t i1) {
      for (int64_t i = i0; i < i1; ++i) {
        const int64_t b = i / g.C, c = i % g.C;
        T* s = sp + i * 5 * n_out;
        blur_moments(xp + b * g.H * g.W * g.C, yp + b * g.H * g.W * g.C, c, g, w, s);
        T* out = mp + b * n_out * g.C + c;
        for (int64_t e = 0; e < n_out; ++e) out[e * g.C] = ssim_at(s, n_out, e, C1, C2);
      }
    });
  });
  return {map, stats};
}

// The per-plane backward of the SSIM map, shared by ssim_map_backward and photometric_backward
// (so that the two round alike, bit for bit): from the plane's moments s (5, Ho, Wo) and
// gS(e) = ∂L/∂S at output pixel e, it calls put(o, ∂L/∂x) for every input offset o = at(r, col) + c
// of the plane. gm, v, row: scratch of 3 n_out, 3 H Wo and 3 (W + 2 pad) values.
template <typename T, typename GradS, typename Put>
void ssim_plane_backward(const T* s, GradS&& gS_of, const T* xb, const T* yb, int64_t c, const Plane& g, const T* w,
                         T C1, T C2, T* gm, T* v, T* row, Put&& put) {
  const int64_t n_out = g.Ho * g.Wo, padded = g.W + 2 * g.pad;  // = Wo + kTaps − 1
  // ∂L/∂ of the blurred moments w∗x, w∗x², w∗xy (y's need none)
  for (int64_t e = 0; e < n_out; ++e) {
    const T mx = s[e], my = s[n_out + e];
    const T vx = s[2 * n_out + e] - mx * mx, vy = s[3 * n_out + e] - my * my, cxy = s[4 * n_out + e] - mx * my;
    const T a1 = T(2) * mx * my + C1, a2 = T(2) * cxy + C2, b1 = mx * mx + my * my + C1, b2 = vx + vy + C2;
    const T den = b1 * b2, S = a1 * a2 / den, gS = gS_of(e);
    const T g_a1 = gS * a2 / den, g_a2 = gS * a1 / den, g_b1 = -gS * S / b1, g_b2 = -gS * S / b2;
    // A1 = 2 μx μy + C1, A2 = 2 (w∗xy − μx μy) + C2, B1 = μx² + μy² + C1, B2 = w∗x² − μx² + … + C2
    gm[e] = T(2) * my * g_a1 - T(2) * my * g_a2 + T(2) * mx * g_b1 - T(2) * mx * g_b2;
    gm[n_out + e] = g_b2;
    gm[2 * n_out + e] = T(2) * g_a2;
  }
  // adjoint of the vertical pass: back to every input row
  std::fill(v, v + 3 * g.H * g.Wo, T(0));
  for (int q = 0; q < 3; ++q)
    for (int64_t r = 0; r < g.Ho; ++r) {
      const T* src = gm + q * n_out + r * g.Wo;
      for (int64_t k = 0; k < kTaps; ++k) {
        const int64_t dst_r = r + k - g.pad;
        if (dst_r < 0 || dst_r >= g.H) continue;
        T* dst = v + (q * g.H + dst_r) * g.Wo;
        const T wk = w[k];
#pragma omp simd
        for (int64_t j = 0; j < g.Wo; ++j) dst[j] += wk * src[j];
      }
    }
  // adjoint of the horizontal pass, then x's three moments: ∂x, ∂x² = 2x, ∂xy = y
  for (int64_t r = 0; r < g.H; ++r) {
    for (int q = 0; q < 3; ++q) {  // scatter output column j to input columns j + k − pad
      const T* src = v + (q * g.H + r) * g.Wo;
      T* acc = row + q * padded;
      std::fill(acc, acc + padded, T(0));
      for (int64_t k = 0; k < kTaps; ++k) {
        const T wk = w[k];
        T* dst = acc + k;
#pragma omp simd
        for (int64_t j = 0; j < g.Wo; ++j) dst[j] += wk * src[j];
      }
    }
    const T *a0 = row + g.pad, *a1 = a0 + padded, *a2 = a1 + padded;
    for (int64_t col = 0; col < g.W; ++col) {
      const int64_t o = g.at(r, col) + c;
      put(o, a0[col] + T(2) * xb[o] * a1[col] + yb[o] * a2[col]);
    }
  }
}

// ∂L/∂x (B, H, W, C) from ∂L/∂map.
at::Tensor ssim_map_backward(const at::Tensor& grad, const at::Tensor& x, const at::Tensor& y, const at::Tensor& taps,
                             const at::Tensor& stats, int64_t pad, double c1, double c2) {
  check_params({grad, x, y, taps, stats});
  const Plane g = plane_of(x, pad);
  const int64_t B = x.size(0);
  TORCH_CHECK(grad.sizes() == at::IntArrayRef({B, g.Ho, g.Wo, g.C}), "ssim_map_backward: bad gradient shape");
  at::Tensor gx = at::empty_like(x);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ssim_map_backward", [&] {
    using T = scalar_t;
    const T *xp = x.data_ptr<T>(), *yp = y.data_ptr<T>(), *w = taps.data_ptr<T>(), *gp = grad.data_ptr<T>();
    const T* sp = stats.data_ptr<T>();
    T* out = gx.data_ptr<T>();
    const T C1 = T(c1), C2 = T(c2);
    const int64_t n_out = g.Ho * g.Wo, padded = g.W + 2 * g.pad;
    at::parallel_for(0, B * g.C, 1, [&](int64_t i0, int64_t i1) {
      std::vector<T> gm(3 * n_out), v(3 * g.H * g.Wo), row(3 * padded);
      for (int64_t i = i0; i < i1; ++i) {
        const int64_t b = i / g.C, c = i % g.C, image = b * g.H * g.W * g.C;
        const T* gs = gp + b * n_out * g.C + c;
        T* ob = out + image;
        ssim_plane_backward(sp + i * 5 * n_out, [&](int64_t e) { return gs[e * g.C]; }, xp + image, yp + image, c, g, w,
                            C1, C2, gm.data(), v.data(), row.data(), [&](int64_t o, T value) { ob[o] = value; });
      }
    });
  });
  return gx;
}

// --- the photometric loss of a training step ---------------------------------------------------
//
// losses.photometric without a mask, L = (1 − λ) mean|x − y| + λ (1 − mean S) with the "same"
// SSIM map (zero padding 5), as one op: the forward blurs the moments once per plane (kept for
// the backward) and sums |x − y| and S per plane in double (planes added in order: the same value
// at any thread count); the backward writes ∂L/∂x in one pass,
//   ∂L/∂x = sgn(x − y) ((1 − λ) g) / N + ∂/∂x of Σ S · (−(λ g)) / N,
// in the float operations autograd performs on the composition (the scalars in T, the mean's
// backward a division by N, the SSIM part through ssim_plane_backward): the same gradient bit for
// bit. The loss itself differs from torch's float reductions in the last bits (double sums).

// Returns the loss (a 0-dim tensor) and the moments (B, C, 5, H, W) the backward needs.
std::vector<at::Tensor> photometric_forward(const at::Tensor& x, const at::Tensor& y, const at::Tensor& taps,
                                            double lambda, double c1, double c2) {
  check_params({x, y, taps});
  TORCH_CHECK(x.dim() == 4 && x.sizes() == y.sizes() && taps.numel() == kTaps && x.numel() > 0,
              "photometric: x and y (B, H, W, C), not empty, 11 taps");
  const Plane g = plane_of(x, 5);
  const int64_t B = x.size(0), planes = B * g.C, n_out = g.Ho * g.Wo;
  at::Tensor loss = at::empty({}, x.options());
  at::Tensor stats = at::empty({B, g.C, 5, g.Ho, g.Wo}, x.options());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "photometric_forward", [&] {
    using T = scalar_t;
    const T *xp = x.data_ptr<T>(), *yp = y.data_ptr<T>(), *w = taps.data_ptr<T>();
    T* sp = stats.data_ptr<T>();
    const T C1 = T(c1), C2 = T(c2);
    std::vector<double> l1_sum(planes), ssim_sum(planes);
    at::parallel_for(0, planes, 1, [&](int64_t i0, int64_t i1) {
      for (int64_t i = i0; i < i1; ++i) {
        const int64_t b = i / g.C, c = i % g.C, image = b * g.H * g.W * g.C;
        T* s = sp + i * 5 * n_out;
        blur_moments(xp + image, yp + image, c, g, w, s);
        double total = 0.0;
        for (int64_t e = 0; e < n_out; ++e) total += double(ssim_at(s, n_out, e, C1, C2));
        ssim_sum[i] = total;
        total = 0.0;
        for (int64_t e = 0; e < g.H * g.W; ++e) total += double(std::abs(xp[image + e * g.C + c] - yp[image + e * g.C + c]));
        l1_sum[i] = total;
      }
    });
    double l1 = 0.0, ssim = 0.0;
    for (int64_t i = 0; i < planes; ++i) l1 += l1_sum[i], ssim += ssim_sum[i];
    const double n = double(x.numel());   // = B Ho Wo C: the "same" map has the image's size
    // as the composition: (1 − λ) · l1 + λ · (1 − ssim), each mean rounded to T
    const T mean_l1 = T(l1 / n), mean_ssim = T(ssim / n);
    loss.fill_(T(1.0 - lambda) * mean_l1 + T(lambda) * (T(1) - mean_ssim));
  });
  return {loss, stats};
}

// ∂L/∂x (B, H, W, C) from ∂L/∂loss (a 0-dim tensor).
at::Tensor photometric_backward(const at::Tensor& grad, const at::Tensor& x, const at::Tensor& y, const at::Tensor& taps,
                                const at::Tensor& stats, double lambda, double c1, double c2) {
  check_params({grad, x, y, taps, stats});
  TORCH_CHECK(grad.numel() == 1, "photometric_backward: the gradient of a scalar");
  const Plane g = plane_of(x, 5);
  const int64_t B = x.size(0), n_out = g.Ho * g.Wo, padded = g.W + 2 * g.pad;
  TORCH_CHECK(stats.sizes() == at::IntArrayRef({B, g.C, 5, g.Ho, g.Wo}), "photometric_backward: bad moments");
  at::Tensor gx = at::empty_like(x);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "photometric_backward", [&] {
    using T = scalar_t;
    const T *xp = x.data_ptr<T>(), *yp = y.data_ptr<T>(), *w = taps.data_ptr<T>(), *sp = stats.data_ptr<T>();
    T* out = gx.data_ptr<T>();
    const T C1 = T(c1), C2 = T(c2), g_loss = grad.data_ptr<T>()[0], n = T(x.numel());
    // autograd on the composition: MulBackward (g · (1 − λ), g · λ in T), RsubBackward (−),
    // MeanBackward (÷ N), AbsBackward (· sgn(x − y))
    const T g_l1 = (g_loss * T(1.0 - lambda)) / n, g_ssim = -(g_loss * T(lambda)) / n;
    at::parallel_for(0, B * g.C, 1, [&](int64_t i0, int64_t i1) {
      std::vector<T> gm(3 * n_out), v(3 * g.H * g.Wo), row(3 * padded);
      for (int64_t i = i0; i < i1; ++i) {
        const int64_t b = i / g.C, c = i % g.C, image = b * g.H * g.W * g.C;
        const T *xb = xp + image, *yb = yp + image;
        T* ob = out + image;
        ssim_plane_backward(sp + i * 5 * n_out, [&](int64_t) { return g_ssim; }, xb, yb, c, g, w, C1, C2, gm.data(),
                            v.data(), row.data(), [&](int64_t o, T value) {
                              const T d = xb[o] - yb[o];
                              const T sgn = T((T(0) < d) - (d < T(0)));
                              ob[o] = value + g_l1 * sgn;
                            });
      }
    });
  });
  return gx;
}

// --- the anisotropy regulariser ---------------------------------------------------------------

// The scales s = exp(ℓ) of primitives [p0, p1) into s (3 per primitive), in SIMD (Sleef's exp, as
// torch.exp; a scalar std::exp per scale was most of the op's time).
template <typename T>
void scales_of(const T* l, int64_t p0, int64_t p1, T* s) {
  radfield::simd_exp(l + 3 * p0, s, 3 * (p1 - p0));
}

constexpr int64_t kScaleChunk = 512;   // primitives whose scales are exponentiated at once

// One primitive's ratios r = s / m (m = min s), their mean and their Bessel-corrected std, what
// the forward sums and the backward differentiates.
template <typename T>
struct RatioStats {
  T m, r[3], mean, sd;
};

template <typename T>
RatioStats<T> ratio_stats(const T* s) {
  RatioStats<T> st;
  st.m = std::min({s[0], s[1], s[2]});
  for (int i = 0; i < 3; ++i) st.r[i] = s[i] / st.m;
  st.mean = (st.r[0] + st.r[1] + st.r[2]) / T(3);
  const T d0 = st.r[0] - st.mean, d1 = st.r[1] - st.mean, d2 = st.r[2] - st.mean;
  st.sd = std::sqrt((d0 * d0 + d1 * d1 + d2 * d2) / T(2));
  return st;
}

// mean over primitives of std(s / min(s)) (Bessel-corrected, as torch.std)
at::Tensor anisotropy_forward(const at::Tensor& log_scales) {
  check_params({log_scales});
  TORCH_CHECK(log_scales.dim() == 2 && log_scales.size(1) == 3, "log_scales must be (P, 3)");
  const int64_t P = log_scales.size(0);
  at::Tensor out = at::empty({}, log_scales.options());
  AT_DISPATCH_FLOATING_TYPES(log_scales.scalar_type(), "anisotropy_forward", [&] {
    using T = scalar_t;
    const T* l = log_scales.data_ptr<T>();
    const double total = at::parallel_reduce(0, P, 2048, 0.0, [&](int64_t p0, int64_t p1, double sum) {
      T scales[3 * kScaleChunk];
      for (int64_t p = p0; p < p1; ++p) {
        if ((p - p0) % kScaleChunk == 0) scales_of(l, p, std::min(p + kScaleChunk, p1), scales);
        const T* s = scales + 3 * ((p - p0) % kScaleChunk);
        sum += double(ratio_stats(s).sd);
      }
      return sum;
    }, std::plus<double>());
    out.fill_(T(total / double(std::max<int64_t>(P, 1))));
    if (P == 0) out.fill_(std::numeric_limits<T>::quiet_NaN());  // torch: the mean of nothing
  });
  return out;
}

at::Tensor anisotropy_backward(const at::Tensor& grad, const at::Tensor& log_scales) {
  check_params({grad, log_scales});
  const int64_t P = log_scales.size(0);
  at::Tensor g_ls = at::empty_like(log_scales);
  AT_DISPATCH_FLOATING_TYPES(log_scales.scalar_type(), "anisotropy_backward", [&] {
    using T = scalar_t;
    const T* l = log_scales.data_ptr<T>();
    T* gl = g_ls.data_ptr<T>();
    const T g_mean = grad.data_ptr<T>()[0] / T(P);
    at::parallel_for(0, P, 2048, [&](int64_t p0, int64_t p1) {
      T scales[3 * kScaleChunk];
      for (int64_t p = p0; p < p1; ++p) {
        if ((p - p0) % kScaleChunk == 0) scales_of(l, p, std::min(p + kScaleChunk, p1), scales);
        const T* s = scales + 3 * ((p - p0) % kScaleChunk);
        const RatioStats<T> st = ratio_stats(s);
        const T m = st.m, mean = st.mean, sd = st.sd;
        const T* r = st.r;
        // ∂std/∂r_i = (r_i − mean) / (2 std) (Bessel: n − 1 = 2); torch gives 0 at std = 0? it
        // divides: std = 0 only when all r are equal, where every (r_i − mean) = 0 as well
        T g_r[3];
        for (int i = 0; i < 3; ++i) g_r[i] = sd > T(0) ? g_mean * (r[i] - mean) / (T(2) * sd) : T(0);
        // r_i = s_i / m: ∂/∂s_i = g_r_i / m, ∂/∂m = −Σ g_r_i s_i / m²; amin splits it among ties
        const int ties = int(s[0] == m) + int(s[1] == m) + int(s[2] == m);
        T g_m = T(0);
        for (int i = 0; i < 3; ++i) g_m -= g_r[i] * s[i] / (m * m);
        for (int i = 0; i < 3; ++i) gl[3 * p + i] = (g_r[i] / m + (s[i] == m ? g_m / T(ties) : T(0))) * s[i];
      }
    });
  });
  return g_ls;
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(radfield, m) {
  m.def("ssim_map_forward", &ssim_map_forward);
  m.def("ssim_map_backward", &ssim_map_backward);
  m.def("photometric_forward", &photometric_forward);
  m.def("photometric_backward", &photometric_backward);
  m.def("anisotropy_forward", &anisotropy_forward);
  m.def("anisotropy_backward", &anisotropy_backward);
}
