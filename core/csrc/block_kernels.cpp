// Fused CPU kernels of the rasteriser's two block kernels, forward and backward.
//
// They compute what the pure-torch twins in core/rasterize.py compute (`_neural_block`,
// `_gaussian_block`, built from core/kernels.py), which stay the readable reference that
// tests/test_fused.py compares against. The eager twins make one pass over (P, A, N) tensors per
// elementwise op (~60 of them); here a tile of one primitive's pixels is read once and everything
// stays in small per-thread buffers.
//
// Shapes: P primitives, A image points per primitive (its padded bounding-box pixels), N hidden
// units of the density MLP. All tensors contiguous, on the CPU, float32 or float64.
//
// SIMD: the code is written per pixel j of a tile (up to kTile pixels of one primitive, stored as
// structure of arrays) in loops that the compiler vectorises (`#pragma omp simd`: no reordering
// except of the double gradient sums). sin, cos, exp and expm1 go through ATen's Vectorized<T>,
// i.e. the same Sleef routines torch.sin / torch.cos / torch.exp use on this machine.
//
// Threads (OpenMP): the forward pass splits the P×A elements into (primitive, tile) work items;
// the backward pass gives each thread whole primitives, so the per-primitive gradient sums need
// no atomics. Gradient sums over A are accumulated in double, also for float32 (torch reduces
// pairwise; a sequential float sum over 65536 pixels would lose digits).
//
// Branches follow the torch twins' autograd exactly: clamp_min / clamp_max pass the gradient at
// equality, torch.maximum splits it in half at a tie, where(hit, I, 0) and the α < 1/255 skip
// zero it.

#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/cpu/vec/functional.h>
#include <ATen/cpu/vec/vec.h>
#include <torch/library.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr double kAlphaMax = 0.99;         // 3DGS clamp: no primitive fully opaque
constexpr double kAlphaMin = 1.0 / 255.0;  // 3DGS skip threshold
constexpr int64_t kTile = 128;             // pixels of one primitive evaluated together

// --- SIMD transcendentals over arrays ---------------------------------------------------------

template <typename T>
void simd_sin(const T* x, T* out, int64_t n) {
  at::vec::map([](at::vec::Vectorized<T> v) { return v.sin(); }, out, x, n);
}

template <typename T>
void simd_cos(const T* x, T* out, int64_t n) {
  at::vec::map([](at::vec::Vectorized<T> v) { return v.cos(); }, out, x, n);
}

template <typename T>
void simd_exp(const T* x, T* out, int64_t n) {
  at::vec::map([](at::vec::Vectorized<T> v) { return v.exp(); }, out, x, n);
}

template <typename T>
void simd_expm1(const T* x, T* out, int64_t n) {
  at::vec::map([](at::vec::Vectorized<T> v) { return v.expm1(); }, out, x, n);
}

// --- shared scalar pieces ---------------------------------------------------------------------

template <typename T>
struct Intrinsics {
  T fx, fy, cx, cy, near;
};

template <typename T>
Intrinsics<T> read_intrinsics(const at::Tensor& intrinsics) {
  const T* k = intrinsics.data_ptr<T>();
  return {k[0], k[1], k[2], k[3], k[4]};
}

// Unnormalised sinc, sin(x)/x; only x = 0 itself needs its limit (kernels.py: sinc).
template <typename T>
inline T sinc(T x, T sin_x) {
  return x == T(0) ? T(1) : sin_x / x;
}

// d sinc/dx = (cos x − sinc x)/x, by its series −x/3 + x³/30 where the difference cancels
// (kernels.py: _sinc_slope); correct when a ray runs perpendicular to a frequency (a_k ≈ 0).
template <typename T>
inline T sinc_slope(T x, T cos_x, T sinc_x) {
  if (std::abs(x) < T(1e-2)) return x * (x * x / T(30) - T(1) / T(3));
  return (cos_x - sinc_x) / x;
}

// Paper eq. 9 with the 3DGS clamps, given expm1(−max(0, I)):
// α = min(0.99, 1 − exp(−max(0, I))), and 0 below 1/255.
template <typename T>
inline T alpha_from_expm1(T expm1_neg_depth) {
  const T alpha = std::min(T(kAlphaMax), -expm1_neg_depth);
  return alpha < T(kAlphaMin) ? T(0) : alpha;
}

// =============================================================================================
// Neural primitive: rays through one bounding ellipsoid (DESIGN.md "Splattable neural primitive").

// Parameters of one primitive: pointers into the (P, ...) tensors.
template <typename T>
struct NeuralParams {
  const T* m_cam;  // (3, 3), M = S⁻¹Rᵀ R_cam
  const T* o_ell;  // (3,), o' = S⁻¹Rᵀ (o − μ)
  const T* w_cam;  // (N, 3), rows ω0 W1_k R_cam
  const T* c;      // (N,), c_k = ω0 (W1_k · u0 + b1_k)
  const T* w2;     // (N,)
  T b2, inv_smax;  // b2, 1 / max(s)
};

template <typename T>
struct NeuralInputs {  // the whole block
  int64_t P, A, N;
  Intrinsics<T> k;
  const T *u, *v, *m_cam, *o_ell, *w_cam, *c, *w2, *b2, *inv_smax;

  NeuralParams<T> primitive(int64_t p) const {
    return {m_cam + 9 * p, o_ell + 3 * p, w_cam + 3 * N * p, c + N * p, w2 + N * p, b2[p], inv_smax[p]};
  }
};

// Gradient sums of one primitive (double, see the top of the file).
struct NeuralGrads {
  std::vector<double> m_cam, o_ell, w_cam, c, w2;
  double b2 = 0, inv_smax = 0;
  explicit NeuralGrads(int64_t units)
      : m_cam(9, 0.0), o_ell(3, 0.0), w_cam(3 * units, 0.0), c(units, 0.0), w2(units, 0.0) {}
};

// C = o'·o' − 1 of the ray-sphere equation, the same for every pixel of a primitive
template <typename T>
inline T sphere_c(const T* o_ell) {
  return o_ell[0] * o_ell[0] + o_ell[1] * o_ell[1] + o_ell[2] * o_ell[2] - T(1);
}

// Σ_j x_j y_j, accumulated in double
template <typename T>
double dot(const T* x, const T* y, int64_t n) {
  double sum = 0;
#pragma omp simd reduction(+ : sum)
  for (int64_t j = 0; j < n; ++j) sum += double(x[j] * y[j]);
  return sum;
}

// Per-thread scratch for a tile of one primitive's pixels, one array entry per pixel j (structure
// of arrays, so that the loops over j run in SIMD). `chords` fills it for every pixel of the tile,
// then keeps the n pixels whose chord is not empty (hit and Δ > 0): the others have α = 0 and
// no gradient.
template <typename T>
struct ChordTile {
  int64_t n = 0;
  std::vector<int64_t> pixel;            // a, index into the primitive's row
  // step 1, entry and exit
  std::vector<T> d0, d1, d2;             // unit camera-space direction d̂
  std::vector<T> l_near;                 // ray distance of the near plane
  std::vector<T> e0, e1, e2;             // d' = M d̂
  std::vector<T> A, B;                   // |o' + ℓ d'|² = 1  ⇔  A ℓ² + 2 B ℓ + C = 0 (C = o'·o' − 1)
  std::vector<T> root;                   // √(B² − A C)
  std::vector<T> l_in_raw, l_in, l_out;  // entry before and after the near-plane clip, exit
  std::vector<T> delta, tau_m;           // Δ = max(ℓ_out − ℓ_in, 0)/max(s), τ_m = (ℓ_in + ℓ_out)/2/max(s)
  // step 2, the MLP integral: the current unit k (forward), or all units at [k * kTile + j] (backward)
  std::vector<T> a, phase, x;            // a_k = w_cam_k · d̂, a_k τ_m + c_k, a_k Δ/2
  std::vector<T> cos_p, sin_x, sinc_x, cos_x;
  std::vector<T> unit_a, unit_cos_p, unit_sin_p, unit_sinc, unit_slope;
  std::vector<T> integral;               // I
  // backward: ∂L/∂I, ∂L/∂τ_m, ∂L/∂Δ, ∂L/∂A, ∂L/∂B, ∂L/∂d'_r
  std::vector<T> g_I, g_tau, g_delta, g_A, g_B, g_e;

  ChordTile(int64_t units, bool backward) {
    for (auto* buf : chord_fields()) buf->resize(kTile);
    for (auto* buf : {&a, &phase, &x, &cos_p, &sin_x, &sinc_x, &integral}) buf->resize(kTile);
    pixel.resize(kTile);
    if (backward) {
      for (auto* buf : {&unit_a, &unit_cos_p, &unit_sin_p, &unit_sinc, &unit_slope}) buf->resize(units * kTile);
      for (auto* buf : {&cos_x, &g_I, &g_tau, &g_delta, &g_A, &g_B, &g_e}) buf->resize(kTile);
    }
  }

  std::array<std::vector<T>*, 15> chord_fields() {
    return {&d0, &d1, &d2, &l_near, &e0, &e1, &e2, &A, &B, &root, &l_in_raw, &l_in, &l_out, &delta, &tau_m};
  }

  // Step 1 for pixels [a0, a1) of primitive p (rasterize.py: _camera_directions, kernels.py:
  // ray_ellipsoid): o' + ℓ d' enters and leaves the unit sphere at ℓ = (−B ∓ √(B² − AC))/A.
  // Keeps the pixels with a chord (in the backward, also a nonzero upstream gradient `grad`).
  void chords(const NeuralInputs<T>& in, const NeuralParams<T>& q, int64_t p, int64_t a0, int64_t a1,
              const T* grad) {
    const int64_t m = a1 - a0;
    const T *u = in.u + p * in.A + a0, *v = in.v + p * in.A + a0;
    const Intrinsics<T> k = in.k;
    const T* M = q.m_cam;
    const T* o = q.o_ell;
    const T C = sphere_c(o);
#pragma omp simd
    for (int64_t j = 0; j < m; ++j) {
      // d̂ = normalize((u − cx)/fx, (v − cy)/fy, 1), near plane at ℓ = near · |(…)|
      const T xn = (u[j] - k.cx) / k.fx, yn = (v[j] - k.cy) / k.fy;
      const T norm = std::sqrt(xn * xn + yn * yn + T(1));
      d0[j] = xn / norm;
      d1[j] = yn / norm;
      d2[j] = T(1) / norm;
      l_near[j] = k.near * norm;
      e0[j] = M[0] * d0[j] + M[1] * d1[j] + M[2] * d2[j];
      e1[j] = M[3] * d0[j] + M[4] * d1[j] + M[5] * d2[j];
      e2[j] = M[6] * d0[j] + M[7] * d1[j] + M[8] * d2[j];
      A[j] = e0[j] * e0[j] + e1[j] * e1[j] + e2[j] * e2[j];
      B[j] = o[0] * e0[j] + o[1] * e1[j] + o[2] * e2[j];
      const T disc = B[j] * B[j] - A[j] * C;
      const bool hit = disc > T(0);
      root[j] = std::sqrt(hit ? disc : T(1));
      l_in_raw[j] = (-B[j] - root[j]) / A[j];
      l_out[j] = (-B[j] + root[j]) / A[j];
      l_in[j] = std::max(l_in_raw[j], l_near[j]);  // camera inside: start at the near plane
      // a miss contributes nothing (where(hit, I, 0)); give it no chord
      delta[j] = hit ? std::max(l_out[j] - l_in[j], T(0)) * q.inv_smax : T(0);
      tau_m[j] = T(0.5) * (l_in[j] + l_out[j]) * q.inv_smax;
    }
    n = 0;
    for (int64_t j = 0; j < m; ++j) {
      if (!(delta[j] > T(0))) continue;  // a miss, or an empty chord (I = 0 < 1/255)
      if (grad != nullptr && grad[j] == T(0)) continue;
      pixel[n++] = j;
    }
    for (auto* field : chord_fields()) {  // compact in place (pixel[i] ≥ i)
      T* f = field->data();
      for (int64_t i = 0; i < n; ++i) f[i] = f[pixel[i]];
    }
    for (int64_t i = 0; i < n; ++i) pixel[i] += a0;
  }

  // Step 2, paper eq. 7–8 in the stable sinc form (kernels.py: neural_optical_depth):
  //   I = Σ_k W2_k Δ cos(a_k τ_m + c_k) sinc(a_k Δ / 2) + b2 Δ,   a_k = ω0 W1_k · d̂,
  // one unit at a time; the backward keeps each unit's a_k, cos, sin, sinc and sinc slope.
  void optical_depth(const NeuralParams<T>& q, int64_t units, bool keep_units) {
    std::fill(integral.begin(), integral.begin() + n, T(0));
    for (int64_t k = 0; k < units; ++k) {
      const T* w = q.w_cam + 3 * k;
      T* ak = keep_units ? unit_a.data() + k * kTile : a.data();
      T* cos_pk = keep_units ? unit_cos_p.data() + k * kTile : cos_p.data();
      T* sk = keep_units ? unit_sinc.data() + k * kTile : sinc_x.data();
#pragma omp simd
      for (int64_t j = 0; j < n; ++j) {
        ak[j] = w[0] * d0[j] + w[1] * d1[j] + w[2] * d2[j];
        phase[j] = ak[j] * tau_m[j] + q.c[k];
        x[j] = T(0.5) * ak[j] * delta[j];
      }
      simd_cos(phase.data(), cos_pk, n);
      simd_sin(x.data(), sin_x.data(), n);
#pragma omp simd
      for (int64_t j = 0; j < n; ++j) {
        sk[j] = sinc(x[j], sin_x[j]);
        integral[j] += q.w2[k] * delta[j] * cos_pk[j] * sk[j];
      }
      if (keep_units) {
        simd_sin(phase.data(), unit_sin_p.data() + k * kTile, n);
        simd_cos(x.data(), cos_x.data(), n);
        T* slopek = unit_slope.data() + k * kTile;
#pragma omp simd
        for (int64_t j = 0; j < n; ++j) slopek[j] = sinc_slope(x[j], cos_x[j], sk[j]);
      }
    }
#pragma omp simd
    for (int64_t j = 0; j < n; ++j) integral[j] += q.b2 * delta[j];
  }

  // Step 2 backward (kernels.py: _CosMLPIntegral.backward), + b2 Δ: from g_I to g_tau and
  // g_delta, and the sums for c, w2, w_cam and b2, one unit at a time.
  void optical_depth_backward(const NeuralParams<T>& q, int64_t units, NeuralGrads& acc) {
    double sum_b2 = 0;
#pragma omp simd reduction(+ : sum_b2)
    for (int64_t j = 0; j < n; ++j) {
      sum_b2 += double(g_I[j] * delta[j]);
      g_delta[j] = g_I[j] * q.b2;
      g_tau[j] = T(0);
    }
    acc.b2 += sum_b2;
    for (int64_t k = 0; k < units; ++k) {
      const T *ak = unit_a.data() + k * kTile, *sk = unit_sinc.data() + k * kTile;
      const T *cos_pk = unit_cos_p.data() + k * kTile, *sin_pk = unit_sin_p.data() + k * kTile;
      const T* slopek = unit_slope.data() + k * kTile;
      double sum_c = 0, sum_w2 = 0, sum_wx = 0, sum_wy = 0, sum_wz = 0;
#pragma omp simd reduction(+ : sum_c, sum_w2, sum_wx, sum_wy, sum_wz)
      for (int64_t j = 0; j < n; ++j) {
        const T gwd = g_I[j] * q.w2[k] * delta[j];
        const T g_phase = -gwd * sin_pk[j] * sk[j];  // ∂/∂(a_k τ_m + c_k)
        const T g_x = gwd * cos_pk[j] * slopek[j];   // ∂/∂(a_k Δ / 2)
        const T g_a = g_phase * tau_m[j] + T(0.5) * g_x * delta[j];
        g_tau[j] += g_phase * ak[j];
        g_delta[j] += g_I[j] * q.w2[k] * cos_pk[j] * sk[j] + T(0.5) * g_x * ak[j];
        sum_c += double(g_phase);
        sum_w2 += double(g_I[j] * delta[j] * cos_pk[j] * sk[j]);
        sum_wx += double(g_a * d0[j]);  // a_k = w_cam_k · d̂
        sum_wy += double(g_a * d1[j]);
        sum_wz += double(g_a * d2[j]);
      }
      acc.c[k] += sum_c;
      acc.w2[k] += sum_w2;
      acc.w_cam[3 * k] += sum_wx;
      acc.w_cam[3 * k + 1] += sum_wy;
      acc.w_cam[3 * k + 2] += sum_wz;
    }
  }

  // Step 1 backward: from g_delta and g_tau to the sums for inv_smax, m_cam and o_ell.
  void chords_backward(const NeuralParams<T>& q, NeuralGrads& acc) {
    const T* o = q.o_ell;
    const T C = sphere_c(o);
    double sum_inv_smax = 0, sum_g_C = 0;
#pragma omp simd reduction(+ : sum_inv_smax, sum_g_C)
    for (int64_t j = 0; j < n; ++j) {
      // Δ = max(ℓ_out − ℓ_in, 0)/max(s) with Δ > 0 here, τ_m = (ℓ_in + ℓ_out)/2/max(s)
      sum_inv_smax += double(g_delta[j] * (l_out[j] - l_in[j]) + g_tau[j] * T(0.5) * (l_in[j] + l_out[j]));
      const T g_length = g_delta[j] * q.inv_smax;
      const T g_l_in = -g_length + T(0.5) * q.inv_smax * g_tau[j];
      const T g_l_out = g_length + T(0.5) * q.inv_smax * g_tau[j];
      // ℓ_in = maximum(ℓ_in_raw, ℓ_near): the near plane is a constant; half the gradient at a tie
      const T g_l_in_raw = l_in_raw[j] > l_near[j] ? g_l_in : (l_in_raw[j] == l_near[j] ? T(0.5) * g_l_in : T(0));
      // ℓ_in/out = (−B ∓ root)/A, root = √(B² − A C)
      const T g_root = (g_l_out - g_l_in_raw) / A[j];
      const T g_disc = g_root / (T(2) * root[j]);
      g_B[j] = -(g_l_in_raw + g_l_out) / A[j] + T(2) * B[j] * g_disc;
      g_A[j] = -(g_l_in_raw * l_in_raw[j] + g_l_out * l_out[j]) / A[j] - C * g_disc;
      sum_g_C += double(-A[j] * g_disc);
    }
    acc.inv_smax += sum_inv_smax;
    // A = d'·d', B = o'·d', C = o'·o' − 1, d' = m_cam d̂
    const T* d[3] = {d0.data(), d1.data(), d2.data()};
    const T* e[3] = {e0.data(), e1.data(), e2.data()};
    for (int r = 0; r < 3; ++r) {
#pragma omp simd
      for (int64_t j = 0; j < n; ++j) g_e[j] = T(2) * e[r][j] * g_A[j] + o[r] * g_B[j];  // ∂L/∂d'_r
      for (int f = 0; f < 3; ++f) acc.m_cam[3 * r + f] += dot(g_e.data(), d[f], n);
      acc.o_ell[r] += dot(e[r], g_B.data(), n) + 2.0 * double(o[r]) * sum_g_C;
    }
  }
};

template <typename T>
NeuralInputs<T> neural_inputs(const at::Tensor& u, const at::Tensor& v, const at::Tensor& intrinsics,
                              const at::Tensor& m_cam, const at::Tensor& o_ell, const at::Tensor& w_cam,
                              const at::Tensor& c, const at::Tensor& w2, const at::Tensor& b2,
                              const at::Tensor& inv_smax) {
  return {u.size(0), u.size(1), c.size(1), read_intrinsics<T>(intrinsics),
          u.data_ptr<T>(), v.data_ptr<T>(), m_cam.data_ptr<T>(), o_ell.data_ptr<T>(), w_cam.data_ptr<T>(),
          c.data_ptr<T>(), w2.data_ptr<T>(), b2.data_ptr<T>(), inv_smax.data_ptr<T>()};
}

template <typename T>
void neural_forward_kernel(const NeuralInputs<T>& in, T* alpha) {
  const int64_t tiles = (in.A + kTile - 1) / kTile;
#pragma omp parallel num_threads(at::get_num_threads())
  {
    ChordTile<T> tile(in.N, /*backward=*/false);
    std::vector<T> neg_depth(kTile), expm1_neg(kTile);

#pragma omp for schedule(dynamic, 2)
    for (int64_t item = 0; item < in.P * tiles; ++item) {
      const int64_t p = item / tiles, a0 = (item % tiles) * kTile, a1 = std::min(a0 + kTile, in.A);
      const NeuralParams<T> q = in.primitive(p);
      std::fill(alpha + p * in.A + a0, alpha + p * in.A + a1, T(0));
      tile.chords(in, q, p, a0, a1, nullptr);
      tile.optical_depth(q, in.N, /*keep_units=*/false);
      // eq. 9
      for (int64_t j = 0; j < tile.n; ++j) neg_depth[j] = -std::max(tile.integral[j], T(0));
      simd_expm1(neg_depth.data(), expm1_neg.data(), tile.n);
      for (int64_t j = 0; j < tile.n; ++j) alpha[p * in.A + tile.pixel[j]] = alpha_from_expm1(expm1_neg[j]);
    }
  }
}

template <typename T>
void neural_backward_kernel(const NeuralInputs<T>& in, const T* grad, std::vector<at::Tensor>& out) {
  T *g_m_cam = out[0].data_ptr<T>(), *g_o_ell = out[1].data_ptr<T>(), *g_w_cam = out[2].data_ptr<T>();
  T *g_c = out[3].data_ptr<T>(), *g_w2 = out[4].data_ptr<T>(), *g_b2 = out[5].data_ptr<T>();
  T* g_inv_smax = out[6].data_ptr<T>();
  const int64_t N = in.N;

#pragma omp parallel num_threads(at::get_num_threads())
  {
    ChordTile<T> tile(N, /*backward=*/true);
    std::vector<T> neg_depth(kTile), expm1_neg(kTile);

#pragma omp for schedule(dynamic, 1)
    for (int64_t p = 0; p < in.P; ++p) {
      const NeuralParams<T> q = in.primitive(p);
      NeuralGrads acc(N);
      for (int64_t a0 = 0; a0 < in.A; a0 += kTile) {
        tile.chords(in, q, p, a0, std::min(a0 + kTile, in.A), grad + p * in.A + a0);
        tile.optical_depth(q, N, /*keep_units=*/true);
        for (int64_t j = 0; j < tile.n; ++j) neg_depth[j] = -std::max(tile.integral[j], T(0));
        simd_expm1(neg_depth.data(), expm1_neg.data(), tile.n);
        for (int64_t j = 0; j < tile.n; ++j) {
          // eq. 9: ∂α/∂I = exp(−I) where neither the 0.99 clamp nor the 1/255 skip is active (I < 0,
          // where clamp_min(I, 0) blocks the gradient, gives α = 0 and is skipped too)
          const bool passes = !(-expm1_neg[j] > T(kAlphaMax)) && alpha_from_expm1(expm1_neg[j]) != T(0);
          tile.g_I[j] = passes ? grad[p * in.A + tile.pixel[j]] * (expm1_neg[j] + T(1)) : T(0);
        }
        tile.optical_depth_backward(q, N, acc);
        tile.chords_backward(q, acc);
      }
      for (int e = 0; e < 9; ++e) g_m_cam[9 * p + e] = T(acc.m_cam[e]);
      for (int e = 0; e < 3; ++e) g_o_ell[3 * p + e] = T(acc.o_ell[e]);
      for (int64_t j = 0; j < 3 * N; ++j) g_w_cam[3 * N * p + j] = T(acc.w_cam[j]);
      for (int64_t k = 0; k < N; ++k) {
        g_c[N * p + k] = T(acc.c[k]);
        g_w2[N * p + k] = T(acc.w2[k]);
      }
      g_b2[p] = T(acc.b2);
      g_inv_smax[p] = T(acc.inv_smax);
    }
  }
}

// --- checks and entry points ------------------------------------------------------------------

void check_params(const std::vector<at::Tensor>& tensors) {
  const at::ScalarType dtype = tensors[0].scalar_type();
  TORCH_CHECK(dtype == at::kFloat || dtype == at::kDouble, "fused kernels take float32 or float64, got ", dtype);
  for (const at::Tensor& t : tensors) {
    TORCH_CHECK(t.device().is_cpu(), "fused kernels run on the CPU");
    TORCH_CHECK(t.scalar_type() == dtype, "fused kernels need one dtype for all inputs");
    TORCH_CHECK(t.is_contiguous(), "fused kernels need contiguous inputs");
  }
}

void check_neural(const at::Tensor& u, const at::Tensor& v, const at::Tensor& intrinsics, const at::Tensor& m_cam,
                  const at::Tensor& o_ell, const at::Tensor& w_cam, const at::Tensor& c, const at::Tensor& w2,
                  const at::Tensor& b2, const at::Tensor& inv_smax) {
  TORCH_CHECK(u.dim() == 2 && v.sizes() == u.sizes(), "u, v must both be (P, A)");
  TORCH_CHECK(intrinsics.numel() == 5, "intrinsics must be (fx, fy, cx, cy, near)");
  check_params({u, v, intrinsics, m_cam, o_ell, w_cam, c, w2, b2, inv_smax});
  const int64_t P = u.size(0);
  TORCH_CHECK(c.dim() == 2 && c.size(0) == P, "c must be (P, N)");
  const int64_t N = c.size(1);
  TORCH_CHECK(m_cam.sizes() == at::IntArrayRef({P, 3, 3}), "m_cam must be (P, 3, 3)");
  TORCH_CHECK(o_ell.sizes() == at::IntArrayRef({P, 3}), "o_ell must be (P, 3)");
  TORCH_CHECK(w_cam.sizes() == at::IntArrayRef({P, N, 3}), "w_cam must be (P, N, 3)");
  TORCH_CHECK(w2.sizes() == at::IntArrayRef({P, N}), "w2 must be (P, N)");
  TORCH_CHECK(b2.sizes() == at::IntArrayRef({P}) && inv_smax.sizes() == at::IntArrayRef({P}),
              "b2 and inv_smax must be (P,)");
}

at::Tensor neural_block_forward(const at::Tensor& u, const at::Tensor& v, const at::Tensor& intrinsics,
                                const at::Tensor& m_cam, const at::Tensor& o_ell, const at::Tensor& w_cam,
                                const at::Tensor& c, const at::Tensor& w2, const at::Tensor& b2,
                                const at::Tensor& inv_smax) {
  check_neural(u, v, intrinsics, m_cam, o_ell, w_cam, c, w2, b2, inv_smax);
  at::Tensor alpha = at::empty_like(u);
  AT_DISPATCH_FLOATING_TYPES(u.scalar_type(), "neural_block_forward", [&] {
    neural_forward_kernel<scalar_t>(
        neural_inputs<scalar_t>(u, v, intrinsics, m_cam, o_ell, w_cam, c, w2, b2, inv_smax),
        alpha.data_ptr<scalar_t>());
  });
  return alpha;
}

// Gradients for (m_cam, o_ell, w_cam, c, w2, b2, inv_smax).
std::vector<at::Tensor> neural_block_backward(const at::Tensor& grad_alpha, const at::Tensor& u,
                                              const at::Tensor& v, const at::Tensor& intrinsics,
                                              const at::Tensor& m_cam, const at::Tensor& o_ell,
                                              const at::Tensor& w_cam, const at::Tensor& c, const at::Tensor& w2,
                                              const at::Tensor& b2, const at::Tensor& inv_smax) {
  check_neural(u, v, intrinsics, m_cam, o_ell, w_cam, c, w2, b2, inv_smax);
  check_params({u, grad_alpha});
  TORCH_CHECK(grad_alpha.sizes() == u.sizes(), "grad_alpha must be (P, A)");
  std::vector<at::Tensor> out = {at::empty_like(m_cam), at::empty_like(o_ell), at::empty_like(w_cam),
                                 at::empty_like(c),     at::empty_like(w2),    at::empty_like(b2),
                                 at::empty_like(inv_smax)};
  AT_DISPATCH_FLOATING_TYPES(u.scalar_type(), "neural_block_backward", [&] {
    neural_backward_kernel<scalar_t>(
        neural_inputs<scalar_t>(u, v, intrinsics, m_cam, o_ell, w_cam, c, w2, b2, inv_smax),
        grad_alpha.data_ptr<scalar_t>(), out);
  });
  return out;
}

// =============================================================================================
// 3D Gaussian (EWA splat, as 3DGS; kernels.py: gaussian_alpha).

// power = −½ (c0 dx² + c2 dy²) − c1 dx dy with conic (c0, c1, c2) = inverse 2D covariance entries
template <typename T>
inline T gaussian_power(T dx, T dy, const T* conic) {
  return T(-0.5) * (conic[0] * dx * dx + conic[2] * dy * dy) - conic[1] * dx * dy;
}

// exp(min(power, 0)) of pixels [a0, a1) of primitive p into e, their powers into power
template <typename T>
void gaussian_tile(const T* u, const T* v, const T* mean2d, const T* conic, int64_t A, int64_t p, int64_t a0,
                   int64_t a1, T* power, T* e) {
#pragma omp simd
  for (int64_t a = a0; a < a1; ++a) {
    const int64_t i = p * A + a;
    power[a - a0] = gaussian_power(u[i] - mean2d[2 * p], v[i] - mean2d[2 * p + 1], conic + 3 * p);
    e[a - a0] = std::min(power[a - a0], T(0));
  }
  simd_exp(e, e, a1 - a0);
}

template <typename T>
void gaussian_forward_kernel(const T* u, const T* v, const T* mean2d, const T* conic, const T* opacity, int64_t P,
                             int64_t A, T* alpha) {
  const int64_t tiles = (A + kTile - 1) / kTile;
#pragma omp parallel num_threads(at::get_num_threads())
  {
    std::vector<T> power(kTile), e(kTile);
#pragma omp for schedule(dynamic, 8)
    for (int64_t item = 0; item < P * tiles; ++item) {
      const int64_t p = item / tiles, a0 = (item % tiles) * kTile, a1 = std::min(a0 + kTile, A);
      gaussian_tile(u, v, mean2d, conic, A, p, a0, a1, power.data(), e.data());
#pragma omp simd
      for (int64_t a = a0; a < a1; ++a) {
        // α = min(0.99, opacity exp(min(power, 0))), 0 below 1/255 or where power > 0
        const T value = std::min(T(kAlphaMax), opacity[p] * e[a - a0]);
        alpha[p * A + a] = (value < T(kAlphaMin) || power[a - a0] > T(0)) ? T(0) : value;
      }
    }
  }
}

template <typename T>
void gaussian_backward_kernel(const T* grad, const T* u, const T* v, const T* mean2d, const T* conic,
                              const T* opacity, int64_t P, int64_t A, std::vector<at::Tensor>& out) {
  T *g_mean2d = out[0].data_ptr<T>(), *g_conic = out[1].data_ptr<T>(), *g_opacity = out[2].data_ptr<T>();
#pragma omp parallel num_threads(at::get_num_threads())
  {
    std::vector<T> power(kTile), e(kTile);
#pragma omp for schedule(dynamic, 4)
    for (int64_t p = 0; p < P; ++p) {
      const T* q = conic + 3 * p;
      double sum_mx = 0, sum_my = 0, sum_c0 = 0, sum_c1 = 0, sum_c2 = 0, sum_opacity = 0;
      for (int64_t a0 = 0; a0 < A; a0 += kTile) {
        const int64_t a1 = std::min(a0 + kTile, A);
        gaussian_tile(u, v, mean2d, conic, A, p, a0, a1, power.data(), e.data());
        const T *g_tile = grad + p * A + a0, *u_tile = u + p * A + a0, *v_tile = v + p * A + a0;
#pragma omp simd reduction(+ : sum_mx, sum_my, sum_c0, sum_c1, sum_c2, sum_opacity)
        for (int64_t j = 0; j < a1 - a0; ++j) {
          const T value = opacity[p] * e[j];
          // zero gradient where skipped (α < 1/255 or power > 0) or clamped at 0.99
          const bool passes = !(power[j] > T(0)) && !(value > T(kAlphaMax)) && !(value < T(kAlphaMin));
          const T g_alpha = passes ? g_tile[j] : T(0);
          const T dx = u_tile[j] - mean2d[2 * p], dy = v_tile[j] - mean2d[2 * p + 1];
          const T g_power = g_alpha * value;  // (exp)' = exp; clamp_max(power, 0) passes at power ≤ 0
          sum_opacity += double(g_alpha * e[j]);
          sum_c0 += double(T(-0.5) * g_power * dx * dx);
          sum_c2 += double(T(-0.5) * g_power * dy * dy);
          sum_c1 += double(-g_power * dx * dy);
          sum_mx -= double(g_power * (-q[0] * dx - q[1] * dy));  // ∂dx/∂mean_x = −1
          sum_my -= double(g_power * (-q[2] * dy - q[1] * dx));
        }
      }
      g_mean2d[2 * p] = T(sum_mx);
      g_mean2d[2 * p + 1] = T(sum_my);
      g_conic[3 * p] = T(sum_c0);
      g_conic[3 * p + 1] = T(sum_c1);
      g_conic[3 * p + 2] = T(sum_c2);
      g_opacity[p] = T(sum_opacity);
    }
  }
}

void check_gaussian(const at::Tensor& u, const at::Tensor& v, const at::Tensor& mean2d, const at::Tensor& conic,
                    const at::Tensor& opacity) {
  TORCH_CHECK(u.dim() == 2 && v.sizes() == u.sizes(), "u, v must both be (P, A)");
  check_params({u, v, mean2d, conic, opacity});
  const int64_t P = u.size(0);
  TORCH_CHECK(mean2d.sizes() == at::IntArrayRef({P, 2}), "mean2d must be (P, 2)");
  TORCH_CHECK(conic.sizes() == at::IntArrayRef({P, 3}), "conic must be (P, 3)");
  TORCH_CHECK(opacity.sizes() == at::IntArrayRef({P}), "opacity must be (P,)");
}

at::Tensor gaussian_block_forward(const at::Tensor& u, const at::Tensor& v, const at::Tensor& mean2d,
                                  const at::Tensor& conic, const at::Tensor& opacity) {
  check_gaussian(u, v, mean2d, conic, opacity);
  at::Tensor alpha = at::empty_like(u);
  AT_DISPATCH_FLOATING_TYPES(u.scalar_type(), "gaussian_block_forward", [&] {
    gaussian_forward_kernel<scalar_t>(u.data_ptr<scalar_t>(), v.data_ptr<scalar_t>(), mean2d.data_ptr<scalar_t>(),
                                      conic.data_ptr<scalar_t>(), opacity.data_ptr<scalar_t>(), u.size(0),
                                      u.size(1), alpha.data_ptr<scalar_t>());
  });
  return alpha;
}

// Gradients for (mean2d, conic, opacity).
std::vector<at::Tensor> gaussian_block_backward(const at::Tensor& grad_alpha, const at::Tensor& u,
                                                const at::Tensor& v, const at::Tensor& mean2d,
                                                const at::Tensor& conic, const at::Tensor& opacity) {
  check_gaussian(u, v, mean2d, conic, opacity);
  check_params({u, grad_alpha});
  TORCH_CHECK(grad_alpha.sizes() == u.sizes(), "grad_alpha must be (P, A)");
  std::vector<at::Tensor> out = {at::empty_like(mean2d), at::empty_like(conic), at::empty_like(opacity)};
  AT_DISPATCH_FLOATING_TYPES(u.scalar_type(), "gaussian_block_backward", [&] {
    gaussian_backward_kernel<scalar_t>(grad_alpha.data_ptr<scalar_t>(), u.data_ptr<scalar_t>(),
                                       v.data_ptr<scalar_t>(), mean2d.data_ptr<scalar_t>(),
                                       conic.data_ptr<scalar_t>(), opacity.data_ptr<scalar_t>(), u.size(0),
                                       u.size(1), out);
  });
  return out;
}

}  // namespace

// Called from Python as torch.ops.radfield.<name> (core/fused.py wraps them in autograd Functions).
TORCH_LIBRARY(radfield, m) {
  m.def("neural_block_forward", &neural_block_forward);
  m.def("neural_block_backward", &neural_block_backward);
  m.def("gaussian_block_forward", &gaussian_block_forward);
  m.def("gaussian_block_backward", &gaussian_block_backward);
}
