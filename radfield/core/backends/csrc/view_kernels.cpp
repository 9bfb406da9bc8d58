// Whole-view rasteriser, forward and backward, as 3DGS does it on a GPU (Kerbl et al. 2023, §6),
// for neural primitives and 3D Gaussians: core/render/rasterize.py's compositing loop (its torch path
// stays the readable reference twin that tests/test_fused.py compares against) without any
// per-pair tensor.
//
// Binning: the image is cut into 16×16 tiles; every tile gets the list of the primitives whose
// pixel bounds touch it, in the caller's `order` (the visible primitives' indices front to back by
// centre depth). Every per-primitive tensor is first gathered into that order (one index_select
// each, in C++), and the lists hold positions in it: a tile then reads the primitives' records in
// increasing address order instead of at random, which the cache prefetchers follow (at 10k
// primitives the neural records alone exceed a core's L2). The gradients are summed per position
// and scattered back to the primitives at the end (zero for the primitives not drawn).
//
// Forward, per tile (OpenMP over tiles): for each primitive of the list, the tile's pixels inside
// its bounds that have not terminated form one batch whose α is evaluated in SIMD
// (pair_kernels.h); then each pixel composites front to back (paper eq. 4) in double:
//   w_i = α_i T_i,  T_{i+1} = T_i (1 − α_i),
// skipping α = 0 (below 1/255, a miss) and stopping at the first pair that would take T below
// t_min (3DGS: that pair is not composited, and the pixel is done). The pixel keeps its final T
// (double) and `last`, the list position after its last composited pair; every list entry keeps
// whether it composited any pixel (`used`).
//
// Backward, per tile: each pixel starts from its final T and walks the list back to front from
// `last`, recovering T_i = T_{i+1} / (1 − α_i) and the suffix
//   S_i = Σ_{j>i} (g_C·c_j + g_D z_j) α_j T_j + g_T T_final,
// so that ∂L/∂α_i = (g_C·c_i + g_D z_i) T_i − S_i / (1 − α_i), ∂L/∂c_i = g_C α_i T_i and
// ∂L/∂z_i = g_D α_i T_i; the pair kernel's backward turns ∂L/∂α_i into the primitive's
// parameter gradients. An entry that composited no pixel (all misses, α below 1/255, or pixels
// already done) has no gradient and is skipped before its pixels are gathered. Each thread sums
// into its own buffer (double), reduced at the end.
//
// Outputs are the raw sums Σ w_i c_i, Σ w_i z_i and T; the background, α = 1 − T and the mean
// depth are formed in torch (core/backends/fused.py), which also differentiates them.

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <omp.h>
#include <torch/library.h>

#include "pair_kernels.h"

namespace {

using namespace radfield;

constexpr int64_t kSide = 16;             // tile side in pixels
constexpr int64_t kPixels = kSide * kSide;

struct Grid {
  int64_t H, W, nx, ny;
  Grid(int64_t height, int64_t width) : H(height), W(width), nx((width + kSide - 1) / kSide), ny((height + kSide - 1) / kSide) {}
  int64_t tiles() const { return nx * ny; }
};

// Tile lists of the V primitives (bounds (V, 4) in depth order): offsets (tiles + 1) into entries,
// the positions of tile t's primitives at [offsets[t], offsets[t+1]). Returns the candidate pairs
// (pixels inside the bounds).
int64_t bin(const int64_t* bounds, int64_t V, const Grid& g, int64_t* offsets, std::vector<int32_t>& entries) {
  std::vector<int64_t> count(g.tiles() + 1, 0);
  int64_t candidates = 0;
  for (int64_t v = 0; v < V; ++v) {
    const int64_t* b = bounds + 4 * v;  // x0, y0, x1, y1 inclusive, inside the image
    candidates += (b[2] - b[0] + 1) * (b[3] - b[1] + 1);
    for (int64_t ty = b[1] / kSide; ty <= b[3] / kSide; ++ty)
      for (int64_t tx = b[0] / kSide; tx <= b[2] / kSide; ++tx) ++count[ty * g.nx + tx + 1];
  }
  offsets[0] = 0;
  for (int64_t t = 0; t < g.tiles(); ++t) offsets[t + 1] = offsets[t] + count[t + 1];
  entries.resize(offsets[g.tiles()]);
  std::vector<int64_t> fill(offsets, offsets + g.tiles());
  for (int64_t v = 0; v < V; ++v) {
    const int64_t* b = bounds + 4 * v;
    for (int64_t ty = b[1] / kSide; ty <= b[3] / kSide; ++ty)
      for (int64_t tx = b[0] / kSide; tx <= b[2] / kSide; ++tx) entries[fill[ty * g.nx + tx]++] = int32_t(v);
  }
  return candidates;
}

// The pixels of tile (tx, ty) and a batch of them for one primitive.
template <typename T>
struct TileBatch {
  int64_t x0, y0, w, h;       // the tile's first pixel and size (clipped at the image border)
  int64_t m = 0;              // pixels in the batch
  std::array<T, kPixels> u, v;
  std::array<int32_t, kPixels> local;  // (y − y0) · kSide + (x − x0)

  TileBatch(const Grid& g, int64_t t)
      : x0((t % g.nx) * kSide), y0((t / g.nx) * kSide), w(std::min(kSide, g.W - x0)), h(std::min(kSide, g.H - y0)) {}

  // the tile's pixels inside bounds b for which keep(local index) holds
  template <typename Keep>
  void gather(const int64_t* b, Keep&& keep) {
    m = 0;
    const int64_t xa = std::max(b[0], x0), xb = std::min(b[2], x0 + w - 1);
    const int64_t ya = std::max(b[1], y0), yb = std::min(b[3], y0 + h - 1);
    for (int64_t y = ya; y <= yb; ++y)
      for (int64_t x = xa; x <= xb; ++x) {
        const int32_t i = int32_t((y - y0) * kSide + (x - x0));
        if (!keep(i)) continue;
        u[m] = T(x) + T(0.5);  // pixel centres, as rasterize.py
        v[m] = T(y) + T(0.5);
        local[m++] = i;
      }
  }
};

// --- the two primitive kinds: α of a batch, and its backward ---------------------------------

template <typename T, int kUnits = 0>  // kUnits: ChordTile's compile-time hidden units (0: run time)
struct NeuralKind {
  NeuralTensors<T> prm;
  Intrinsics<T> k;
  ChordTile<T, kUnits> tile;
  std::array<T, kPixels> dx, dy, dz, near;  // the current tile's pixel directions and near planes
  static int64_t stride(int64_t units) { return neural_grad_stride(units); }

  NeuralKind(const NeuralTensors<T>& params, const Intrinsics<T>& intrinsics, bool backward)
      : prm(params), k(intrinsics), tile(params.N, kPixels, backward) {}

  // directions depend on the pixel only: once per tile, not once per pair
  void begin_tile(const TileBatch<T>& b) {
    std::array<T, kPixels> u, v;
    for (int64_t y = 0; y < kSide; ++y)
      for (int64_t x = 0; x < kSide; ++x) u[y * kSide + x] = T(b.x0 + x) + T(0.5), v[y * kSide + x] = T(b.y0 + y) + T(0.5);
    ChordTile<T, kUnits>::directions(u.data(), v.data(), kPixels, k, dx.data(), dy.data(), dz.data(), near.data());
  }

  void load(const TileBatch<T>& b) {
    for (int64_t j = 0; j < b.m; ++j) {
      const int32_t i = b.local[j];
      tile.d0[j] = dx[i], tile.d1[j] = dy[i], tile.d2[j] = dz[i], tile.l_near[j] = near[i];
    }
  }

  void alpha(int64_t p, const TileBatch<T>& b, T* out) {
    const NeuralParams<T> q = prm.primitive(p);
    std::fill(out, out + b.m, T(0));
    load(b);
    tile.intersect(b.m, q, nullptr, /*backward=*/false);
    tile.optical_depth(q, /*backward=*/false);
    for (int64_t j = 0; j < tile.n; ++j) out[tile.pixel[j]] = alpha_from_expm1(tile.expm1_neg[j]);  // eq. 9
  }

  // grad_of(j, α) composites batch pixel j and returns ∂L/∂α; sums go to acc (this primitive's slot)
  template <typename GradOf>
  void backward(int64_t p, const TileBatch<T>& b, GradOf&& grad_of, double* acc) {
    const NeuralParams<T> q = prm.primitive(p);
    load(b);
    tile.intersect(b.m, q, nullptr, /*backward=*/true);
    tile.optical_depth(q, /*backward=*/true);
    bool any = false;
    for (int64_t j = 0; j < tile.n; ++j) {
      const T a = alpha_from_expm1(tile.expm1_neg[j]);
      const T g = a != T(0) ? grad_of(tile.pixel[j], a) : T(0);
      tile.g_I[j] = g * alpha_slope_from_expm1(tile.expm1_neg[j]);
      any = any || tile.g_I[j] != T(0);
    }
    if (!any) return;
    const NeuralGradRefs refs = neural_grad_refs(acc, prm.N);
    tile.optical_depth_backward(q, refs);
    tile.chords_backward(q, refs);
  }
};

template <typename T>
struct GaussianKind {
  const T *mean2d, *conic, *opacity;
  std::array<T, kPixels> power, e;
  static int64_t stride(int64_t) { return 6; }  // mean2d (2), conic (3), opacity

  GaussianKind(const T* mean2d_, const T* conic_, const T* opacity_) : mean2d(mean2d_), conic(conic_), opacity(opacity_) {}

  // power and e = exp(min(power, 0)) of the batch (kernels.py: gaussian_alpha)
  void splat(int64_t p, const T* u, const T* v, int64_t m) {
    const T mx = mean2d[2 * p], my = mean2d[2 * p + 1];
#pragma omp simd
    for (int64_t j = 0; j < m; ++j) {
      power[j] = gaussian_power(u[j] - mx, v[j] - my, conic + 3 * p);
      e[j] = std::min(power[j], T(0));
    }
    simd_exp(e.data(), e.data(), m);
  }

  void begin_tile(const TileBatch<T>&) {}

  void alpha(int64_t p, const TileBatch<T>& b, T* out) {
    const int64_t m = b.m;
    splat(p, b.u.data(), b.v.data(), m);
    gaussian_alpha_batch(power.data(), e.data(), opacity[p], m, out);
  }

  template <typename GradOf>
  void backward(int64_t p, const TileBatch<T>& b, GradOf&& grad_of, double* acc) {
    const int64_t m = b.m;
    const T *u = b.u.data(), *v = b.v.data();
    splat(p, u, v, m);
    const T* q = conic + 3 * p;
    const T mx = mean2d[2 * p], my = mean2d[2 * p + 1];
    double s[6] = {0, 0, 0, 0, 0, 0};   // this entry's sums, added to acc once
    for (int64_t j = 0; j < m; ++j) {
      const T value = opacity[p] * e[j];
      const T a = gaussian_alpha(power[j], std::min(T(kAlphaMax), value));
      if (a == T(0)) continue;
      const T g_alpha = grad_of(j, a);
      if (!gaussian_passes(power[j], value)) continue;  // clamped at 0.99: no gradient
      const T dx = u[j] - mx, dy = v[j] - my;
      const T g_power = g_alpha * value;  // (exp)' = exp; clamp_max(power, 0) passes at power ≤ 0
      s[0] -= double(g_power * (-q[0] * dx - q[1] * dy));  // ∂dx/∂mean_x = −1
      s[1] -= double(g_power * (-q[2] * dy - q[1] * dx));
      s[2] += double(T(-0.5) * g_power * dx * dx);
      s[3] += double(-g_power * dx * dy);
      s[4] += double(T(-0.5) * g_power * dy * dy);
      s[5] += double(g_alpha * e[j]);
    }
    for (int k = 0; k < 6; ++k) acc[k] += s[k];
  }
};

// --- forward and backward over the tiles ------------------------------------------------------

template <typename T>
struct View {  // the drawn primitives, in depth order
  Grid grid;
  int64_t P;
  const int64_t* bounds;  // (P, 4)
  const T* colors;        // (P, 3)
  const T* depth;         // (P,)
};

struct ForwardOut {
  void* acc_color;          // (H, W, 3) T
  void* acc_depth;          // (H, W) T
  void* trans;              // (H, W) T
  double* trans64;          // (H, W)
  int32_t* last;            // (H, W)
  uint8_t* used;            // (entries,) zero-initialised
  int64_t counters[4] = {0, 0, 0, 0};  // evaluated pairs, composited pairs, terminated pixels, candidate pairs
};

template <typename T, typename MakeKind>
void view_forward(const View<T>& view, const int64_t* offsets, const int32_t* entries, double t_min,
                  MakeKind&& make_kind, ForwardOut& out) {
  const Grid& g = view.grid;
  T* acc_color = static_cast<T*>(out.acc_color);
  T* acc_depth = static_cast<T*>(out.acc_depth);
  T* trans = static_cast<T*>(out.trans);
  int64_t pairs = 0, composited = 0, terminated = 0;
#pragma omp parallel num_threads(at::get_num_threads()) reduction(+ : pairs, composited, terminated)
  {
    auto kind = make_kind(/*backward=*/false);
    std::array<T, kPixels> alpha;
    std::array<double, kPixels> tr, color_r, color_g, color_b, z;
    std::array<int32_t, kPixels> last;
    std::array<bool, kPixels> done;
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < g.tiles(); ++t) {
      TileBatch<T> batch(g, t);
      kind.begin_tile(batch);
      tr.fill(1.0);
      color_r.fill(0.0), color_g.fill(0.0), color_b.fill(0.0), z.fill(0.0);
      last.fill(0);
      done.fill(false);
      int64_t alive = batch.w * batch.h;
      for (int64_t li = offsets[t]; li < offsets[t + 1] && alive > 0; ++li) {
        const int64_t p = entries[li];
        batch.gather(view.bounds + 4 * p, [&](int32_t i) { return !done[i]; });
        if (batch.m == 0) continue;
        pairs += batch.m;
        kind.alpha(p, batch, alpha.data());
        const double cr = view.colors[3 * p], cg = view.colors[3 * p + 1], cb = view.colors[3 * p + 2];
        const double zp = view.depth[p];
        bool any = false;
        for (int64_t j = 0; j < batch.m; ++j) {
          const double a = alpha[j];
          if (a == 0.0) continue;  // below 1/255, or a miss
          const int32_t i = batch.local[j];
          const double next = tr[i] * (1.0 - a);
          if (next < t_min) {  // early termination: this pair is not composited
            done[i] = true;
            --alive;
            ++terminated;
            continue;
          }
          const double w = a * tr[i];
          color_r[i] += w * cr, color_g[i] += w * cg, color_b[i] += w * cb;
          z[i] += w * zp;
          tr[i] = next;
          last[i] = int32_t(li - offsets[t] + 1);
          ++composited;
          any = true;
        }
        out.used[li] = uint8_t(any);
      }
      for (int64_t y = 0; y < batch.h; ++y)
        for (int64_t x = 0; x < batch.w; ++x) {
          const int64_t i = y * kSide + x, pix = (batch.y0 + y) * g.W + batch.x0 + x;
          acc_color[3 * pix] = T(color_r[i]), acc_color[3 * pix + 1] = T(color_g[i]), acc_color[3 * pix + 2] = T(color_b[i]);
          acc_depth[pix] = T(z[i]);
          trans[pix] = T(tr[i]);
          out.trans64[pix] = tr[i];
          out.last[pix] = last[i];
        }
    }
  }
  out.counters[0] = pairs, out.counters[1] = composited, out.counters[2] = terminated;
}

// Per-thread double sums of the gradients of the per-primitive inputs: thread th's sums of
// primitive v are at sums[(th · P + v) · width], valid where touched[th · P + v] (a slot is zeroed
// when its thread first reaches the primitive, so untouched slots are never written nor read).
struct GradSums {
  int threads;
  int64_t P, width;
  double* sums;
  std::vector<uint8_t> touched;
};

// The buffer behind GradSums, kept by the calling thread from one backward to the next: at 10k
// neural primitives it is 5 MB a thread, which as a fresh allocation every view cost more in page
// faults and zeroing than the tiles' own work at 64×64.
inline double* grad_buffer(size_t doubles) {
  static thread_local std::vector<double> buffer;
  if (buffer.size() < doubles) buffer.resize(doubles);
  return buffer.data();
}

// Gradients of the per-primitive inputs: colors (P, 3), depth (P,), and the kind's parameters
// (stride doubles per primitive, in the layout of Kind::backward's acc), as per-thread double sums.
template <typename T, typename MakeKind>
GradSums view_backward(const View<T>& view, const int64_t* offsets, const int32_t* entries, const uint8_t* used,
                       const T* g_color, const T* g_depth, const T* g_trans, const double* trans64,
                       const int32_t* last_in, int64_t stride, MakeKind&& make_kind) {
  const Grid& g = view.grid;
  const int64_t width = stride + 4;  // + colour (3) + depth
  const int threads = at::get_num_threads();
  GradSums out{threads, view.P, width, grad_buffer(size_t(threads) * view.P * width),
               std::vector<uint8_t>(size_t(threads) * view.P, 0)};
#pragma omp parallel num_threads(threads)
  {
    auto kind = make_kind(/*backward=*/true);
    const int th = omp_get_thread_num();
    double* mine = out.sums + size_t(th) * view.P * width;
    uint8_t* touched = out.touched.data() + size_t(th) * view.P;
    std::array<double, kPixels> tr, suffix, gr, gg, gb, gz;
    std::array<int32_t, kPixels> last;
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < g.tiles(); ++t) {
      TileBatch<T> batch(g, t);
      kind.begin_tile(batch);
      int32_t longest = 0;
      last.fill(0);
      for (int64_t y = 0; y < batch.h; ++y)
        for (int64_t x = 0; x < batch.w; ++x) {
          const int64_t i = y * kSide + x, pix = (batch.y0 + y) * g.W + batch.x0 + x;
          tr[i] = trans64[pix];
          suffix[i] = double(g_trans[pix]) * trans64[pix];
          gr[i] = g_color[3 * pix], gg[i] = g_color[3 * pix + 1], gb[i] = g_color[3 * pix + 2];
          gz[i] = g_depth[pix];
          last[i] = last_in[pix];
          longest = std::max(longest, last[i]);
        }
      for (int64_t pos = longest - 1; pos >= 0; --pos) {  // back to front
        if (!used[offsets[t] + pos]) continue;
        const int64_t p = entries[offsets[t] + pos];
        batch.gather(view.bounds + 4 * p, [&](int32_t i) { return pos < last[i]; });
        if (batch.m == 0) continue;
        const double cr = view.colors[3 * p], cg = view.colors[3 * p + 1], cb = view.colors[3 * p + 2];
        const double zp = view.depth[p];
        double* acc = mine + p * width;
        if (!touched[p]) std::fill(acc, acc + width, 0.0), touched[p] = 1;
        // this entry's colour and depth sums, in locals (registers) rather than through acc
        double s_r = 0, s_g = 0, s_b = 0, s_z = 0;
        auto grad_of = [&](int64_t j, T alpha) -> T {
          const int32_t i = batch.local[j];
          const double a = alpha, keep = 1.0 - a;
          const double before = tr[i] / keep;  // T_i
          const double wgt = gr[i] * cr + gg[i] * cg + gb[i] * cb + gz[i] * zp;
          const double g_alpha = wgt * before - suffix[i] / keep;
          const double w = a * before;
          suffix[i] += wgt * w;
          tr[i] = before;
          s_r += gr[i] * w, s_g += gg[i] * w, s_b += gb[i] * w, s_z += gz[i] * w;
          return T(g_alpha);
        };
        kind.backward(p, batch, grad_of, acc);
        double* acc_view = acc + stride;  // colour, depth
        acc_view[0] += s_r, acc_view[1] += s_g, acc_view[2] += s_b, acc_view[3] += s_z;
      }
    }
  }
  return out;
}

// Copy the double sums of the V drawn primitives (in depth order) into gradient tensors for all P
// primitives shaped as `like` (V rows), row order[v] from sums row v, zero elsewhere: colors,
// depth, then the kind's fields, whose per-primitive sizes add up to stride.
template <typename T>
std::vector<at::Tensor> unpack_grads(const GradSums& grad, const at::Tensor& order, int64_t stride,
                                     const std::vector<at::Tensor>& like, int64_t P) {
  const int64_t V = order.numel();
  const int64_t* ids = order.data_ptr<int64_t>();
  std::vector<at::Tensor> out;
  std::vector<T*> dst;
  std::vector<int64_t> size;
  for (const at::Tensor& t : like) {
    std::vector<int64_t> sizes = t.sizes().vec();
    sizes[0] = P;
    // V == P: every row is written (order holds each primitive once)
    out.push_back(V == P ? at::empty(sizes, t.options()) : at::zeros(sizes, t.options()));
    dst.push_back(out.back().data_ptr<T>());
    int64_t row = 1;
    for (size_t d = 1; d < sizes.size(); ++d) row *= sizes[d];
    size.push_back(row);
  }
  const int64_t width = stride + 4;
  const std::vector<double> zeros(width, 0.0);
  at::parallel_for(0, V, 1024, [&](int64_t v0, int64_t v1) {
    std::vector<double> total(width);
    for (int64_t v = v0; v < v1; ++v) {
      const int64_t p = ids[v];
      const double* s = zeros.data();
      if (grad.threads == 1) {
        if (grad.touched[v]) s = grad.sums + v * width;
      } else {
        std::fill(total.begin(), total.end(), 0.0);   // the threads' sums, in thread order
        for (int th = 0; th < grad.threads; ++th) {
          if (!grad.touched[size_t(th) * V + v]) continue;
          const double* theirs = grad.sums + (size_t(th) * V + v) * width;
          for (int64_t e = 0; e < width; ++e) total[e] += theirs[e];
        }
        s = total.data();
      }
      T* gc = dst[0] + 3 * p;
      gc[0] = T(s[stride]), gc[1] = T(s[stride + 1]), gc[2] = T(s[stride + 2]);
      dst[1][p] = T(s[stride + 3]);
      for (size_t f = 2; f < like.size(); ++f) {
        T* d = dst[f] + size[f] * p;
        for (int64_t e = 0; e < size[f]; ++e) d[e] = T(s[e]);
        s += size[f];
      }
    }
  });
  return out;
}

// --- checks and entry points ------------------------------------------------------------------

void check_view(const at::Tensor& bounds, const at::Tensor& colors, const at::Tensor& depth, int64_t height,
                int64_t width) {
  const int64_t P = bounds.size(0);
  TORCH_CHECK(bounds.scalar_type() == at::kLong && bounds.is_contiguous() && bounds.dim() == 2 && bounds.size(1) == 4,
              "bounds must be contiguous int64 (P, 4)");
  TORCH_CHECK(colors.sizes() == at::IntArrayRef({P, 3}) && depth.sizes() == at::IntArrayRef({P}),
              "colors must be (P, 3) and depth (P,)");
  TORCH_CHECK(height > 0 && width > 0, "the view needs pixels");
}

// the drawn primitives: valid, distinct indices whose bounds are non-empty and inside the image
void check_order(const at::Tensor& order, const at::Tensor& bounds, int64_t height, int64_t width) {
  const int64_t P = bounds.size(0);
  TORCH_CHECK(order.scalar_type() == at::kLong && order.is_contiguous() && order.dim() == 1, "order must be int64 (V,)");
  const int64_t* b = bounds.data_ptr<int64_t>();
  const int64_t* o = order.data_ptr<int64_t>();
  std::vector<uint8_t> seen(P, 0);
  for (int64_t v = 0; v < order.numel(); ++v) {
    const int64_t p = o[v];
    TORCH_CHECK(0 <= p && p < P, "order holds a primitive index out of range");
    TORCH_CHECK(!seen[p], "order holds a primitive twice");
    seen[p] = 1;
    TORCH_CHECK(0 <= b[4 * p] && b[4 * p] <= b[4 * p + 2] && b[4 * p + 2] < width && 0 <= b[4 * p + 1] &&
                    b[4 * p + 1] <= b[4 * p + 3] && b[4 * p + 3] < height,
                "bounds must be non-empty and inside the image");
  }
}

// Rows order[v] of a contiguous (P, ...) tensor of 4- or 8-byte elements, copied as bits: a
// loop per row (index_select pays a memcpy call per row of a few bytes).
// kRow > 0: the row length fixed at compile time (the short rows of the view's tensors).
template <typename Bits, int kRow>
void copy_rows(const at::Tensor& from, at::Tensor& to, const int64_t* ids, int64_t V, int64_t row) {
  const Bits* src = static_cast<const Bits*>(from.data_ptr());
  Bits* dst = static_cast<Bits*>(to.data_ptr());
  const int64_t n = kRow > 0 ? kRow : row;
  at::parallel_for(0, V, 4096, [&](int64_t v0, int64_t v1) {
    for (int64_t v = v0; v < v1; ++v) {
      const Bits* r = src + ids[v] * n;
      for (int64_t e = 0; e < n; ++e) dst[v * n + e] = r[e];
    }
  });
}

template <typename Bits>
void copy_rows(const at::Tensor& from, at::Tensor& to, const int64_t* ids, int64_t V, int64_t row) {
  switch (row) {
    case 1: return copy_rows<Bits, 1>(from, to, ids, V, row);
    case 2: return copy_rows<Bits, 2>(from, to, ids, V, row);
    case 3: return copy_rows<Bits, 3>(from, to, ids, V, row);
    case 4: return copy_rows<Bits, 4>(from, to, ids, V, row);
    case 8: return copy_rows<Bits, 8>(from, to, ids, V, row);
    case 9: return copy_rows<Bits, 9>(from, to, ids, V, row);
    case 24: return copy_rows<Bits, 24>(from, to, ids, V, row);
    default: return copy_rows<Bits, 0>(from, to, ids, V, row);
  }
}

// The per-primitive tensors (P, ...) gathered into depth order (V, ...): what the tiles read.
std::vector<at::Tensor> in_order(const std::vector<at::Tensor>& tensors, const at::Tensor& order) {
  const int64_t V = order.numel();
  const int64_t* ids = order.data_ptr<int64_t>();
  std::vector<at::Tensor> out;
  for (const at::Tensor& t : tensors) {
    std::vector<int64_t> sizes = t.sizes().vec();
    const int64_t row = sizes[0] > 0 ? t.numel() / sizes[0] : 0;
    sizes[0] = V;
    at::Tensor rows = at::empty(sizes, t.options());
    TORCH_CHECK(t.is_contiguous() && (t.element_size() == 4 || t.element_size() == 8), "in_order: contiguous 4- or 8-byte tensors");
    if (t.element_size() == 4) copy_rows<uint32_t>(t, rows, ids, V, row);
    else copy_rows<uint64_t>(t, rows, ids, V, row);
    out.push_back(rows);
  }
  return out;
}

// Runs the forward on the gathered tensors (bounds (V, 4) first); returns acc_color, acc_depth, T,
// T (float64), last, offsets, entries, used, counters (the caller appends the gathered tensors,
// which the backward takes instead of gathering again).
template <typename Run>
std::vector<at::Tensor> forward_outputs(const at::Tensor& colors, const at::Tensor& bounds, int64_t height,
                                        int64_t width, Run&& run) {
  const Grid g(height, width);
  at::Tensor offsets = at::empty({g.tiles() + 1}, bounds.options());
  std::vector<int32_t> list;
  const int64_t candidates = bin(bounds.data_ptr<int64_t>(), bounds.size(0), g, offsets.data_ptr<int64_t>(), list);
  at::Tensor entries = at::empty({int64_t(list.size())}, bounds.options().dtype(at::kInt));
  std::copy(list.begin(), list.end(), entries.data_ptr<int32_t>());
  at::Tensor acc_color = at::empty({height, width, 3}, colors.options());
  at::Tensor acc_depth = at::empty({height, width}, colors.options());
  at::Tensor trans = at::empty({height, width}, colors.options());
  at::Tensor trans64 = at::empty({height, width}, colors.options().dtype(at::kDouble));
  at::Tensor last = at::empty({height, width}, colors.options().dtype(at::kInt));
  at::Tensor used = at::zeros({entries.numel()}, colors.options().dtype(at::kByte));
  ForwardOut out;
  out.acc_color = acc_color.data_ptr(), out.acc_depth = acc_depth.data_ptr(), out.trans = trans.data_ptr();
  out.trans64 = trans64.data_ptr<double>(), out.last = last.data_ptr<int32_t>(), out.used = used.data_ptr<uint8_t>();
  run(g, offsets.data_ptr<int64_t>(), entries.data_ptr<int32_t>(), out);
  out.counters[3] = candidates;
  at::Tensor counters = at::empty({4}, bounds.options());
  std::copy(out.counters, out.counters + 4, counters.data_ptr<int64_t>());
  return {acc_color, acc_depth, trans, trans64, last, offsets, entries, used, counters};
}

void check_backward(const at::Tensor& g_color, const at::Tensor& g_depth, const at::Tensor& g_trans,
                    const at::Tensor& trans64, const at::Tensor& last, const at::Tensor& offsets,
                    const at::Tensor& entries, const at::Tensor& used, const at::Tensor& order, int64_t height,
                    int64_t width) {
  check_params({g_color, g_depth, g_trans});
  TORCH_CHECK(g_color.sizes() == at::IntArrayRef({height, width, 3}) && g_depth.sizes() == at::IntArrayRef({height, width}) &&
                  g_trans.sizes() == at::IntArrayRef({height, width}),
              "gradients must match the view's outputs");
  TORCH_CHECK(trans64.scalar_type() == at::kDouble && last.scalar_type() == at::kInt && offsets.scalar_type() == at::kLong &&
                  entries.scalar_type() == at::kInt && order.scalar_type() == at::kLong,
              "saved forward state has the wrong dtypes");
  TORCH_CHECK(trans64.is_contiguous() && last.is_contiguous() && offsets.is_contiguous() && entries.is_contiguous() &&
                  order.is_contiguous(),
              "saved forward state must be contiguous");
  TORCH_CHECK(offsets.numel() == Grid(height, width).tiles() + 1, "offsets do not match the view");
  TORCH_CHECK(used.scalar_type() == at::kByte && used.is_contiguous() && used.numel() == entries.numel(),
              "used must be uint8 (entries,)");
  TORCH_CHECK(order.dim() == 1, "order must be (V,)");
}

std::vector<at::Tensor> neural_view_forward(const at::Tensor& bounds, const at::Tensor& order, const at::Tensor& intrinsics,
                                            const at::Tensor& colors, const at::Tensor& depth,
                                            const at::Tensor& m_cam, const at::Tensor& o_ell, const at::Tensor& w_cam,
                                            const at::Tensor& c, const at::Tensor& w2, const at::Tensor& b2,
                                            const at::Tensor& inv_smax, int64_t height, int64_t width, double t_min,
                                            double gain) {
  check_params({colors, depth, intrinsics, m_cam, o_ell, w_cam, c, w2, b2, inv_smax});
  check_view(bounds, colors, depth, height, width);
  check_order(order, bounds, height, width);
  const std::vector<at::Tensor> v = in_order({bounds, colors, depth, m_cam, o_ell, w_cam, c, w2, b2, inv_smax}, order);
  std::vector<at::Tensor> result;
  AT_DISPATCH_FLOATING_TYPES(colors.scalar_type(), "neural_view_forward", [&] {
    using T = scalar_t;
    const NeuralTensors<T> prm = neural_tensors<T>(v[3], v[4], v[5], v[6], v[7], v[8], v[9], gain);
    const Intrinsics<T> k = read_intrinsics<T>(intrinsics);
    result = forward_outputs(colors, v[0], height, width, [&](const Grid& g, const int64_t* off, const int32_t* ent, ForwardOut& out) {
      const View<T> view{g, v[0].size(0), v[0].data_ptr<int64_t>(), v[1].data_ptr<T>(), v[2].data_ptr<T>()};
      if (prm.N == 8)   // the default width, unrolled
        view_forward<T>(view, off, ent, t_min, [&](bool backward) { return NeuralKind<T, 8>(prm, k, backward); }, out);
      else
        view_forward<T>(view, off, ent, t_min, [&](bool backward) { return NeuralKind<T>(prm, k, backward); }, out);
    });
  });
  result.insert(result.end(), v.begin(), v.end());
  return result;
}

// Gradients for (colors, depth, m_cam, o_ell, w_cam, c, w2, b2, inv_smax) of all `count` primitives,
// from the forward's tensors in depth order (bounds … inv_smax: its gathered outputs).
std::vector<at::Tensor> neural_view_backward(const at::Tensor& g_color, const at::Tensor& g_depth,
                                             const at::Tensor& g_trans, const at::Tensor& bounds,
                                             const at::Tensor& intrinsics, const at::Tensor& colors,
                                             const at::Tensor& depth, const at::Tensor& m_cam, const at::Tensor& o_ell,
                                             const at::Tensor& w_cam, const at::Tensor& c, const at::Tensor& w2,
                                             const at::Tensor& b2, const at::Tensor& inv_smax,
                                             const at::Tensor& trans64, const at::Tensor& last,
                                             const at::Tensor& offsets, const at::Tensor& entries,
                                             const at::Tensor& used, const at::Tensor& order, int64_t count,
                                             double gain) {
  const int64_t height = trans64.size(0), width = trans64.size(1);
  check_params({colors, depth, intrinsics, m_cam, o_ell, w_cam, c, w2, b2, inv_smax, g_color});
  check_view(bounds, colors, depth, height, width);
  check_backward(g_color, g_depth, g_trans, trans64, last, offsets, entries, used, order, height, width);
  const std::vector<at::Tensor> v = {bounds, colors, depth, m_cam, o_ell, w_cam, c, w2, b2, inv_smax};
  std::vector<at::Tensor> grads;
  AT_DISPATCH_FLOATING_TYPES(colors.scalar_type(), "neural_view_backward", [&] {
    using T = scalar_t;
    const NeuralTensors<T> prm = neural_tensors<T>(v[3], v[4], v[5], v[6], v[7], v[8], v[9], gain);
    const Intrinsics<T> k = read_intrinsics<T>(intrinsics);
    const View<T> view{Grid(height, width), v[0].size(0), v[0].data_ptr<int64_t>(), v[1].data_ptr<T>(),
                       v[2].data_ptr<T>()};
    const int64_t stride = NeuralKind<T>::stride(prm.N);
    const auto run = [&](auto make_kind) {
      return view_backward<T>(view, offsets.data_ptr<int64_t>(), entries.data_ptr<int32_t>(), used.data_ptr<uint8_t>(),
                              g_color.data_ptr<T>(),
                              g_depth.data_ptr<T>(), g_trans.data_ptr<T>(), trans64.data_ptr<double>(),
                              last.data_ptr<int32_t>(), stride, make_kind);
    };
    const GradSums sums = prm.N == 8   // the default width, unrolled
        ? run([&](bool backward) { return NeuralKind<T, 8>(prm, k, backward); })
        : run([&](bool backward) { return NeuralKind<T>(prm, k, backward); });
    grads = unpack_grads<T>(sums, order, stride, {colors, depth, m_cam, o_ell, w_cam, c, w2, b2, inv_smax}, count);
  });
  return grads;
}

std::vector<at::Tensor> gaussian_view_forward(const at::Tensor& bounds, const at::Tensor& order, const at::Tensor& colors,
                                              const at::Tensor& depth, const at::Tensor& mean2d,
                                              const at::Tensor& conic, const at::Tensor& opacity, int64_t height,
                                              int64_t width, double t_min) {
  check_params({colors, depth, mean2d, conic, opacity});
  check_view(bounds, colors, depth, height, width);
  const int64_t P = bounds.size(0);
  TORCH_CHECK(mean2d.sizes() == at::IntArrayRef({P, 2}) && conic.sizes() == at::IntArrayRef({P, 3}) &&
                  opacity.sizes() == at::IntArrayRef({P}),
              "mean2d, conic, opacity must be (P, 2), (P, 3), (P,)");
  check_order(order, bounds, height, width);
  const std::vector<at::Tensor> v = in_order({bounds, colors, depth, mean2d, conic, opacity}, order);
  std::vector<at::Tensor> result;
  AT_DISPATCH_FLOATING_TYPES(colors.scalar_type(), "gaussian_view_forward", [&] {
    using T = scalar_t;
    result = forward_outputs(colors, v[0], height, width, [&](const Grid& g, const int64_t* off, const int32_t* ent, ForwardOut& out) {
      const View<T> view{g, v[0].size(0), v[0].data_ptr<int64_t>(), v[1].data_ptr<T>(), v[2].data_ptr<T>()};
      view_forward<T>(view, off, ent, t_min, [&](bool) {
        return GaussianKind<T>(v[3].data_ptr<T>(), v[4].data_ptr<T>(), v[5].data_ptr<T>());
      }, out);
    });
  });
  result.insert(result.end(), v.begin(), v.end());
  return result;
}

// Gradients for (colors, depth, mean2d, conic, opacity) of all `count` primitives, from the
// forward's tensors in depth order (bounds … opacity: its gathered outputs).
std::vector<at::Tensor> gaussian_view_backward(const at::Tensor& g_color, const at::Tensor& g_depth,
                                               const at::Tensor& g_trans, const at::Tensor& bounds,
                                               const at::Tensor& colors, const at::Tensor& depth,
                                               const at::Tensor& mean2d, const at::Tensor& conic,
                                               const at::Tensor& opacity, const at::Tensor& trans64,
                                               const at::Tensor& last, const at::Tensor& offsets,
                                               const at::Tensor& entries, const at::Tensor& used,
                                               const at::Tensor& order, int64_t count) {
  const int64_t height = trans64.size(0), width = trans64.size(1);
  check_params({colors, depth, mean2d, conic, opacity, g_color});
  check_view(bounds, colors, depth, height, width);
  check_backward(g_color, g_depth, g_trans, trans64, last, offsets, entries, used, order, height, width);
  const std::vector<at::Tensor> v = {bounds, colors, depth, mean2d, conic, opacity};
  std::vector<at::Tensor> grads;
  AT_DISPATCH_FLOATING_TYPES(colors.scalar_type(), "gaussian_view_backward", [&] {
    using T = scalar_t;
    const View<T> view{Grid(height, width), v[0].size(0), v[0].data_ptr<int64_t>(), v[1].data_ptr<T>(),
                       v[2].data_ptr<T>()};
    const int64_t stride = GaussianKind<T>::stride(0);
    const GradSums sums = view_backward<T>(
        view, offsets.data_ptr<int64_t>(), entries.data_ptr<int32_t>(), used.data_ptr<uint8_t>(), g_color.data_ptr<T>(),
        g_depth.data_ptr<T>(), g_trans.data_ptr<T>(), trans64.data_ptr<double>(), last.data_ptr<int32_t>(), stride, [&](bool) {
          return GaussianKind<T>(v[3].data_ptr<T>(), v[4].data_ptr<T>(), v[5].data_ptr<T>());
        });
    grads = unpack_grads<T>(sums, order, stride, {colors, depth, mean2d, conic, opacity}, count);
  });
  return grads;
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(radfield, m) {
  m.def("neural_view_forward", &neural_view_forward);
  m.def("neural_view_backward", &neural_view_backward);
  m.def("gaussian_view_forward", &gaussian_view_forward);
  m.def("gaussian_view_backward", &gaussian_view_backward);
}
