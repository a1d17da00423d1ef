// Native OpenMP CPU rasteriser for splatk (the ``cpu`` backend): the kernels, torch-free,
// included by raster_kernels.cpp (float32) and raster_kernels_f64.cpp (float64). The steps are
// in raster_binning.h (1-3), raster_forward.h (4) and raster_backward.h; here the entry points.
//
// Semantics are those of ``splatk/backends/torch_ref.py`` (the specification): normalised
// conics with support r2 < 1, alpha = min(0.999, o * profile(r2)), pairs with alpha < 1/255
// skipped, front-to-back compositing in stable depth order, a pixel ends before the primitive
// whose T * (1 - alpha) would fall below 1e-4, pixel centres at +0.5.
//
// Forward
//   1. preprocess (parallel over primitives): the reference's support bbox, shrunk to where
//      o * profile can still reach 1/255 (invisible primitives are dropped), tile hits.
//   2. stable LSD radix sort of the visible primitives by depth -> rank; per-rank records
//      (bbox, geometry, params, colours: one cache line for float RGB) that tiles prefetch.
//   3. binning: an exact ellipse-vs-tile test, counting sort into 16x16 tiles (per-chunk
//      counts, so every tile list stays in rank = depth order), plus each entry's rank-major
//      gradient slot for the deterministic gradient reduction.
//   4. rasterisation, parallel over tiles (dynamic schedule, heaviest tiles first): entries
//      outer, tile rows inner, one 16-lane vector per tile row; T is kept in float64 so the
//      1e-4 stop agrees with the reference's float64 log-space transmittance.
//   Saved for backward: final T per pixel, number of entries processed up to the last blended
//   one per pixel ("last"), tile ranges, entry lists, packed records, rank order.
// Backward (3DGS style, back to front per pixel): T_i recovered by dividing by (1 - alpha),
//   W = sum over the blended primitives behind of (dL/dC . c_j) alpha_j T_j kept per pixel,
//   dL/dalpha_i = T_i (dL/dC . c_i) + (T_final (dL/dA - dL/dC . bg) - W) / (1 - alpha_i).
//   Per-entry gradients go to one slot per (primitive, tile) entry, then a deterministic
//   per-primitive sum (no atomics, bitwise reproducible for any thread count).
// Built with -ffp-contract=off: r2 = a dx^2 + 2 b dx dy + c dy^2 rounds op by op like the
// reference's, so support and 1/255 decisions match it bit for bit (and the forward and backward
// passes agree on them by construction); explicit fmadd() only where values accumulate.
#pragma once

#include "raster_backward.h"
#include "raster_binning.h"
#include "raster_common.h"
#include "raster_forward.h"

namespace splatk {
namespace {

// ---------------------------------------------------------------------------------------------
int variant_of(int kind, int k) {
  switch (kind) {
    case kGaussian: return vGauss;
    case kBeta: return vBeta;
    case kStudentT: return vStudent;
    default: return k == 2 ? vTable2 : (k <= kLanes ? vTable16 : vTableN);
  }
}

template <typename S, template <typename, int> class Fn, typename... Args>
void dispatch_variant(int var, Args&&... args) {
  switch (var) {
    case vGauss: Fn<S, vGauss>::run(args...); break;
    case vBeta: Fn<S, vBeta>::run(args...); break;
    case vStudent: Fn<S, vStudent>::run(args...); break;
    case vTable2: Fn<S, vTable2>::run(args...); break;
    case vTable16: Fn<S, vTable16>::run(args...); break;
    default: Fn<S, vTableN>::run(args...); break;
  }
}

template <typename S, int VAR>
struct FwdRun {
  static void run(const FwdArgs<S>& a) { forward_tiles<S, VAR>(a); }
};
template <typename S, int VAR>
struct BwdRun {
  static void run(const BwdArgs<S>& a) { backward_tiles<S, VAR>(a); }
};

Geometry make_geometry(int W, int H, int C, int P, int kind) {
  Geometry g;
  g.W = W, g.H = H, g.C = C, g.P = P, g.kind = kind;
  g.k = kind == kTable ? P : 0;
  g.tiles_x = (W + kTile - 1) / kTile;
  g.tiles_y = (H + kTile - 1) / kTile;
  g.ntiles = g.tiles_x * g.tiles_y;
  return g;
}

template <typename S>
void forward_impl(const ForwardArgs<S>& in, StateAllocator& alloc) {
  const int nt = omp_threads(in.threads);
  const Geometry g = make_geometry(in.W, in.H, in.C, in.P, in.kind);
  const Prepared pre = prepare<S>(in, g, nt, alloc);
  const int ntr = g.ntiles > 1 ? threads_for(pre.E, kMinEntriesPerRegion, nt) : 1;
  const FwdArgs<S> A{g,           ntr,    pre.pack,  pre.tile_start, pre.entries, pre.tile_order,
                     in.background, in.img, in.alpha, in.T_final,     in.last};
  const double t0 = now();
  dispatch_variant<S, FwdRun>(variant_of(g.kind, g.k), A);
  g_phase[kPhRaster] = now() - t0;
}

template <typename S>
void backward_impl(const BackwardArgs<S>& in) {
  const int nt = omp_threads(in.threads);
  const Geometry g = make_geometry(in.W, in.H, in.C, in.P, in.kind);
  const int C = g.C, P = g.P, F2 = 6 + P + C;
  const int32_t* order = static_cast<const int32_t*>(in.state[kOrder]);
  const int32_t* prim_off = static_cast<const int32_t*>(in.state[kPrimOff]);
  Workspace& ws = workspace();
  const size_t need = sizeof(S) * size_t(in.E) * F2;
  if (ws.grad_bytes.size() < need) ws.grad_bytes.resize(need);
  S* egrad = reinterpret_cast<S*>(ws.grad_bytes.data());
  std::vector<S> tile_bg(size_t(g.ntiles) * C);
  const BwdArgs<S> A{g,
                     g.ntiles > 1 ? threads_for(in.E, kMinEntriesPerRegion, nt) : 1,
                     static_cast<const uint8_t*>(in.state[kPack]),
                     static_cast<const int32_t*>(in.state[kTileStart]),
                     static_cast<const int32_t*>(in.state[kEntries]),
                     static_cast<const int32_t*>(in.state[kTileOrder]),
                     in.background,
                     in.T_final,
                     in.last,
                     in.v_img,
                     in.v_alpha,
                     static_cast<const int32_t*>(in.state[kSlot]),
                     egrad,
                     tile_bg.data()};
  const double t0 = now();
  dispatch_variant<S, BwdRun>(variant_of(g.kind, g.k), A);
  const double t1 = now();
  g_phase[kPhBwdRaster] = t1 - t0;

  // Per-primitive sums of its entries' slots (contiguous, rank-major) -> id order.
  S *vm = in.v_means2d, *vc = in.v_conics, *vo = in.v_opacities, *vcol = in.v_colors,
    *vpar = in.v_params;
#pragma omp parallel num_threads(threads_for(in.V, kMinPrimsPerRegion, nt))
  {
    std::vector<S> sum(F2);
#pragma omp for schedule(static)
    for (int64_t r = 0; r < in.V; ++r) {
      std::fill(sum.begin(), sum.end(), S(0));
      for (int32_t j = prim_off[r]; j < prim_off[r + 1]; ++j) {
        const S* s = egrad + size_t(j) * F2;
        for (int f = 0; f < F2; ++f) sum[f] += s[f];
      }
      const int64_t i = order[r];
      vm[2 * i] = sum[0], vm[2 * i + 1] = sum[1];
      vc[3 * i] = sum[2], vc[3 * i + 1] = sum[3], vc[3 * i + 2] = sum[4];
      vo[i] = sum[5];
      for (int j = 0; j < P; ++j) vpar[i * P + j] = sum[6 + j];
      for (int j = 0; j < C; ++j) vcol[i * C + j] = sum[6 + P + j];
    }
  }
  for (int t = 0; t < g.ntiles; ++t)
    for (int ch = 0; ch < C; ++ch) in.v_background[ch] += tile_bg[size_t(t) * C + ch];
  g_phase[kPhBwdReduce] = now() - t1;
}

}  // namespace
}  // namespace splatk
