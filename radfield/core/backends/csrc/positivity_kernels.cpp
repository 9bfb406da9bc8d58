// The projection of radfield.core.train.positivity (its readable torch twin: `project_nonnegative`), in
// place on the rows a mask selects: each (W2_p (N,), b2_p) onto the cone ‖W2‖₁ ≤ b2, so that the
// primitive's density σ = W2·cos(…) + b2 ≥ b2 − ‖W2‖₁ ≥ 0 everywhere (positivity.py eq. 1-2):
//
//   W2' = sign(W2) max(|W2| − λ, 0),   b2' = b2 + λ,
//   λ = (Σ_{i≤m} a_i − b2) / (m + 1) for the first m with a_{m+1} ≤ λ < a_m (a = |W2| descending),
//
// rows already in the cone (to rounding) unchanged, rows in the polar cone (no valid m) to zero.
// In torch it is a sort and some fifteen small ops over the selected rows, and two gathers and
// scatters of them, every training step. Threads: OpenMP over rows.

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>

#include "pair_kernels.h"

namespace {

constexpr int64_t kMaxWidth = 64;   // hidden units per primitive the stack buffers hold

template <typename T>
void project_row(T* w2, T& b2, int64_t N) {
  T a[kMaxWidth];
  T l1 = T(0);
  for (int64_t n = 0; n < N; ++n) a[n] = std::abs(w2[n]), l1 += a[n];
  if (l1 <= b2 + T(1e-6) * (std::abs(b2) + T(1))) return;   // inside, to rounding: unchanged
  for (int64_t i = 1; i < N; ++i) {   // insertion sort, descending: N is a handful of units
    const T v = a[i];
    int64_t j = i;
    for (; j > 0 && a[j - 1] < v; --j) a[j] = a[j - 1];
    a[j] = v;
  }
  T cumsum = T(0), lam = T(0);
  bool found = false;
  for (int64_t m = 0; m < N && !found; ++m) {
    cumsum += a[m];
    const T candidate = (cumsum - b2) / T(m + 2);
    const T below = m + 1 < N ? a[m + 1] : T(0);
    if (candidate >= below && candidate < a[m]) lam = candidate, found = true;
  }
  if (!found) {   // the polar cone: no density is left
    std::fill(w2, w2 + N, T(0));
    b2 = T(0);
    return;
  }
  lam = std::max(lam, T(0));
  for (int64_t n = 0; n < N; ++n) {
    const T shrunk = std::max(std::abs(w2[n]) - lam, T(0));
    w2[n] = w2[n] > T(0) ? shrunk : (w2[n] < T(0) ? -shrunk : T(0));
  }
  b2 += lam;
}

void project_nonnegative_(at::Tensor& w2, at::Tensor& b2, const at::Tensor& mask) {
  radfield::check_params({w2, b2});
  const int64_t P = w2.size(0), N = w2.dim() == 2 ? w2.size(1) : 0;
  TORCH_CHECK(w2.dim() == 2 && b2.sizes() == at::IntArrayRef({P}), "w2 must be (P, N) and b2 (P,)");
  TORCH_CHECK(N <= kMaxWidth, "at most ", kMaxWidth, " hidden units, got ", N);
  TORCH_CHECK(mask.scalar_type() == at::kBool && mask.sizes() == at::IntArrayRef({P}) && mask.is_contiguous() &&
                  mask.device().is_cpu(), "mask must be a contiguous (P,) bool CPU tensor");
  AT_DISPATCH_FLOATING_TYPES(w2.scalar_type(), "project_nonnegative_", [&] {
    scalar_t *w = w2.data_ptr<scalar_t>(), *b = b2.data_ptr<scalar_t>();
    const bool* selected = mask.data_ptr<bool>();
    at::parallel_for(0, P, 4096, [&](int64_t p0, int64_t p1) {
      for (int64_t p = p0; p < p1; ++p)
        if (selected[p]) project_row(w + N * p, b[p], N);
    });
  });
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(radfield, m) {
  m.def("project_nonnegative_(Tensor(a!) w2, Tensor(b!) b2, Tensor mask) -> ()", &project_nonnegative_);
}
