// Fused CPU kernels of the rasteriser's two block kernels, forward and backward.
//
// They compute what the pure-torch twins in core/render/rasterize.py compute (`_neural_block`,
// `_gaussian_block`, built from core/splat/kernels.py), which stay the readable reference that
// tests/test_fused.py compares against, pair by pair: the per-pair code they share with the
// whole-view rasteriser (view_kernels.cpp) lives in pair_kernels.h, so these tests, which hit every
// branch on purpose, check the rasteriser's pair arithmetic too.
//
// Shapes: P primitives, A image points per primitive (its padded bounding-box pixels), N hidden
// units of the density MLP. All tensors contiguous, on the CPU, float32 or float64.
//
// Threads (OpenMP): the forward pass splits the P×A elements into (primitive, tile) work items;
// the backward pass gives each thread whole primitives, so the per-primitive gradient sums need
// no atomics.

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include "pair_kernels.h"

namespace {

using namespace radfield;

constexpr int64_t kTile = 128;  // pixels of one primitive evaluated together

template <typename T>
struct NeuralInputs {  // the whole block
  int64_t P, A, N;
  Intrinsics<T> k;
  const T *u, *v;
  NeuralTensors<T> params;
};

// Gradient sums of one primitive (double).
struct NeuralGradSums {
  std::vector<double> sums;
  explicit NeuralGradSums(int64_t units) : sums(neural_grad_stride(units), 0.0) {}
};

template <typename T>
NeuralInputs<T> neural_inputs(const at::Tensor& u, const at::Tensor& v, const at::Tensor& intrinsics,
                              const at::Tensor& m_cam, const at::Tensor& o_ell, const at::Tensor& w_cam,
                              const at::Tensor& c, const at::Tensor& w2, const at::Tensor& b2,
                              const at::Tensor& inv_smax, double gain) {
  return {u.size(0), u.size(1), c.size(1), read_intrinsics<T>(intrinsics), u.data_ptr<T>(), v.data_ptr<T>(),
          neural_tensors<T>(m_cam, o_ell, w_cam, c, w2, b2, inv_smax, gain)};
}

template <typename T>
void neural_forward_kernel(const NeuralInputs<T>& in, T* alpha) {
  const int64_t tiles = (in.A + kTile - 1) / kTile;
#pragma omp parallel num_threads(at::get_num_threads())
  {
    ChordTile<T> tile(in.N, kTile, /*backward=*/false);

#pragma omp for schedule(dynamic, 2)
    for (int64_t item = 0; item < in.P * tiles; ++item) {
      const int64_t p = item / tiles, a0 = (item % tiles) * kTile, a1 = std::min(a0 + kTile, in.A);
      const NeuralParams<T> q = in.params.primitive(p);
      T* out = alpha + p * in.A + a0;
      std::fill(out, out + (a1 - a0), T(0));
      tile.chords(in.u + p * in.A + a0, in.v + p * in.A + a0, a1 - a0, in.k, q, nullptr, /*backward=*/false);
      tile.optical_depth(q, /*backward=*/false);
      for (int64_t j = 0; j < tile.n; ++j) out[tile.pixel[j]] = alpha_from_expm1(tile.expm1_neg[j]);  // eq. 9
    }
  }
}

template <typename T>
void neural_backward_kernel(const NeuralInputs<T>& in, const T* grad, std::vector<at::Tensor>& out) {
  const int64_t N = in.N;
  T* g_out[7];
  for (int i = 0; i < 7; ++i) g_out[i] = out[i].data_ptr<T>();
  const int64_t sizes[7] = {9, 3, 3 * N, N, N, 1, 1};  // per primitive, in the order of NeuralGradRefs

#pragma omp parallel num_threads(at::get_num_threads())
  {
    ChordTile<T> tile(N, kTile, /*backward=*/true);

#pragma omp for schedule(dynamic, 1)
    for (int64_t p = 0; p < in.P; ++p) {
      const NeuralParams<T> q = in.params.primitive(p);
      NeuralGradSums acc(N);
      const NeuralGradRefs refs = neural_grad_refs(acc.sums.data(), N);
      for (int64_t a0 = 0; a0 < in.A; a0 += kTile) {
        const int64_t i0 = p * in.A + a0;
        tile.chords(in.u + i0, in.v + i0, std::min(a0 + kTile, in.A) - a0, in.k, q, grad + i0, /*backward=*/true);
        tile.optical_depth(q, /*backward=*/true);
        for (int64_t j = 0; j < tile.n; ++j) tile.g_I[j] *= alpha_slope_from_expm1(tile.expm1_neg[j]);
        tile.optical_depth_backward(q, refs);
        tile.chords_backward(q, refs);
      }
      const double* sum = acc.sums.data();
      for (int i = 0; i < 7; ++i) {
        for (int64_t e = 0; e < sizes[i]; ++e) g_out[i][sizes[i] * p + e] = T(sum[e]);
        sum += sizes[i];
      }
    }
  }
}

// --- checks and entry points ------------------------------------------------------------------

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
                                const at::Tensor& inv_smax, double gain) {
  check_neural(u, v, intrinsics, m_cam, o_ell, w_cam, c, w2, b2, inv_smax);
  at::Tensor alpha = at::empty_like(u);
  AT_DISPATCH_FLOATING_TYPES(u.scalar_type(), "neural_block_forward", [&] {
    neural_forward_kernel<scalar_t>(
        neural_inputs<scalar_t>(u, v, intrinsics, m_cam, o_ell, w_cam, c, w2, b2, inv_smax, gain),
        alpha.data_ptr<scalar_t>());
  });
  return alpha;
}

// Gradients for (m_cam, o_ell, w_cam, c, w2, b2, inv_smax).
std::vector<at::Tensor> neural_block_backward(const at::Tensor& grad_alpha, const at::Tensor& u,
                                              const at::Tensor& v, const at::Tensor& intrinsics,
                                              const at::Tensor& m_cam, const at::Tensor& o_ell,
                                              const at::Tensor& w_cam, const at::Tensor& c, const at::Tensor& w2,
                                              const at::Tensor& b2, const at::Tensor& inv_smax, double gain) {
  check_neural(u, v, intrinsics, m_cam, o_ell, w_cam, c, w2, b2, inv_smax);
  check_params({u, grad_alpha});
  TORCH_CHECK(grad_alpha.sizes() == u.sizes(), "grad_alpha must be (P, A)");
  std::vector<at::Tensor> out = {at::empty_like(m_cam), at::empty_like(o_ell), at::empty_like(w_cam),
                                 at::empty_like(c),     at::empty_like(w2),    at::empty_like(b2),
                                 at::empty_like(inv_smax)};
  AT_DISPATCH_FLOATING_TYPES(u.scalar_type(), "neural_block_backward", [&] {
    neural_backward_kernel<scalar_t>(
        neural_inputs<scalar_t>(u, v, intrinsics, m_cam, o_ell, w_cam, c, w2, b2, inv_smax, gain),
        grad_alpha.data_ptr<scalar_t>(), out);
  });
  return out;
}

// =============================================================================================
// 3D Gaussian (EWA splat, as 3DGS; kernels.py: gaussian_alpha).

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
      gaussian_alpha_batch(power.data(), e.data(), opacity[p], a1 - a0, alpha + p * A + a0);
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
          const T g_alpha = gaussian_passes(power[j], value) ? g_tile[j] : T(0);
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

// Called from Python as torch.ops.radfield.<name> (core/backends/fused.py wraps them in autograd Functions).
TORCH_LIBRARY(radfield, m) {
  m.def("neural_block_forward", &neural_block_forward);
  m.def("neural_block_backward", &neural_block_backward);
  m.def("gaussian_block_forward", &gaussian_block_forward);
  m.def("gaussian_block_backward", &gaussian_block_backward);
}
