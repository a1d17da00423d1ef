// The CPU rasteriser's backward pass over tiles (see raster_impl.h): back to front per pixel,
// per-entry gradients into rank-major slots.
#pragma once

#include "raster_binning.h"

namespace splatk {
namespace {

// ---------------------------------------------------------------------------------------------
template <typename S>
struct BwdArgs {
  Geometry g;
  int nt;
  const uint8_t* pack;
  const int32_t* tile_start;
  const int32_t* entries;
  const int32_t* tile_order;
  const S* bg;
  const S* T_final;
  const int32_t* last;
  const S* v_img;    // [H, W, C]
  const S* v_alpha;  // [H, W]
  const int32_t* slot;  // [E] rank-major gradient slot of each tile entry
  S* egrad;             // [E, F2] per-entry gradients, rank-major
  S* tile_bg;        // [ntiles, C]
};

template <typename S, int VAR>
void backward_tiles(const BwdArgs<S>& A) {
  using V = typename SimdOf<S>::V;
  using M = typename SimdOf<S>::M;
  using I = typename SimdOf<S>::I;
  using IS = typename SimdOf<S>::IS;
  const Geometry& g = A.g;
  const int C = g.C, P = g.P, F2 = 6 + P + C;
  const RecLayout<S> lay(g);
  const V amax = V(S(kAlphaMax)), amin = V(S(kAlphaMin));
  constexpr bool kBins = (VAR == vTable16 || VAR == vTableN);
#pragma omp parallel num_threads(A.nt)
  {
    std::vector<V> Gbuf(size_t(C) * kTile), gcol(C);
    std::vector<V> gbin(kBins ? size_t(std::max(g.k, 1)) : 1);
    std::vector<S> sbin(kBins ? size_t(std::max(g.k, 1)) : 1);
#pragma omp for schedule(dynamic, 1)
    for (int ti = 0; ti < g.ntiles; ++ti) {
      const int tile = A.tile_order[ti];
      const int tx = tile % g.tiles_x, ty = tile / g.tiles_x;
      const int px0 = tx * kTile, py0 = ty * kTile;
      const int nrows = std::min(kTile, g.H - py0);
      const int ncols = std::min(kTile, g.W - px0);
      const I xi = I::iota() + I(IS(px0));
      const V xc = V::from_int(xi) + S(0.5);
      V T[kTile], Wacc[kTile], K[kTile];
      I last[kTile];
      int rowmax[kTile];
      V* G = Gbuf.data();
      int emax = 0;
      S* tbg = A.tile_bg + size_t(tile) * C;
      for (int ch = 0; ch < C; ++ch) tbg[ch] = S(0);
      for (int r = 0; r < nrows; ++r) {
        const size_t pix0 = size_t(py0 + r) * g.W + px0;
        alignas(64) S tf[kLanes] = {}, ga[kLanes] = {}, gc[kLanes];
        alignas(64) IS ls[kLanes] = {};
        for (int l = 0; l < ncols; ++l) {
          tf[l] = A.T_final[pix0 + l];
          ga[l] = A.v_alpha[pix0 + l];
          ls[l] = A.last[pix0 + l];
        }
        const V tfv = V::loadu(tf);
        V gbg = V::loadu(ga);  // dL/dT_final = bg . dL/dC - dL/dA, negated below
        for (int ch = 0; ch < C; ++ch) {
          for (int l = 0; l < kLanes; ++l) gc[l] = l < ncols ? A.v_img[(pix0 + l) * C + ch] : S(0);
          const V gv = V::loadu(gc);
          G[ch * kTile + r] = gv;
          gbg = gbg - gv * A.bg[ch];
          tbg[ch] += hsum(gv * tfv);
        }
        T[r] = tfv;
        Wacc[r] = V(S(0));
        K[r] = tfv * gbg;
        last[r] = I::loadu(ls);
        rowmax[r] = int(hmax(last[r]));
        emax = std::max(emax, rowmax[r]);
      }
      const int32_t start = A.tile_start[tile];
      const int n = A.tile_start[tile + 1] - start;
      const int32_t* slots = A.slot + start;
      for (int e = emax; e < n; ++e) std::memset(A.egrad + size_t(slots[e]) * F2, 0, sizeof(S) * F2);
      for (int e = emax - 1; e >= 0; --e) {
        S* slot = A.egrad + size_t(slots[e]) * F2;
        if (e >= kPrefetch)
          prefetch_record(A.pack + size_t(A.entries[start + e - kPrefetch]) * lay.stride, lay.stride);
        const uint8_t* recb = A.pack + size_t(A.entries[start + e]) * lay.stride;
        const int32_t* bb = lay.box(recb);
        const int ylo = std::max(bb[2], py0) - py0, yhi = std::min(bb[3], py0 + nrows) - py0;
        bool touched = false;
        for (int r = ylo; r < yhi; ++r) touched |= e < rowmax[r];
        if (!touched) {
          std::memset(slot, 0, sizeof(S) * F2);
          continue;
        }
        const S* rec = lay.vals(recb);
        const Prim<S, VAR> pr(rec, g.k);
        const S* col = rec + 6 + P;
        const V dx = xc - pr.mx;
        const M xm = (xi >= I(IS(bb[0]))) & (xi < I(IS(bb[1])));
        const V adx2 = V(pr.a) * dx * dx;  // r2 exactly as in the forward pass
        const V b2dx = V(S(2) * pr.b) * dx;
        const I ev = I(IS(e));
        const V zero = V(S(0));
        V R0 = zero, R1 = zero, R2 = zero, go = zero, gp0 = zero, gp1 = zero;
        for (int ch = 0; ch < C; ++ch) gcol[ch] = zero;
        if constexpr (kBins)
          for (int j = 0; j < g.k; ++j) gbin[j] = zero, sbin[j] = S(0);
        for (int row = ylo; row < yhi; ++row) {
          if (e >= rowmax[row]) continue;
          const S dy = S(py0 + row) + S(0.5) - pr.my;
          const V r2 = (adx2 + b2dx * dy) + V(pr.c * dy * dy);
          // blended in the forward pass: inside, before the pixel's last, alpha >= 1/255
          M m = xm & (r2 < V(S(1))) & (r2 >= zero) & (ev < last[row]);
          if (!any(m)) continue;
          const V r2s = maskz(m, r2);
          // profile and d profile / d r2 (+ parameter pieces)
          V prof, dp, bl, su, tr, tlam, td0, td1;
          I tidx;
          if constexpr (VAR == vGauss) {
            prof = vexp(r2s * S(-0.5 * kGaussS2));
            dp = prof * S(-0.5 * kGaussS2);
          } else if constexpr (VAR == vBeta) {
            bl = vlog1p(-r2s);  // (1 - r2)^beta = exp(beta log1p(-r2))
            prof = vexp(bl * pr.p0);
            dp = (-pr.p0) * prof / (S(1) - r2s);
          } else if constexpr (VAR == vStudent) {
            su = r2s * pr.p1;  // u = 9 r2 / nu; profile = exp(-(nu+2)/2 log1p(u))
            bl = vlog1p(su);
            prof = vexp(bl * pr.p2);
            dp = prof * (pr.p2 * pr.p1) / (S(1) + su);
          } else {
            pr.table_lookup(r2s, tr, tlam, tidx, td0, td1);
            prof = (S(1) - tlam) * td0 + tlam * td1;
            // d/dr2 of sqrt(clamp_min(r2, 1e-20)) is 0 below the clamp
            dp = maskz(r2s >= V(S(1e-20)), (td1 - td0) * (pr.km1 * S(0.5)) / tr);
          }
          const V raw = pr.o * prof;
          const V al = vmin(amax, raw);
          m &= al >= amin;
          if (!any(m)) continue;
          const V inv = recip(S(1) - al);
          const V Tc = select(m, T[row] * inv, T[row]);  // T_i = T_{i+1} / (1 - alpha_i)
          T[row] = Tc;
          V gdot = zero;
          for (int ch = 0; ch < C; ++ch) gdot = fmadd(G[ch * kTile + row], V(col[ch]), gdot);
          // dL/dalpha_i = T_i (g . c_i) - (W_behind - T_final dL/dT_final) / (1 - alpha_i)
          V dA = Tc * gdot + (K[row] - Wacc[row]) * inv;
          const V aT = maskz(m, al * Tc);
          Wacc[row] = fmadd(aT, gdot, Wacc[row]);
          for (int ch = 0; ch < C; ++ch) gcol[ch] = fmadd(aT, G[ch * kTile + row], gcol[ch]);
          dA = maskz(m & (raw <= amax), dA);  // clamp(max=0.999) passes no gradient above
          go = fmadd(dA, prof, go);
          const V vp = dA * pr.o;
          const V vr2 = vp * dp;
          R0 += vr2;
          R1 = fmadd(vr2, V(dy), R1);
          R2 = fmadd(vr2, V(dy * dy), R2);
          if constexpr (VAR == vBeta) {
            gp0 = fmadd(vp * prof, bl, gp0);
          } else if constexpr (VAR == vStudent) {
            // d/dnu: profile * (-log1p(u) / 2 + (nu + 2) / (2 nu) * u / (1 + u))
            gp0 += vp * prof *
                   (S(-0.5) * bl + (S(0.5) * (pr.p0 + S(2)) / pr.p0) * su / (S(1) + su));
          } else if constexpr (VAR == vTable2) {
            gp0 = fmadd(vp, S(1) - tlam, gp0);
            gp1 = fmadd(vp, tlam, gp1);
          } else if constexpr (VAR == vTable16) {
            const V w0 = vp * (S(1) - tlam), w1 = vp * tlam;
            for (int j = 0; j + 1 < g.k; ++j) {
              const M sel = tidx == I(IS(j));
              gbin[j] += maskz(sel, w0);
              gbin[j + 1] += maskz(sel, w1);
            }
          } else if constexpr (VAR == vTableN) {
            alignas(64) IS ii[kLanes];
            alignas(64) S a0[kLanes], a1[kLanes];
            tidx.store(ii);
            (vp * (S(1) - tlam)).store(a0);
            (vp * tlam).store(a1);
            for (int l = 0; l < kLanes; ++l) sbin[ii[l]] += a0[l], sbin[ii[l] + 1] += a1[l];
          }
        }
        // r2 = a dx^2 + 2 b dx dy + c dy^2 with dx = px + 0.5 - mx, dy = py + 0.5 - my; dx is
        // constant down a column, so sum_rows vr2 * f(dx, dy) folds into R0, R1, R2.
        const S q1 = hsum(R0 * dx), q2 = hsum(R1);
        slot[0] = S(-2) * (pr.a * q1 + pr.b * q2);
        slot[1] = S(-2) * (pr.b * q1 + pr.c * q2);
        slot[2] = hsum(R0 * dx * dx);
        slot[3] = S(2) * hsum(R1 * dx);
        slot[4] = hsum(R2);
        slot[5] = hsum(go);
        S* sp = slot + 6;
        if constexpr (VAR == vBeta || VAR == vStudent) {
          sp[0] = hsum(gp0);
        } else if constexpr (VAR == vTable2) {
          sp[0] = hsum(gp0), sp[1] = hsum(gp1);
        } else if constexpr (VAR == vTable16) {
          for (int j = 0; j < g.k; ++j) sp[j] = hsum(gbin[j]);
        } else if constexpr (VAR == vTableN) {
          for (int j = 0; j < g.k; ++j) sp[j] = sbin[j];
        }
        for (int ch = 0; ch < C; ++ch) sp[P + ch] = hsum(gcol[ch]);
      }
    }
  }
}

}  // namespace
}  // namespace splatk
