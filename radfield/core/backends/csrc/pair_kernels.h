// The splatting weight α of one pixel ray through one primitive, forward and backward, for a batch
// of pixels of one primitive at a time: shared by the block kernels (block_kernels.cpp, the
// per-pair twins of core/render/rasterize.py's `_neural_block` / `_gaussian_block`) and the whole-view
// tile rasteriser (view_kernels.cpp). At the end, the quaternion rotation and its backward that the
// per-primitive ops share (prepare_kernels.cpp, relight_kernels.cpp).
//
// SIMD: the code is written per pixel j of a batch (up to `cap` pixels of one primitive, stored as
// structure of arrays) in loops that the compiler vectorises (`#pragma omp simd`: no reordering
// except of the double gradient sums). sin, cos, exp and expm1 go through ATen's Vectorized<T>,
// i.e. Sleef routines as torch.sin / torch.exp on this machine (see below for sin and cos). The build
// keeps IEEE semantics and turns off FMA contraction (-ffp-contract=off, core/backends/fused.py), so an
// AVX2, AVX-512 and default build round every +, −, ×, ÷ alike and as torch's eager ops do.
//
// Gradient sums are accumulated in double, also for float32.
//
// Branches follow the torch twins' autograd exactly: clamp_min / clamp_max pass the gradient at
// equality, torch.maximum splits it in half at a tie, where(hit, I, 0) and the α < 1/255 skip
// zero it.

#pragma once

#include <ATen/ATen.h>
#include <ATen/cpu/vec/functional.h>
#include <ATen/cpu/vec/vec.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <vector>

namespace radfield {

constexpr double kAlphaMax = 0.99;         // 3DGS clamp: no primitive fully opaque
constexpr double kAlphaMin = 1.0 / 255.0;  // 3DGS skip threshold

// --- SIMD transcendentals over arrays ---------------------------------------------------------
//
// sin and cos call Sleef's 3.5-ULP routines directly (torch.sin / torch.cos use the 1-ULP ones,
// about twice as slow; either is far inside the float32 rounding of the phases themselves), and
// sincos gives both from one range reduction. The default build (no SIMD) uses libm.

#if defined(CPU_CAPABILITY_AVX512) || defined(CPU_CAPABILITY_AVX2)
#include <immintrin.h>
#include <sleef.h>
#endif

using VecF = at::vec::Vectorized<float>;
using VecD = at::vec::Vectorized<double>;

#if defined(CPU_CAPABILITY_AVX512)
inline VecF vsin(VecF v) { return Sleef_sinf16_u35(v); }
inline VecD vsin(VecD v) { return Sleef_sind8_u35(v); }
inline VecF vcos(VecF v) { return Sleef_cosf16_u35(v); }
inline VecD vcos(VecD v) { return Sleef_cosd8_u35(v); }
inline void vsincos(VecF v, VecF& s, VecF& c) { const auto r = Sleef_sincosf16_u35(v); s = r.x, c = r.y; }
inline void vsincos(VecD v, VecD& s, VecD& c) { const auto r = Sleef_sincosd8_u35(v); s = r.x, c = r.y; }
#elif defined(CPU_CAPABILITY_AVX2)
inline VecF vsin(VecF v) { return Sleef_sinf8_u35(v); }
inline VecD vsin(VecD v) { return Sleef_sind4_u35(v); }
inline VecF vcos(VecF v) { return Sleef_cosf8_u35(v); }
inline VecD vcos(VecD v) { return Sleef_cosd4_u35(v); }
inline void vsincos(VecF v, VecF& s, VecF& c) { const auto r = Sleef_sincosf8_u35(v); s = r.x, c = r.y; }
inline void vsincos(VecD v, VecD& s, VecD& c) { const auto r = Sleef_sincosd4_u35(v); s = r.x, c = r.y; }
#else
template <typename V>
V vsin(V v) { return v.sin(); }
template <typename V>
V vcos(V v) { return v.cos(); }
template <typename V>
void vsincos(V v, V& s, V& c) { s = v.sin(), c = v.cos(); }
#endif

template <typename T>
void simd_sin(const T* x, T* out, int64_t n) {
  at::vec::map([](at::vec::Vectorized<T> v) { return vsin(v); }, out, x, n);
}

template <typename T>
void simd_cos(const T* x, T* out, int64_t n) {
  at::vec::map([](at::vec::Vectorized<T> v) { return vcos(v); }, out, x, n);
}

template <typename T>
void simd_sincos(const T* x, T* s, T* c, int64_t n) {
  using V = at::vec::Vectorized<T>;
  int64_t i = 0;
  V vs, vc;
  for (; i + V::size() <= n; i += V::size()) {
    vsincos(V::loadu(x + i), vs, vc);
    vs.store(s + i), vc.store(c + i);
  }
  if (i < n) {
    vsincos(V::loadu(x + i, n - i), vs, vc);
    vs.store(s + i, n - i), vc.store(c + i, n - i);
  }
}

template <typename T>
void simd_exp(const T* x, T* out, int64_t n) {
  at::vec::map([](at::vec::Vectorized<T> v) { return v.exp(); }, out, x, n);
}

template <typename T>
void simd_expm1(const T* x, T* out, int64_t n) {
  at::vec::map([](at::vec::Vectorized<T> v) { return v.expm1(); }, out, x, n);
}

// --- stream compaction: keep the flagged entries of a batch's arrays, in order, in place -------
//
// The chord step keeps the pixels that hit their primitive (two thirds of a batch at 504×378) in
// about twenty arrays: an index-by-index copy cost as much as the ray–ellipsoid algebra itself. Here
// each SIMD chunk of an array is moved with one compress (AVX-512) or one table-driven permute
// (AVX2); float64 and the default build copy entry by entry without branches. Every compacted array
// holds kCompactPad entries past its capacity: the vector paths read and write whole chunks.

constexpr int64_t kCompactPad = 16;

struct Compaction {
#if defined(CPU_CAPABILITY_AVX512)
  static constexpr int kChunk = 16;
#else
  static constexpr int kChunk = 8;
#endif
  std::vector<uint32_t> bits;  // per chunk of kChunk entries: bit i keeps entry chunk · kChunk + i
  std::vector<uint8_t> flags;  // per entry, 0 or 1
  int64_t m = 0, n = 0;        // entries, entries kept

  explicit Compaction(int64_t capacity)
      : bits((capacity + kChunk - 1) / kChunk + 1), flags(capacity + kCompactPad, 0) {}

  // after the caller has set flags[0, m): the chunk masks and the number kept
  void plan(int64_t m_) {
    m = m_, n = 0;
    for (int64_t c = 0; c * kChunk < m; ++c) {
      uint32_t b = 0;
      const int64_t j0 = c * kChunk, len = std::min<int64_t>(kChunk, m - j0);
      for (int64_t i = 0; i < len; ++i) b |= uint32_t(flags[j0 + i]) << i;
      bits[c] = b;
      n += __builtin_popcount(b);
    }
  }

  // the kept indices, in order
  void indices(int64_t* out) const {
    int64_t w = 0;
    for (int64_t j = 0; j < m; ++j) out[w] = j, w += flags[j];
  }

  template <typename T>
  void apply(T* f) const {
    if constexpr (std::is_same_v<T, float>) {
#if defined(CPU_CAPABILITY_AVX512)
      int64_t w = 0;
      for (int64_t c = 0; c * kChunk < m; ++c) {
        const __mmask16 k = __mmask16(bits[c]);
        // the register form of the compress and a whole store: the memory form is slow on some cores
        _mm512_storeu_ps(f + w, _mm512_maskz_compress_ps(k, _mm512_loadu_ps(f + c * kChunk)));
        w += __builtin_popcount(bits[c]);
      }
      return;
#elif defined(CPU_CAPABILITY_AVX2)
      int64_t w = 0;
      for (int64_t c = 0; c * kChunk < m; ++c) {
        const __m256i order = _mm256_load_si256(reinterpret_cast<const __m256i*>(avx2_order()[bits[c]].data()));
        _mm256_storeu_ps(f + w, _mm256_permutevar8x32_ps(_mm256_loadu_ps(f + c * kChunk), order));
        w += __builtin_popcount(bits[c]);
      }
      return;
#endif
    }
    int64_t w = 0;
    for (int64_t j = 0; j < m; ++j) f[w] = f[j], w += flags[j];
  }

#if defined(CPU_CAPABILITY_AVX2)
  // for each 8-bit mask, the lanes it keeps, in order, then zeros
  static const std::array<std::array<int32_t, 8>, 256>& avx2_order() {
    alignas(32) static const std::array<std::array<int32_t, 8>, 256> table = [] {
      std::array<std::array<int32_t, 8>, 256> t{};
      for (int mask = 0; mask < 256; ++mask) {
        int w = 0;
        for (int lane = 0; lane < 8; ++lane)
          if (mask & (1 << lane)) t[mask][w++] = lane;
      }
      return t;
    }();
    return table;
  }
#endif
};

// --- shared scalar pieces ---------------------------------------------------------------------

inline void check_params(const std::vector<at::Tensor>& tensors) {
  const at::ScalarType dtype = tensors[0].scalar_type();
  TORCH_CHECK(dtype == at::kFloat || dtype == at::kDouble, "fused kernels take float32 or float64, got ", dtype);
  for (const at::Tensor& t : tensors) {
    TORCH_CHECK(t.device().is_cpu(), "fused kernels run on the CPU");
    TORCH_CHECK(t.scalar_type() == dtype, "fused kernels need one dtype for all inputs");
    TORCH_CHECK(t.is_contiguous(), "fused kernels need contiguous inputs");
  }
}

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

// The window's twin of sinc (kernels.py: window_integral): W(x) = ½∫_{−1}^{1} (1 − t²) cos(x t) dt
// = 2 (sin x − x cos x)/x³, by its series below |x| = 1, where the difference cancels.
template <typename T>
inline T window_integral(T x, T sin_x, T cos_x) {
  const T x2 = x * x;
  if (std::abs(x) < T(1))
    return T(2) / T(3) -
           x2 * (T(1) / T(15) - x2 * (T(1) / T(420) - x2 * (T(1) / T(22680) - x2 * (T(1) / T(1995840) - x2 / T(259459200)))));
  return T(2) * (sin_x - x * cos_x) / (x2 * x);
}

// W'(x) = 2 sin x / x² − 3 W / x, by its series −2x/15 + x³/105 − … below |x| = 1.
template <typename T>
inline T window_slope(T x, T sin_x, T w) {
  const T x2 = x * x;
  if (std::abs(x) < T(1))
    return -x * (T(2) / T(15) -
                 x2 * (T(1) / T(105) - x2 * (T(1) / T(3780) - x2 * (T(1) / T(249480) - x2 / T(25945920)))));
  return T(2) * sin_x / x2 - T(3) * w / x;
}

// Paper eq. 9 with the 3DGS clamps, given expm1(−max(0, I)):
// α = min(0.99, 1 − exp(−max(0, I))), and 0 below 1/255.
template <typename T>
inline T alpha_from_expm1(T expm1_neg_depth) {
  const T alpha = std::min(T(kAlphaMax), -expm1_neg_depth);
  return alpha < T(kAlphaMin) ? T(0) : alpha;
}

// ∂α/∂I = exp(−I) where neither the 0.99 clamp nor the 1/255 skip is active (I < 0, where
// clamp_min(I, 0) blocks the gradient, gives α = 0 and is skipped too)
template <typename T>
inline T alpha_slope_from_expm1(T expm1_neg_depth) {
  const bool passes = !(-expm1_neg_depth > T(kAlphaMax)) && alpha_from_expm1(expm1_neg_depth) != T(0);
  return passes ? expm1_neg_depth + T(1) : T(0);
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
  T gain;          // the density window's 1.5 (kernels.py: windowed_optical_depth), 0: the hard-edged ellipsoid
};

template <typename T>
struct NeuralTensors {  // the (P, ...) parameter tensors of all primitives
  int64_t P, N;
  const T *m_cam, *o_ell, *w_cam, *c, *w2, *b2, *inv_smax;
  T gain;  // 1.5: the windowed density of every primitive (prims.window); 0: hard-edged

  NeuralParams<T> primitive(int64_t p) const {
    return {m_cam + 9 * p, o_ell + 3 * p, w_cam + 3 * N * p, c + N * p, w2 + N * p, b2[p], inv_smax[p], gain};
  }
};

template <typename T>
NeuralTensors<T> neural_tensors(const at::Tensor& m_cam, const at::Tensor& o_ell, const at::Tensor& w_cam,
                                const at::Tensor& c, const at::Tensor& w2, const at::Tensor& b2,
                                const at::Tensor& inv_smax, double gain) {
  return {c.size(0), c.size(1), m_cam.data_ptr<T>(), o_ell.data_ptr<T>(), w_cam.data_ptr<T>(),
          c.data_ptr<T>(), w2.data_ptr<T>(), b2.data_ptr<T>(), inv_smax.data_ptr<T>(), T(gain)};
}

// Where one primitive's gradient sums go (double; NeuralGradSums or a slice of a per-thread buffer).
struct NeuralGradRefs {
  double *m_cam, *o_ell, *w_cam, *c, *w2, *b2, *inv_smax;
};

// Number of doubles of one primitive's gradient sums, and their layout in a flat buffer.
inline int64_t neural_grad_stride(int64_t units) { return 9 + 3 + 3 * units + units + units + 2; }

inline NeuralGradRefs neural_grad_refs(double* base, int64_t units) {
  double* w_cam = base + 12;
  double* c = w_cam + 3 * units;
  double* w2 = c + units;
  return {base, base + 9, w_cam, c, w2, w2 + units, w2 + units + 1};
}

// Per-thread scratch for a batch of one primitive's pixels, one array entry per pixel j (structure
// of arrays, so that the loops over j run in SIMD). kUnits > 0 fixes the number of hidden units at
// compile time (the default 8 of pipeline.yaml: the loops over units then unroll into one 8-lane
// vector each, which matters when a batch has one or two pixels, the usual case at 64×64); 0 takes
// it at run time. `chords` fills it for every pixel of the
// batch, then keeps the n pixels whose chord is not empty (hit and Δ > 0): the others have α = 0
// and no gradient.
template <typename T, int kUnits = 0>
struct ChordTile {
  int64_t cap, n = 0;
  std::vector<int64_t> pixel;            // index of the pixel in the batch
  Compaction keep;                       // which pixels of the batch have a chord
  // step 1, entry and exit
  std::vector<T> d0, d1, d2;             // unit camera-space direction d̂
  std::vector<T> l_near;                 // ray distance of the near plane
  std::vector<T> e0, e1, e2;             // d' = M d̂
  std::vector<T> A, l_mid;               // A = d'·d', ℓ* = −(o'·d')/A, the ray's closest approach to the centre
  std::vector<T> p0, p1, p2;             // p = o' + ℓ* d', the closest point (|p| < 1: a hit)
  std::vector<T> half;                   // half the chord, √((1 − |p|²)/A)
  std::vector<T> l_in_raw, l_in, l_out;  // entry before and after the near-plane clip, exit
  std::vector<T> delta, tau_m;           // Δ = max(ℓ_out − ℓ_in, 0)/max(s), τ_m = (ℓ_in + ℓ_out)/2/max(s)
  std::vector<T> clip, kappa;            // window: e = (ℓ_in − ℓ_in,raw)/max(s), the near plane's cut; κ = A max(s)²
  // step 2, the MLP integral, for pixel j and unit k at [j * units + k] (SIMD over both: a batch
  // of a small splat has few pixels, but every pixel has `units` terms); a `wide` batch (windowed,
  // kWideBatch pixels or more: the usual batch of a full-size view) at [k * n + j] instead, so that
  // the loops over units run in SIMD over the pixels with no horizontal sum per pixel
  int64_t units;
  bool wide = false;
  static constexpr int64_t kWideBatch = 16;
  std::vector<T> w_t;                    // the primitive's w_cam transposed, (3, N)
  std::vector<T> a;                      // a_k = w_cam_k · d̂
  // the phases a_k τ_m + c_k at [0, L) and x = a_k Δ/2 at [L, 2L) of one buffer (L = n · units),
  // and their sines and cosines: the backward takes both of both in one SIMD sincos pass
  std::vector<T> px, sin_px, cos_px;
  T *phase = nullptr, *x = nullptr, *cos_p = nullptr, *sin_x = nullptr, *sin_p = nullptr, *cos_x = nullptr;  // set by optical_depth
  std::vector<T> sinc_x, slope;
  std::vector<T> win, win_slope;         // window: W(x) = ½∫(1 − t²) cos(x t) dt and W'(x), per (pixel, unit)
  std::vector<T> inner, g_clip, g_kappa; // window: I / (1.5 κ) per pixel; backward: ∂L/∂e, ∂L/∂κ
  std::vector<double> sum_c, sum_w2, sum_wx, sum_wy, sum_wz;  // backward: per-unit gradient sums
  std::vector<T> integral;               // I
  std::vector<T> g_scaled;               // backward of a wide batch: ∂L/∂I · 1.5 κ per pixel
  std::vector<T> neg_depth, expm1_neg;   // −max(I, 0) and expm1 of it (eq. 9)
  // backward: ∂L/∂I, ∂L/∂τ_m, ∂L/∂Δ, ∂L/∂p_r, ∂L/∂ℓ* / A, ∂L/∂A
  std::vector<T> g_I, g_tau, g_delta, g_p0, g_p1, g_p2, g_mid, g_A;

  ChordTile(int64_t n_units, int64_t capacity, bool backward) : cap(capacity), keep(capacity), units(n_units) {
    for (auto* buf : chord_fields()) buf->resize(cap + kCompactPad);
    for (auto* buf : {&integral, &neg_depth, &expm1_neg, &g_I, &inner}) buf->resize(cap);
    for (auto* buf : {&a, &sinc_x, &win}) buf->resize(cap * units);
    for (auto* buf : {&px, &sin_px, &cos_px}) buf->resize(2 * cap * units);
    w_t.resize(3 * units);
    pixel.resize(cap);
    if (backward) {
      for (auto* buf : {&slope, &win_slope}) buf->resize(cap * units);
      for (auto* buf : {&sum_c, &sum_w2, &sum_wx, &sum_wy, &sum_wz}) buf->resize(units);
      for (auto* buf : {&g_tau, &g_delta, &g_p0, &g_p1, &g_p2, &g_mid, &g_A, &g_clip, &g_kappa, &g_scaled})
        buf->resize(cap);
    }
  }

  std::array<std::vector<T>*, 20> chord_fields() {
    return {&d0, &d1, &d2, &l_near, &e0, &e1, &e2, &A, &l_mid, &p0, &p1, &p2, &half,
            &l_in_raw, &l_in, &l_out, &delta, &tau_m, &clip, &kappa};
  }

  // Step 1 for image points (u, v)[0, m) (rasterize.py: _camera_directions, kernels.py:
  // ray_ellipsoid): o' + ℓ d' enters and leaves the unit sphere at ℓ* ∓ √((1 − |p|²)/A). The
  // closest-approach form has no cancellation at grazing rays, where B² − AC of the quadratic
  // loses all its digits in float32 for a primitive many radii away. Keeps the pixels with a chord
  // (with `grad`, also a nonzero upstream gradient, which is kept in g_I).
  void chords(const T* u, const T* v, int64_t m, const Intrinsics<T>& k, const NeuralParams<T>& q, const T* grad,
              bool backward) {
    directions(u, v, m, k, d0.data(), d1.data(), d2.data(), l_near.data());
    intersect(m, q, grad, backward);
  }

  // d̂ = normalize((u − cx)/fx, (v − cy)/fy, 1), and the near plane at ℓ = near · |(…)|
  static void directions(const T* u, const T* v, int64_t m, const Intrinsics<T>& k, T* dx, T* dy, T* dz, T* ln) {
#pragma omp simd
    for (int64_t j = 0; j < m; ++j) {
      const T xn = (u[j] - k.cx) / k.fx, yn = (v[j] - k.cy) / k.fy;
      const T norm = std::sqrt(xn * xn + yn * yn + T(1));
      dx[j] = xn / norm;
      dy[j] = yn / norm;
      dz[j] = T(1) / norm;
      ln[j] = k.near * norm;
    }
  }

  // Step 1 given the directions d0, d1, d2 and l_near of m pixels; `backward` keeps every field
  // for chords_backward (the forward needs only d̂, Δ and τ_m).
  void intersect(int64_t m, const NeuralParams<T>& q, const T* grad, bool backward) {
    const T* M = q.m_cam;
    const T* o = q.o_ell;
#pragma omp simd
    for (int64_t j = 0; j < m; ++j) {
      e0[j] = M[0] * d0[j] + M[1] * d1[j] + M[2] * d2[j];
      e1[j] = M[3] * d0[j] + M[4] * d1[j] + M[5] * d2[j];
      e2[j] = M[6] * d0[j] + M[7] * d1[j] + M[8] * d2[j];
      A[j] = e0[j] * e0[j] + e1[j] * e1[j] + e2[j] * e2[j];
      l_mid[j] = -(o[0] * e0[j] + o[1] * e1[j] + o[2] * e2[j]) / A[j];
      p0[j] = o[0] + l_mid[j] * e0[j];
      p1[j] = o[1] + l_mid[j] * e1[j];
      p2[j] = o[2] + l_mid[j] * e2[j];
      const T h = p0[j] * p0[j] + p1[j] * p1[j] + p2[j] * p2[j];
      const bool hit = h < T(1);
      half[j] = std::sqrt(hit ? (T(1) - h) / A[j] : T(1));
      l_in_raw[j] = l_mid[j] - half[j];
      l_out[j] = l_mid[j] + half[j];
      l_in[j] = std::max(l_in_raw[j], l_near[j]);  // camera inside: start at the near plane
      // a miss contributes nothing (where(hit, I, 0)); give it no chord
      delta[j] = hit ? std::max(l_out[j] - l_in[j], T(0)) * q.inv_smax : T(0);
      tau_m[j] = T(0.5) * (l_in[j] + l_out[j]) * q.inv_smax;
      clip[j] = (l_in[j] - l_in_raw[j]) * q.inv_smax;
      kappa[j] = A[j] / (q.inv_smax * q.inv_smax);
    }
    // a miss, or an empty chord (I = 0 < 1/255), is dropped; so is a pixel without upstream gradient
    uint8_t* flag = keep.flags.data();
    if (grad == nullptr) {
#pragma omp simd
      for (int64_t j = 0; j < m; ++j) flag[j] = delta[j] > T(0);
    } else {
#pragma omp simd
      for (int64_t j = 0; j < m; ++j) flag[j] = delta[j] > T(0) && grad[j] != T(0);
    }
    keep.plan(m);
    n = keep.n;
    keep.indices(pixel.data());
    if (grad != nullptr)
      for (int64_t i = 0; i < n; ++i) g_I[i] = grad[pixel[i]];
    if (n == m) return;
    const auto compact = [&](std::vector<T>& field) { keep.apply(field.data()); };
    if (backward) {
      for (auto* field : chord_fields()) compact(*field);
    } else if (q.gain != T(0)) {
      for (auto* field : {&d0, &d1, &d2, &delta, &tau_m, &clip, &kappa}) compact(*field);
    } else {
      for (auto* field : {&d0, &d1, &d2, &delta, &tau_m}) compact(*field);
    }
  }

  // Step 2, paper eq. 7–8 in the stable sinc form (kernels.py: neural_optical_depth):
  //   I = Σ_k W2_k Δ cos(a_k τ_m + c_k) sinc(a_k Δ / 2) + b2 Δ,   a_k = ω0 W1_k · d̂;
  // with `backward`, also sin of the phase and sinc's slope. Then eq. 9:
  // expm1_neg = expm1(−max(I, 0)), α = alpha_from_expm1(expm1_neg).
  void optical_depth(const NeuralParams<T>& q, bool backward) {
    if (n == 0) return;   // every pixel missed: nothing to evaluate
    const int64_t N = kUnits > 0 ? kUnits : units, L = n * N;
    T *wx = w_t.data(), *wy = wx + N, *wz = wy + N;
    for (int64_t k = 0; k < N; ++k) wx[k] = q.w_cam[3 * k], wy[k] = q.w_cam[3 * k + 1], wz[k] = q.w_cam[3 * k + 2];
    const T* c = q.c;
    phase = px.data(), x = px.data() + L;
    sin_p = sin_px.data(), sin_x = sin_px.data() + L, cos_p = cos_px.data(), cos_x = cos_px.data() + L;
    wide = q.gain != T(0) && n >= kWideBatch;
    if (wide) {
      for (int64_t k = 0; k < N; ++k) {
        const T wxk = wx[k], wyk = wy[k], wzk = wz[k], ck = c[k];
        T *ak = a.data() + k * n, *pk = phase + k * n, *xk = x + k * n;
#pragma omp simd
        for (int64_t j = 0; j < n; ++j) {
          ak[j] = wxk * d0[j] + wyk * d1[j] + wzk * d2[j];
          pk[j] = ak[j] * tau_m[j] + ck;
          xk[j] = T(0.5) * ak[j] * delta[j];
        }
      }
      return windowed_optical_depth(q, backward, N, L);
    }
    for (int64_t j = 0; j < n; ++j) {
      const T dx = d0[j], dy = d1[j], dz = d2[j], tm = tau_m[j], dl = delta[j];
      T *aj = a.data() + j * N, *pj = phase + j * N, *xj = x + j * N;
#pragma omp simd
      for (int64_t k = 0; k < N; ++k) {
        aj[k] = wx[k] * dx + wy[k] * dy + wz[k] * dz;
        pj[k] = aj[k] * tm + c[k];
        xj[k] = T(0.5) * aj[k] * dl;
      }
    }
    if (q.gain != T(0)) return windowed_optical_depth(q, backward, N, L);
    if (backward) {  // also sin of the phase and cos of x, from the same range reductions
      simd_sincos(px.data(), sin_px.data(), cos_px.data(), 2 * L);
    } else {
      simd_cos(phase, cos_p, L);
      simd_sin(x, sin_x, L);
    }
    const T *xs = x, *sx = sin_x;
    T* s = sinc_x.data();
#pragma omp simd
    for (int64_t e = 0; e < L; ++e) s[e] = sinc(xs[e], sx[e]);
    for (int64_t j = 0; j < n; ++j) {
      const T* cj = cos_p + j * N;
      const T* sj = s + j * N;
      T sum = T(0);
      for (int64_t k = 0; k < N; ++k) sum += q.w2[k] * delta[j] * cj[k] * sj[k];  // in order, as the twin
      integral[j] = sum + q.b2 * delta[j];
      neg_depth[j] = -std::max(integral[j], T(0));
    }
    simd_expm1(neg_depth.data(), expm1_neg.data(), n);
    if (backward) {
      const T* cx = cos_x;
      T* sl = slope.data();
#pragma omp simd
      for (int64_t e = 0; e < L; ++e) sl[e] = sinc_slope(xs[e], cx[e], s[e]);
    }
  }

  // Step 2 for the windowed density 1.5 (1 − r²) σ (kernels.py: windowed_optical_depth), e the
  // near plane's cut, κ = A max(s)², x_k = a_k Δ/2, W = window_integral:
  //   I = 1.5 κ [Σ_k W2_k (cos φ_k Δ³/4 W(x_k) + e Δ²/2 (cos φ_k sinc x_k + sin φ_k x_k W(x_k)/2))
  //              + b2 (Δ³/6 + e Δ²/2)];
  // sin φ enters only the cut's term (and the backward): a batch with no cut chord skips it.
  void windowed_optical_depth(const NeuralParams<T>& q, bool backward, int64_t N, int64_t L) {
    bool cut_any = false;  // the near plane cuts a chord of this batch: its term needs sin φ
    for (int64_t j = 0; j < n; ++j) cut_any = cut_any || clip[j] != T(0);
    if (backward || cut_any) {
      simd_sincos(px.data(), sin_px.data(), cos_px.data(), 2 * L);
    } else {
      simd_cos(phase, cos_p, L);
      simd_sincos(x, sin_x, cos_x, L);
    }
    const T *xs = x, *sx = sin_x, *cx = cos_x;
    T *s = sinc_x.data(), *w = win.data();
#pragma omp simd
    for (int64_t e = 0; e < L; ++e) {
      s[e] = sinc(xs[e], sx[e]);
      w[e] = window_integral(xs[e], sx[e], cx[e]);
    }
    if (backward) {
      T* ws = win_slope.data();
#pragma omp simd
      for (int64_t e = 0; e < L; ++e) ws[e] = window_slope(xs[e], sx[e], w[e]);
    }
    if (wide) return windowed_sums_wide(q, N, cut_any);
    for (int64_t j = 0; j < n; ++j) {
      const T dl = delta[j], cut = clip[j];
      const T d3 = T(0.25) * dl * dl * dl, d2 = T(0.5) * dl * dl;
      const T *cj = cos_p + j * N, *spj = sin_p + j * N, *sj = s + j * N, *wj = w + j * N, *xj = xs + j * N;
      T sum = T(0);
      if (cut == T(0)) {  // the usual chord, whole: only the first term (and sin φ may not be there)
        for (int64_t k = 0; k < N; ++k) sum += q.w2[k] * (cj[k] * d3 * wj[k]);
      } else {
        for (int64_t k = 0; k < N; ++k)
          sum += q.w2[k] * (cj[k] * d3 * wj[k] + cut * d2 * (cj[k] * sj[k] + spj[k] * (T(0.5) * xj[k] * wj[k])));
      }
      inner[j] = sum + q.b2 * (dl * dl * dl / T(6) + cut * (T(0.5) * dl * dl));
      integral[j] = q.gain * kappa[j] * inner[j];
      neg_depth[j] = -std::max(integral[j], T(0));
    }
    simd_expm1(neg_depth.data(), expm1_neg.data(), n);
  }

  // windowed_optical_depth's sums for a wide batch: the same terms in the same order per pixel
  // (units ascending), each unit's in SIMD over the pixels
  void windowed_sums_wide(const NeuralParams<T>& q, int64_t N, bool cut_any) {
    T* sum = inner.data();
    std::fill(sum, sum + n, T(0));
    const T *dl = delta.data(), *cut = clip.data();
    for (int64_t k = 0; k < N; ++k) {
      const T w2k = q.w2[k];
      const T *C = cos_p + k * n, *W = win.data() + k * n;
      if (!cut_any) {  // sin φ was not computed: only the whole chord's term
#pragma omp simd
        for (int64_t j = 0; j < n; ++j) sum[j] += w2k * (C[j] * (T(0.25) * dl[j] * dl[j] * dl[j]) * W[j]);
      } else {
        const T *S = sinc_x.data() + k * n, *SP = sin_p + k * n, *X = x + k * n;
#pragma omp simd
        for (int64_t j = 0; j < n; ++j) {
          const T d3 = T(0.25) * dl[j] * dl[j] * dl[j], dl2 = T(0.5) * dl[j] * dl[j];
          const T whole = C[j] * d3 * W[j];
          sum[j] += cut[j] == T(0) ? w2k * whole : w2k * (whole + cut[j] * dl2 * (C[j] * S[j] + SP[j] * (T(0.5) * X[j] * W[j])));
        }
      }
    }
#pragma omp simd
    for (int64_t j = 0; j < n; ++j) {
      inner[j] = sum[j] + q.b2 * (dl[j] * dl[j] * dl[j] / T(6) + cut[j] * (T(0.5) * dl[j] * dl[j]));
      integral[j] = q.gain * kappa[j] * inner[j];
      neg_depth[j] = -std::max(integral[j], T(0));
    }
    simd_expm1(neg_depth.data(), expm1_neg.data(), n);
  }

  // Step 2 backward for the windowed density: from g_I to g_tau, g_delta, g_clip and g_kappa, and
  // the sums for c, w2, w_cam and b2 (sinc' = −j1 and j1' = f2 with j1 = x W/2, f2 = (W + x W')/2).
  // A whole chord (e = 0, the usual case) takes the loop without the cut's terms; e's gradient
  // there would reach ℓ_in and ℓ_in_raw alike and cancel (chords_backward), so g_clip = 0.
  void windowed_optical_depth_backward(const NeuralParams<T>& q, const NeuralGradRefs& acc) {
    const int64_t N = kUnits > 0 ? kUnits : units;
    if (wide) return windowed_backward_wide(q, acc, N);
    for (auto* buf : {&sum_c, &sum_w2, &sum_wx, &sum_wy, &sum_wz}) std::fill(buf->begin(), buf->end(), 0.0);
    double sum_b2 = 0;
    for (int64_t j = 0; j < n; ++j) {
      const T gk = g_I[j] * q.gain * kappa[j], dl = delta[j], cut = clip[j];
      sum_b2 += double(gk * (dl * dl * dl / T(6) + cut * (T(0.5) * dl * dl)));
      if (cut == T(0))
        windowed_pixel_backward<false>(q, j, N, gk);
      else
        windowed_pixel_backward<true>(q, j, N, gk);
      g_kappa[j] = g_I[j] * q.gain * inner[j];
    }
    add_unit_sums(acc, N, sum_b2);
  }

  // windowed_optical_depth_backward for a wide batch: the per-pixel sums over the units accumulate
  // in g_tau, g_delta and g_clip, each unit's sums are SIMD reductions over the pixels
  void windowed_backward_wide(const NeuralParams<T>& q, const NeuralGradRefs& acc, int64_t N) {
    const T *dl = delta.data(), *cut = clip.data();
    T* gk = g_scaled.data();
    bool cut_any = false;
    double sum_b2 = 0;
#pragma omp simd reduction(+ : sum_b2) reduction(|| : cut_any)
    for (int64_t j = 0; j < n; ++j) {
      const T dl2 = T(0.5) * dl[j] * dl[j];
      gk[j] = g_I[j] * q.gain * kappa[j];
      sum_b2 += double(gk[j] * (dl[j] * dl[j] * dl[j] / T(6) + cut[j] * dl2));
      g_tau[j] = T(0);
      g_delta[j] = gk[j] * q.b2 * (dl2 + cut[j] * dl[j]);
      g_clip[j] = gk[j] * q.b2 * dl2;
      g_kappa[j] = g_I[j] * q.gain * inner[j];
      cut_any = cut_any || cut[j] != T(0);
    }
    for (int64_t k = 0; k < N; ++k) {
      if (cut_any)
        wide_unit_backward<true>(k, q, acc);
      else
        wide_unit_backward<false>(k, q, acc);
    }
    *acc.b2 += sum_b2;
    // a whole chord's e gets no gradient (see windowed_optical_depth_backward)
    for (int64_t j = 0; j < n; ++j)
      if (cut[j] == T(0)) g_clip[j] = T(0);
  }

  // unit k of windowed_backward_wide, in SIMD over the pixels: windowed_pixel_backward's terms
  // (kCut: the batch has a cut chord; a whole chord's cut terms are then × e = 0)
  template <bool kCut>
  void wide_unit_backward(int64_t k, const NeuralParams<T>& q, const NeuralGradRefs& acc) {
    const int64_t o = k * n;
    const T w2k = q.w2[k];
    const T *dl = delta.data(), *cut = clip.data(), *tm = tau_m.data(), *gk = g_scaled.data();
    const T *ak = a.data() + o, *SC = sinc_x.data() + o, *C = cos_p + o, *SP = sin_p + o;
    const T *W = win.data() + o, *WS = win_slope.data() + o, *X = x + o;
    double s_c = 0, s_w2 = 0, s_x = 0, s_y = 0, s_z = 0;
#pragma omp simd reduction(+ : s_c, s_w2, s_x, s_y, s_z)
    for (int64_t j = 0; j < n; ++j) {
      const T d3 = T(0.25) * dl[j] * dl[j] * dl[j], d3_dl = T(0.75) * dl[j] * dl[j], gw = gk[j] * w2k;
      const T Cj = C[j], Sj = SP[j], Wj = W[j];
      T f = Cj * d3 * Wj, f_phase = -Sj * d3 * Wj, f_x = Cj * d3 * WS[j], f_dl = Cj * d3_dl * Wj;  // F and ∂F/∂(φ, x, Δ)
      if constexpr (kCut) {
        const T e = cut[j], dl2 = T(0.5) * dl[j] * dl[j];
        const T j1 = T(0.5) * X[j] * Wj, f2 = T(0.5) * (Wj + X[j] * WS[j]);
        const T cut_term = Cj * SC[j] + Sj * j1;  // the near plane's bracket
        f += e * dl2 * cut_term;
        f_phase += e * dl2 * (Cj * j1 - Sj * SC[j]);
        f_x += e * dl2 * (Sj * f2 - Cj * j1);
        f_dl += e * dl[j] * cut_term;
        g_clip[j] += gw * dl2 * cut_term;
      }
      const T g_phase = gw * f_phase, g_x = gw * f_x;
      const T g_a = g_phase * tm[j] + T(0.5) * g_x * dl[j];
      g_tau[j] += g_phase * ak[j];
      g_delta[j] += gw * f_dl + T(0.5) * g_x * ak[j];
      s_c += double(g_phase);
      s_w2 += double(gk[j] * f);
      s_x += double(g_a * d0[j]);  // a_k = w_cam_k · d̂
      s_y += double(g_a * d1[j]);
      s_z += double(g_a * d2[j]);
    }
    acc.c[k] += s_c;
    acc.w2[k] += s_w2;
    acc.w_cam[3 * k] += s_x;
    acc.w_cam[3 * k + 1] += s_y;
    acc.w_cam[3 * k + 2] += s_z;
  }

  // the batch's per-unit sums (and b2's) into the primitive's gradient sums
  void add_unit_sums(const NeuralGradRefs& acc, int64_t N, double sum_b2) const {
    *acc.b2 += sum_b2;
    for (int64_t k = 0; k < N; ++k) {
      acc.c[k] += sum_c[k];
      acc.w2[k] += sum_w2[k];
      acc.w_cam[3 * k] += sum_wx[k];
      acc.w_cam[3 * k + 1] += sum_wy[k];
      acc.w_cam[3 * k + 2] += sum_wz[k];
    }
  }

  // pixel j of windowed_optical_depth_backward, gk = ∂L/∂I · 1.5 κ; kCut: its chord is cut (e > 0)
  template <bool kCut>
  void windowed_pixel_backward(const NeuralParams<T>& q, int64_t j, int64_t N, T gk) {
    double *sc = sum_c.data(), *sw2 = sum_w2.data(), *swx = sum_wx.data(), *swy = sum_wy.data(), *swz = sum_wz.data();
    const T dl = delta[j], cut = clip[j], tm = tau_m[j], dx = d0[j], dy = d1[j], dz = d2[j];
    const T d3 = T(0.25) * dl * dl * dl, d2 = T(0.5) * dl * dl, d3_dl = T(0.75) * dl * dl;
    const int64_t o = j * N;
    const T *aj = a.data() + o, *sj = sinc_x.data() + o, *cj = cos_p + o, *spj = sin_p + o;
    const T *wj = win.data() + o, *wsj = win_slope.data() + o, *xj = x + o, *w2 = q.w2;
    T gt = T(0), gd = gk * q.b2 * (d2 + cut * dl), ge = kCut ? gk * q.b2 * d2 : T(0);
#pragma omp simd reduction(+ : gt, gd, ge)
    for (int64_t k = 0; k < N; ++k) {
      const T C = cj[k], S = spj[k], W = wj[k], gw = gk * w2[k];
      T f = C * d3 * W, f_phase = -S * d3 * W, f_x = C * d3 * wsj[k], f_dl = C * d3_dl * W;  // F and ∂F/∂(φ, x, Δ)
      if constexpr (kCut) {
        const T j1 = T(0.5) * xj[k] * W, f2 = T(0.5) * (W + xj[k] * wsj[k]);
        const T cut_term = C * sj[k] + S * j1;  // the near plane's bracket
        f += cut * d2 * cut_term;
        f_phase += cut * d2 * (C * j1 - S * sj[k]);
        f_x += cut * d2 * (S * f2 - C * j1);
        f_dl += cut * dl * cut_term;
        ge += gw * d2 * cut_term;
      }
      const T g_phase = gw * f_phase, g_x = gw * f_x;
      const T g_a = g_phase * tm + T(0.5) * g_x * dl;
      gt += g_phase * aj[k];
      gd += gw * f_dl + T(0.5) * g_x * aj[k];
      sc[k] += double(g_phase);
      sw2[k] += double(gk * f);
      swx[k] += double(g_a * dx);  // a_k = w_cam_k · d̂
      swy[k] += double(g_a * dy);
      swz[k] += double(g_a * dz);
    }
    g_tau[j] = gt;
    g_delta[j] = gd;
    g_clip[j] = ge;
  }

  // Step 2 backward (kernels.py: _CosMLPIntegral.backward), + b2 Δ: from g_I to g_tau and
  // g_delta, and the sums for c, w2, w_cam and b2.
  void optical_depth_backward(const NeuralParams<T>& q, const NeuralGradRefs& acc) {
    if (q.gain != T(0)) return windowed_optical_depth_backward(q, acc);
    const int64_t N = kUnits > 0 ? kUnits : units;
    for (auto* buf : {&sum_c, &sum_w2, &sum_wx, &sum_wy, &sum_wz}) std::fill(buf->begin(), buf->end(), 0.0);
    double *sc = sum_c.data(), *sw2 = sum_w2.data(), *swx = sum_wx.data(), *swy = sum_wy.data(), *swz = sum_wz.data();
    const T* w2 = q.w2;
    double sum_b2 = 0;
    for (int64_t j = 0; j < n; ++j) {
      const T gI = g_I[j], dl = delta[j], tm = tau_m[j], dx = d0[j], dy = d1[j], dz = d2[j];
      sum_b2 += double(gI * dl);
      const int64_t o = j * N;
      const T *aj = a.data() + o, *sj = sinc_x.data() + o, *cj = cos_p + o, *spj = sin_p + o;
      const T* slj = slope.data() + o;
      T gt = T(0), gd = gI * q.b2;
#pragma omp simd reduction(+ : gt, gd)
      for (int64_t k = 0; k < N; ++k) {
        const T gwd = gI * w2[k] * dl;
        const T g_phase = -gwd * spj[k] * sj[k];  // ∂/∂(a_k τ_m + c_k)
        const T g_x = gwd * cj[k] * slj[k];       // ∂/∂(a_k Δ / 2)
        const T g_a = g_phase * tm + T(0.5) * g_x * dl;
        gt += g_phase * aj[k];
        gd += gI * w2[k] * cj[k] * sj[k] + T(0.5) * g_x * aj[k];
        sc[k] += double(g_phase);
        sw2[k] += double(gI * dl * cj[k] * sj[k]);
        swx[k] += double(g_a * dx);  // a_k = w_cam_k · d̂
        swy[k] += double(g_a * dy);
        swz[k] += double(g_a * dz);
      }
      g_tau[j] = gt;
      g_delta[j] = gd;
    }
    add_unit_sums(acc, N, sum_b2);
  }

  // Step 1 backward: from g_delta and g_tau to the sums for inv_smax, m_cam and o_ell, through
  // ℓ_in/out = ℓ* ∓ h, h = √((1 − |p|²)/A), p = o' + ℓ* d', ℓ* = −(o'·d')/A, A = d'·d', d' = M d̂.
  void chords_backward(const NeuralParams<T>& q, const NeuralGradRefs& acc) {
    const T* o = q.o_ell;
    const bool windowed = q.gain != T(0);
    const T inv2 = q.inv_smax * q.inv_smax;
    double sum_inv_smax = 0;
#pragma omp simd reduction(+ : sum_inv_smax)
    for (int64_t j = 0; j < n; ++j) {
      // the window's e = (ℓ_in − ℓ_in_raw)/max(s) and κ = A/(1/max(s))² (zero gradients without it)
      const T g_cut = windowed ? g_clip[j] : T(0), g_kap = windowed ? g_kappa[j] : T(0);
      // Δ = max(ℓ_out − ℓ_in, 0)/max(s) with Δ > 0 here, τ_m = (ℓ_in + ℓ_out)/2/max(s)
      sum_inv_smax += double(g_delta[j] * (l_out[j] - l_in[j]) + g_tau[j] * T(0.5) * (l_in[j] + l_out[j]));
      if (windowed) sum_inv_smax += double(g_cut * (l_in[j] - l_in_raw[j]) - T(2) * g_kap * A[j] / (inv2 * q.inv_smax));
      const T g_length = g_delta[j] * q.inv_smax;
      const T g_l_in = -g_length + T(0.5) * q.inv_smax * g_tau[j] + g_cut * q.inv_smax;
      const T g_l_out = g_length + T(0.5) * q.inv_smax * g_tau[j];
      // ℓ_in = maximum(ℓ_in_raw, ℓ_near): the near plane is a constant; half the gradient at a tie
      const T g_l_in_raw = (l_in_raw[j] > l_near[j] ? g_l_in : (l_in_raw[j] == l_near[j] ? T(0.5) * g_l_in : T(0))) -
                           g_cut * q.inv_smax;
      const T g_half = g_l_out - g_l_in_raw;
      // half = √s, s = (1 − |p|²)/A
      const T g_s = g_half / (T(2) * half[j]);
      const T g_h = -g_s / A[j];  // h = |p|²
      g_p0[j] = T(2) * g_h * p0[j];
      g_p1[j] = T(2) * g_h * p1[j];
      g_p2[j] = T(2) * g_h * p2[j];
      const T g_lmid = g_l_in_raw + g_l_out + g_p0[j] * e0[j] + g_p1[j] * e1[j] + g_p2[j] * e2[j];
      g_mid[j] = g_lmid / A[j];
      g_A[j] = -g_s * (half[j] * half[j]) / A[j] - g_mid[j] * l_mid[j] + g_kap / inv2;
    }
    *acc.inv_smax += sum_inv_smax;
    // the 12 sums over the pixels: in SIMD over pixels for a large batch (a whole-view render at
    // 504×378 has about 70 pixels a batch), pixel by pixel for a small one (one or two at 64×64)
    double sum_m[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0}, sum_o[3] = {0, 0, 0};
    if (n >= kSimdSums)
      chord_sums_simd(sum_m, sum_o, o);
    else
      for (int64_t j = 0; j < n; ++j) chord_sums_pixel(j, sum_m, sum_o, o);
    for (int i = 0; i < 9; ++i) acc.m_cam[i] += sum_m[i];
    for (int r = 0; r < 3; ++r) acc.o_ell[r] += sum_o[r];
  }

  static constexpr int64_t kSimdSums = 16;

  // pixel j's terms of chords_backward's sums: ∂L/∂M through d' = M d̂ and ∂L/∂o'
  void chord_sums_pixel(int64_t j, double* sum_m, double* sum_o, const T* o) const {
    const T* d[3] = {d0.data(), d1.data(), d2.data()};
    const T* e[3] = {e0.data(), e1.data(), e2.data()};
    const T* gp[3] = {g_p0.data(), g_p1.data(), g_p2.data()};
    for (int r = 0; r < 3; ++r) {
      // ∂L/∂d'_r: through p (ℓ* p_r), ℓ* (−o'_r/A) and A (2 d'_r)
      const T ge = l_mid[j] * gp[r][j] - g_mid[j] * o[r] + T(2) * g_A[j] * e[r][j];
      for (int f = 0; f < 3; ++f) sum_m[3 * r + f] += double(ge * d[f][j]);
      // ∂L/∂o'_r: through p (1) and ℓ* (−d'_r/A)
      sum_o[r] += double(gp[r][j]) - double(g_mid[j] * e[r][j]);
    }
  }

  // the same terms as chord_sums_pixel for every pixel, as twelve SIMD reductions in one pass
  void chord_sums_simd(double* sum_m, double* sum_o, const T* o) const {
    const T *D0 = d0.data(), *D1 = d1.data(), *D2 = d2.data(), *E0 = e0.data(), *E1 = e1.data(), *E2 = e2.data();
    const T *G0 = g_p0.data(), *G1 = g_p1.data(), *G2 = g_p2.data(), *Lm = l_mid.data(), *Gm = g_mid.data(),
            *Ga = g_A.data();
    double m0 = 0, m1 = 0, m2 = 0, m3 = 0, m4 = 0, m5 = 0, m6 = 0, m7 = 0, m8 = 0, s0 = 0, s1 = 0, s2 = 0;
#pragma omp simd reduction(+ : m0, m1, m2, m3, m4, m5, m6, m7, m8, s0, s1, s2)
    for (int64_t j = 0; j < n; ++j) {
      const T ge0 = Lm[j] * G0[j] - Gm[j] * o[0] + T(2) * Ga[j] * E0[j];
      const T ge1 = Lm[j] * G1[j] - Gm[j] * o[1] + T(2) * Ga[j] * E1[j];
      const T ge2 = Lm[j] * G2[j] - Gm[j] * o[2] + T(2) * Ga[j] * E2[j];
      m0 += double(ge0 * D0[j]), m1 += double(ge0 * D1[j]), m2 += double(ge0 * D2[j]);
      m3 += double(ge1 * D0[j]), m4 += double(ge1 * D1[j]), m5 += double(ge1 * D2[j]);
      m6 += double(ge2 * D0[j]), m7 += double(ge2 * D1[j]), m8 += double(ge2 * D2[j]);
      s0 += double(G0[j]) - double(Gm[j] * E0[j]);
      s1 += double(G1[j]) - double(Gm[j] * E1[j]);
      s2 += double(G2[j]) - double(Gm[j] * E2[j]);
    }
    const double m[9] = {m0, m1, m2, m3, m4, m5, m6, m7, m8};
    for (int i = 0; i < 9; ++i) sum_m[i] += m[i];
    sum_o[0] += s0, sum_o[1] += s1, sum_o[2] += s2;
  }
};

// =============================================================================================
// 3D Gaussian (EWA splat, as 3DGS; kernels.py: gaussian_alpha).

// power = −½ (c0 dx² + c2 dy²) − c1 dx dy with conic (c0, c1, c2) = inverse 2D covariance entries
template <typename T>
inline T gaussian_power(T dx, T dy, const T* conic) {
  return T(-0.5) * (conic[0] * dx * dx + conic[2] * dy * dy) - conic[1] * dx * dy;
}

// α = min(0.99, opacity exp(min(power, 0))), 0 below 1/255 or where power > 0
template <typename T>
inline T gaussian_alpha(T power, T value) {
  return (value < T(kAlphaMin) || power > T(0)) ? T(0) : value;
}

// α of a batch of m pixels from power and e = exp(min(power, 0)), the opacity clamped at 0.99, in
// two loops: written as one, GCC (with -fno-trapping-math) loads e only where power ≤ 0 and then
// leaves the loop scalar
template <typename T>
inline void gaussian_alpha_batch(const T* power, const T* e, T opacity, int64_t m, T* out) {
#pragma omp simd
  for (int64_t j = 0; j < m; ++j) out[j] = std::min(T(kAlphaMax), opacity * e[j]);
#pragma omp simd
  for (int64_t j = 0; j < m; ++j) out[j] = gaussian_alpha(power[j], out[j]);
}

// the gradient passes where α is neither skipped (α < 1/255 or power > 0) nor clamped at 0.99
template <typename T>
inline bool gaussian_passes(T power, T value) {
  return !(power > T(0)) && !(value > T(kAlphaMax)) && !(value < T(kAlphaMin));
}

// R(q̂) of a unit quaternion (w, x, y, z), row-major (core/geometry/rotations.py: quat_to_rotmat),
// and ∂L/∂q̂ from ∂L/∂R: the neural primitives' frame (prepare_kernels.cpp) and the relightable
// kinds' own frame (relight_kernels.cpp)
template <typename T>
void rotmat(const T* q, T* R) {
  const T w = q[0], x = q[1], y = q[2], z = q[3];
  R[0] = 1 - 2 * (y * y + z * z), R[1] = 2 * (x * y - w * z), R[2] = 2 * (x * z + w * y);
  R[3] = 2 * (x * y + w * z), R[4] = 1 - 2 * (x * x + z * z), R[5] = 2 * (y * z - w * x);
  R[6] = 2 * (x * z - w * y), R[7] = 2 * (y * z + w * x), R[8] = 1 - 2 * (x * x + y * y);
}

template <typename T>
void rotmat_backward(const T* q, const T* g, T* gq) {
  const T w = q[0], x = q[1], y = q[2], z = q[3];
  gq[0] = 2 * (-z * g[1] + y * g[2] + z * g[3] - x * g[5] - y * g[6] + x * g[7]);
  gq[1] = 2 * (y * g[1] + z * g[2] + y * g[3] - 2 * x * g[4] - w * g[5] + z * g[6] + w * g[7] - 2 * x * g[8]);
  gq[2] = 2 * (-2 * y * g[0] + x * g[1] + w * g[2] + x * g[3] + z * g[5] - w * g[6] + z * g[7] - 2 * y * g[8]);
  gq[3] = 2 * (-2 * z * g[0] - w * g[1] + x * g[2] + w * g[3] - 2 * z * g[4] + y * g[5] + x * g[6] + y * g[7]);
}

}  // namespace radfield
