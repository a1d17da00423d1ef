// The CPU rasteriser's forward step 4 (see raster_impl.h): tiles composited front to back.
#pragma once

#include "raster_binning.h"

namespace splatk {
namespace {

// ---------------------------------------------------------------------------------------------
template <typename S>
struct FwdArgs {
  Geometry g;
  int nt;
  const uint8_t* pack;
  const int32_t* tile_start;
  const int32_t* entries;
  const int32_t* tile_order;
  const S* bg;
  S* img;         // [H, W, C]
  S* alpha;       // [H, W]
  S* T_final;     // [H, W]
  int32_t* last;  // [H, W]
};

template <typename S, int VAR>
void forward_tiles(const FwdArgs<S>& A) {
  using V = typename SimdOf<S>::V;
  using M = typename SimdOf<S>::M;
  using I = typename SimdOf<S>::I;
  using IS = typename SimdOf<S>::IS;
  using TV = typename SimdOf<S>::T;
  const Geometry& g = A.g;
  const int C = g.C;
  const RecLayout<S> lay(g);
  const V amax = V(S(kAlphaMax)), amin = V(S(kAlphaMin));
#pragma omp parallel num_threads(A.nt)
  {
    std::vector<V> accbuf(size_t(C) * kTile);
#pragma omp for schedule(dynamic, 1)
    for (int ti = 0; ti < g.ntiles; ++ti) {
      const int tile = A.tile_order[ti];
      const int tx = tile % g.tiles_x, ty = tile / g.tiles_x;
      const int px0 = tx * kTile, py0 = ty * kTile;
      const int nrows = std::min(kTile, g.H - py0);
      const I xi = I::iota() + I(IS(px0));
      const V xc = V::from_int(xi) + S(0.5);
      const M valid = xi < I(IS(g.W));
      TV T[kTile];
      I last[kTile];
      M done[kTile];
      V* acc = accbuf.data();
      for (int r = 0; r < nrows; ++r) {
        T[r] = t_one(V());
        last[r] = I(IS(0));
        done[r] = ~valid;
        for (int ch = 0; ch < C; ++ch) acc[ch * kTile + r] = V(S(0));
      }
      uint32_t live = (1u << nrows) - 1u;  // rows with a pixel still open
      const int32_t* ent = A.entries + A.tile_start[tile];
      const int n = A.tile_start[tile + 1] - A.tile_start[tile];
      for (int e = 0; e < n && live; ++e) {
        if (e + kPrefetch < n) prefetch_record(A.pack + size_t(ent[e + kPrefetch]) * lay.stride, lay.stride);
        const uint8_t* recb = A.pack + size_t(ent[e]) * lay.stride;
        const int32_t* bb = lay.box(recb);
        const int ylo = std::max(bb[2], py0) - py0, yhi = std::min(bb[3], py0 + nrows) - py0;
        if (yhi <= ylo || !((live >> ylo) & ((2u << (yhi - 1 - ylo)) - 1u))) continue;
        const S* rec = lay.vals(recb);
        const Prim<S, VAR> pr(rec, g.k);
        const S* col = rec + 6 + g.P;
        const V dx = xc - pr.mx;
        const M xm = (xi >= I(IS(bb[0]))) & (xi < I(IS(bb[1])));
        // r2 = a dx^2 + 2 b dx dy + c dy^2, rounded op by op as torch_ref does (no FMA), so the
        // support and 1/255 tests see the reference's r2 bit for bit
        const V adx2 = V(pr.a) * dx * dx;
        const V b2dx = V(S(2) * pr.b) * dx;
        const I e1 = I(IS(e + 1));
        for (int row = ylo; row < yhi; ++row) {
          if (!((live >> row) & 1u)) continue;
          const S dy = S(py0 + row) + S(0.5) - pr.my;
          const V r2 = (adx2 + b2dx * dy) + V(pr.c * dy * dy);
          M m = xm & (r2 < V(S(1))) & (r2 >= V(S(0))) & ~done[row];
          if (!any(m)) continue;
          const V al = vmin(amax, pr.o * pr.value(maskz(m, r2)));
          m &= al >= amin;
          if (!any(m)) continue;
          TV Tn;
          const M stop = t_step(T[row], al, Tn, kTMin) & m;  // T (1 - alpha) < 1e-4: pixel ends
          const M blend = m & ~stop;
          const V w = maskz(blend, al * t_value(T[row]));
          for (int ch = 0; ch < C; ++ch)
            acc[ch * kTile + row] = fmadd(w, V(col[ch]), acc[ch * kTile + row]);
          t_select(blend, T[row], Tn);
          last[row] = select(blend, e1, last[row]);
          if (any(stop)) {
            done[row] |= stop;
            if (all(done[row])) live &= ~(1u << row);
          }
        }
      }
      // write out
      const int ncols = std::min(kTile, g.W - px0);
      alignas(64) S tmp[kLanes];
      alignas(64) IS itmp[kLanes];
      for (int r = 0; r < nrows; ++r) {
        const size_t pix0 = size_t(py0 + r) * g.W + px0;
        last[r].store(itmp);
        for (int l = 0; l < ncols; ++l) {
          const S Tf = S(t_lane(T[r], l));
          A.alpha[pix0 + l] = S(1) - Tf;
          A.T_final[pix0 + l] = Tf;
          A.last[pix0 + l] = int32_t(itmp[l]);
        }
        for (int ch = 0; ch < C; ++ch) {
          acc[ch * kTile + r].store(tmp);
          for (int l = 0; l < ncols; ++l)
            A.img[(pix0 + l) * C + ch] = tmp[l] + A.T_final[pix0 + l] * A.bg[ch];
        }
      }
    }
  }
}

}  // namespace
}  // namespace splatk
