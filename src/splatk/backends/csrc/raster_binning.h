// The CPU rasteriser's forward steps 1-3 (see raster_impl.h): the alpha-cut bbox and tile test,
// the stable depth sort, per-rank records and the binning into 16x16 tiles (prepare).
#pragma once

#include "raster_common.h"

namespace splatk {
namespace {

// ---------------------------------------------------------------------------------------------
// Conservative squared radius beyond which o * profile < 1/255 (< 0: never visible).
template <typename S>
double alpha_cut_r2(int kind, double o, const S* par, int k) {
  const double thr = kAlphaMin * (1.0 - 1e-4);
  double r2 = 1.0;
  if (kind == kTable) {
    int last = -1;
    for (int j = 0; j < k; ++j)
      if (o * double(par[j]) >= thr) last = j;
    if (last < 0) return -1.0;
    double r = 1.0;
    if (last < k - 1) {
      // between samples the profile is linear in r (table_lookup), so o * profile crosses thr
      // once in [last, last + 1], where it falls from >= thr to < thr
      const double t = thr / o, d0 = double(par[last]), d1 = double(par[last + 1]);
      const double lam = d0 > d1 ? std::clamp((d0 - t) / (d0 - d1), 0.0, 1.0) : 1.0;
      r = (double(last) + lam) / double(k - 1);
    }
    r2 = r * r;
  } else if (kind == kGaussian) {
    if (!(o >= thr)) return -1.0;  // profile <= 1
    r2 = std::log(o / thr) / (0.5 * kGaussS2);
  } else if (kind == kBeta) {
    const double beta = par[0];
    if (!(beta > 0)) return 1.0;  // invalid parameter: no shrinking, no culling
    if (!(o >= thr)) return -1.0;
    r2 = 1.0 - std::pow(thr / o, 1.0 / beta);
  } else if (kind == kStudentT) {
    const double nu = par[0];
    if (!(nu > 0)) return 1.0;
    if (!(o >= thr)) return -1.0;
    r2 = nu / kStudentS2 * (std::pow(o / thr, 2.0 / (nu + 2.0)) - 1.0);
  }
  if (!(r2 == r2)) return 1.0;
  return std::min(1.0, r2 * (1.0 + 1e-4) + 1e-6);
}

// Whether the ellipse q(d) = a dx^2 + 2 b dx dy + c dy^2 < cut reaches a pixel centre of tile
// (tx, ty) inside the bbox: min of the convex q over the box of those centres (origin inside,
// or on one of the four edges).
template <typename S>
inline bool tile_hit(const S* rec, const BinInfo& bi, int tx, int ty) {
  const double mx = rec[0], my = rec[1], a = rec[2], b = rec[3], c = rec[4];
  if (!(a > 0 && c > 0 && a * c - b * b > 0)) return true;
  const int x0 = std::max(bi.x0, tx * kTile), x1 = std::min(bi.x1, tx * kTile + kTile);
  const int y0 = std::max(bi.y0, ty * kTile), y1 = std::min(bi.y1, ty * kTile + kTile);
  const double dx0 = x0 + 0.5 - mx, dx1 = x1 - 0.5 - mx;
  const double dy0 = y0 + 0.5 - my, dy1 = y1 - 0.5 - my;
  if (dx0 <= 0 && dx1 >= 0 && dy0 <= 0 && dy1 >= 0) return true;
  auto q = [&](double x, double y) { return (a * x + 2 * b * y) * x + c * y * y; };
  const double ia = 1.0 / a, ic = 1.0 / c;
  double best = q(dx0, std::clamp(-b * dx0 * ic, dy0, dy1));
  best = std::min(best, q(dx1, std::clamp(-b * dx1 * ic, dy0, dy1)));
  best = std::min(best, q(std::clamp(-b * dy0 * ia, dx0, dx1), dy0));
  best = std::min(best, q(std::clamp(-b * dy1 * ia, dx0, dx1), dy1));
  return best < double(bi.cut);
}

// ---------------------------------------------------------------------------------------------
// Stable sort of visible primitive ids by depth (torch.sort(stable=True) order).
inline uint32_t float_key(float x) {
  if (x != x) return 0xFFFFFFFFu;  // NaN last, like torch.sort
  x = x + 0.0f;                    // -0 -> +0 (ties with +0, as in torch)
  uint32_t u;
  std::memcpy(&u, &x, 4);
  return (u & 0x80000000u) ? ~u : (u | 0x80000000u);
}

inline uint64_t double_key(double x) {
  if (x != x) return ~uint64_t(0);
  x = x + 0.0;
  uint64_t u;
  std::memcpy(&u, &x, 8);
  return (u >> 63) ? ~u : (u | (uint64_t(1) << 63));
}

// LSD radix sort (11-bit digits) of ids by 32-bit keys; stable.
void radix_sort32(std::vector<uint32_t>& keys, std::vector<int32_t>& ids, Workspace& ws) {
  const size_t n = keys.size();
  ws.keys2.resize(n);
  ws.idx2.resize(n);
  uint32_t* k0 = keys.data();
  int32_t* i0 = ids.data();
  uint32_t* k1 = ws.keys2.data();
  int32_t* i1 = ws.idx2.data();
  for (int shift = 0; shift < 32; shift += 11) {
    uint32_t hist[2048] = {0};
    for (size_t i = 0; i < n; ++i) hist[(k0[i] >> shift) & 2047]++;
    bool trivial = false;
    for (int d = 0; d < 2048; ++d)
      if (hist[d] == n) trivial = true;
    if (trivial) continue;
    uint32_t sum = 0;
    for (int d = 0; d < 2048; ++d) {
      const uint32_t h = hist[d];
      hist[d] = sum;
      sum += h;
    }
    for (size_t i = 0; i < n; ++i) {
      const uint32_t p = hist[(k0[i] >> shift) & 2047]++;
      k1[p] = k0[i];
      i1[p] = i0[i];
    }
    std::swap(k0, k1);
    std::swap(i0, i1);
  }
  if (i0 != ids.data()) std::memcpy(ids.data(), i0, n * sizeof(int32_t));
}

// ---------------------------------------------------------------------------------------------
struct Geometry {
  int W, H, tiles_x, tiles_y, ntiles, C, P, k, kind;
};

// One primitive's record, in rank order: int32 pixel bbox [x0, x1, y0, y1], then S values
// [mx, my, a, b, c, o, params(P), colors(C)], padded to whole cache lines (one 64-byte line for
// float RGB Gaussians) so a tile entry costs one prefetchable line.
template <typename S>
struct RecLayout {
  size_t stride;
  explicit RecLayout(const Geometry& g)
      : stride((16 + sizeof(S) * size_t(6 + g.P + g.C) + 4 + 63) / 64 * 64) {}
  static const int32_t* box(const uint8_t* r) { return reinterpret_cast<const int32_t*>(r); }
  static int32_t* box(uint8_t* r) { return reinterpret_cast<int32_t*>(r); }
  static const S* vals(const uint8_t* r) { return reinterpret_cast<const S*>(r + 16); }
  static S* vals(uint8_t* r) { return reinterpret_cast<S*>(r + 16); }
  // The ellipse-vs-tile threshold of primitives spanning > 64 tiles, kept in the last 4 bytes
  // (the fill pass re-tests those); a stride is always >= 4 bytes larger than the payload.
  float& cut(uint8_t* r) const { return *reinterpret_cast<float*>(r + stride - 4); }
  float cut(const uint8_t* r) const { return *reinterpret_cast<const float*>(r + stride - 4); }
};

inline void prefetch_record(const uint8_t* r, size_t stride) {
  __builtin_prefetch(r);
  if (stride > 64) __builtin_prefetch(r + 64);
}

// The binned scene (see StateBuffer in raster_kernels.h).
struct Prepared {
  int64_t V = 0, E = 0;
  const int32_t* order = nullptr;
  const uint8_t* pack = nullptr;
  const int32_t* prim_off = nullptr;
  const int32_t* tile_start = nullptr;
  const int32_t* entries = nullptr;
  const int32_t* slot = nullptr;
  const int32_t* tile_order = nullptr;
};

template <typename T>
T* state_alloc(StateAllocator& alloc, StateBuffer which, int64_t count) {
  return static_cast<T*>(alloc.allocate(which, count, int(sizeof(T))));
}

template <typename S>
Prepared prepare(const ForwardArgs<S>& in, const Geometry& g, int nt, StateAllocator& alloc) {
  // nt: threads for the per-primitive passes; the count and fill passes split ranks into nt
  // chunks (the same split in both).
  const int64_t N = in.N;
  const S* mean = in.means2d;
  const S* con = in.conics;
  const S* opa = in.opacities;
  const S* col = in.colors;
  const S* par = in.params;
  const int C = g.C, P = g.P;
  const RecLayout<S> lay(g);
  const size_t stride = lay.stride;
  Workspace& ws = workspace();
  const double t0 = now();

  // 1. per primitive, in id order: support bbox (mirrors support_bboxes() in torch_ref.py, in S),
  //    shrunk to where o * profile can reach 1/255; tile hits; the record, staged by id.
  ws.vis.resize(N);
  ws.hits.resize(N);
  ws.hitbits.resize(N);
  ws.stage.resize(size_t(N) * stride);
  uint8_t* vis = ws.vis.data();
  int32_t* hits_of = ws.hits.data();
  uint64_t* bits_of = ws.hitbits.data();
  uint8_t* stage = ws.stage.data();
#pragma omp parallel for num_threads(threads_for(N, kMinPrimsPerRegion, nt)) schedule(static)
  for (int64_t i = 0; i < N; ++i) {
    const S mx = mean[2 * i], my = mean[2 * i + 1];
    const S a = con[3 * i], b = con[3 * i + 1], c = con[3 * i + 2];
    S det = a * c - b * b;
    det = det > S(1e-30) ? det : S(1e-30);
    const S qx = c / det, qy = a / det;
    const S hx = std::sqrt(qx > 0 ? qx : S(0)), hy = std::sqrt(qy > 0 ? qy : S(0));
    auto clampi = [](double v, int hi) -> int {
      if (!(v == v)) return 0;
      return static_cast<int>(std::min<double>(std::max<double>(v, 0.0), double(hi)));
    };
    int x0 = clampi(std::ceil(mx - hx - S(0.5)), g.W);
    int x1 = clampi(std::floor(mx + hx - S(0.5)) + S(1), g.W);
    int y0 = clampi(std::ceil(my - hy - S(0.5)), g.H);
    int y1 = clampi(std::floor(my + hy - S(0.5)) + S(1), g.H);
    const double cut = alpha_cut_r2<S>(g.kind, double(opa[i]), par + i * P, g.k);
    vis[i] = 0;
    if (!(cut >= 0) || x1 <= x0 || y1 <= y0) continue;
    float tcut = float(1.0 + 1e-5);
    if (cut < 1.0) {
      const double s = std::sqrt(cut);
      const double sx = double(hx) * s, sy = double(hy) * s;
      x0 = std::max(x0, clampi(std::ceil(double(mx) - sx - 0.5), g.W));
      x1 = std::min(x1, clampi(std::floor(double(mx) + sx - 0.5) + 1.0, g.W));
      y0 = std::max(y0, clampi(std::ceil(double(my) - sy - 0.5), g.H));
      y1 = std::min(y1, clampi(std::floor(double(my) + sy - 0.5) + 1.0, g.H));
      if (x1 <= x0 || y1 <= y0) continue;
      tcut = float(cut * (1.0 + 1e-5) + 1e-7);
    }
    vis[i] = 1;
    uint8_t* recb = stage + size_t(i) * stride;
    int32_t* bb = lay.box(recb);
    bb[0] = x0, bb[1] = x1, bb[2] = y0, bb[3] = y1;
    S* rec = lay.vals(recb);
    rec[0] = mx, rec[1] = my, rec[2] = a, rec[3] = b, rec[4] = c, rec[5] = opa[i];
    for (int j = 0; j < P; ++j) rec[6 + j] = par[i * P + j];
    for (int j = 0; j < C; ++j) rec[6 + P + j] = col[i * C + j];
    const BinInfo bi{x0, x1, y0, y1, tcut};
    const int tx0 = x0 / kTile, tx1 = (x1 - 1) / kTile + 1;
    const int ty0 = y0 / kTile, ty1 = (y1 - 1) / kTile + 1;
    if (tx1 - tx0 == 1 || ty1 - ty0 == 1) {
      // a strip of tiles spanning the bbox across: the convex support meets every one
      hits_of[i] = (tx1 - tx0) * (ty1 - ty0);
      bits_of[i] = ~uint64_t(0);
    } else {
      uint64_t bits = 0;
      int hits = 0, j = 0;
      const bool big = (tx1 - tx0) * (ty1 - ty0) > 64;
      for (int ty = ty0; ty < ty1; ++ty)
        for (int tx = tx0; tx < tx1; ++tx, ++j)
          if (tile_hit(rec, bi, tx, ty)) {
            hits++;
            if (!big) bits |= uint64_t(1) << j;
          }
      hits_of[i] = hits;
      bits_of[i] = big ? uint64_t(0) : bits;  // big: the fill pass re-tests (needs the cut)
      if (big) lay.cut(recb) = tcut;
    }
  }
  const double t1 = now();
  g_phase[kPhBbox] = t1 - t0;

  // 2. stable sort of the visible ids by depth.
  std::vector<int32_t>& ids = ws.idx;
  ids.clear();
  for (int64_t i = 0; i < N; ++i)
    if (vis[i]) ids.push_back(int32_t(i));
  const int64_t V = int64_t(ids.size());
  if (in.depths_f32 && V >= 256) {
    const float* dep = static_cast<const float*>(in.depths);
    ws.keys.resize(V);
    for (int64_t r = 0; r < V; ++r) ws.keys[r] = float_key(dep[ids[r]]);
    radix_sort32(ws.keys, ids, ws);
  } else if (in.depths_f32) {
    const float* dep = static_cast<const float*>(in.depths);
    std::stable_sort(ids.begin(), ids.end(), [dep](int32_t x, int32_t y) {
      return float_key(dep[x]) < float_key(dep[y]);
    });
  } else {
    const double* dep = static_cast<const double*>(in.depths);
    std::stable_sort(ids.begin(), ids.end(), [dep](int32_t x, int32_t y) {
      return double_key(dep[x]) < double_key(dep[y]);
    });
  }
  const double t2 = now();
  g_phase[kPhSort] = t2 - t1;

  Prepared out;
  out.V = V;
  int32_t* order = state_alloc<int32_t>(alloc, kOrder, V);
  uint8_t* pack = state_alloc<uint8_t>(alloc, kPack, V * int64_t(stride));
  int32_t* prim_off = state_alloc<int32_t>(alloc, kPrimOff, V + 1);
  out.order = order, out.pack = pack, out.prim_off = prim_off;
  std::memcpy(order, ids.data(), V * sizeof(int32_t));

  // 3. records into rank order; per-chunk tile counts (rank chunk t always uses counts row t,
  //    so the fill below gives every tile list its entries in rank = depth order).
  const int ntiles = g.ntiles;
  nt = threads_for(V, kMinPrimsPerRegion, nt);  // chunks of the count and fill passes
  ws.counts.assign(size_t(nt) * ntiles, 0);
  int32_t* counts = ws.counts.data();
  constexpr int64_t kAhead = 8;
#pragma omp parallel for num_threads(nt) schedule(static, 1)
  for (int t = 0; t < nt; ++t) {
    const int64_t r0 = V * t / nt, r1 = V * (t + 1) / nt;
    int32_t* cnt = counts + size_t(t) * ntiles;
    for (int64_t r = r0; r < r1; ++r) {
      if (r + kAhead < r1) prefetch_record(stage + size_t(order[r + kAhead]) * stride, stride);
      const int64_t i = order[r];
      uint8_t* recb = pack + r * stride;
      std::memcpy(recb, stage + size_t(i) * stride, stride);
      prim_off[r + 1] = hits_of[i];
      const int32_t* bb = lay.box(recb);
      const int tx0 = bb[0] / kTile, tx1 = (bb[1] - 1) / kTile + 1;
      const int ty0 = bb[2] / kTile, ty1 = (bb[3] - 1) / kTile + 1;
      const uint64_t bits = bits_of[i];
      if (bits == ~uint64_t(0)) {
        for (int ty = ty0; ty < ty1; ++ty)
          for (int tx = tx0; tx < tx1; ++tx) cnt[ty * g.tiles_x + tx]++;
      } else if ((tx1 - tx0) * (ty1 - ty0) <= 64) {
        int j = 0;
        for (int ty = ty0; ty < ty1; ++ty)
          for (int tx = tx0; tx < tx1; ++tx, ++j) cnt[ty * g.tiles_x + tx] += int((bits >> j) & 1);
      } else {
        const BinInfo bi{bb[0], bb[1], bb[2], bb[3], lay.cut(recb)};
        for (int ty = ty0; ty < ty1; ++ty)
          for (int tx = tx0; tx < tx1; ++tx)
            if (tile_hit(lay.vals(recb), bi, tx, ty)) cnt[ty * g.tiles_x + tx]++;
      }
    }
  }
  prim_off[0] = 0;
  for (int64_t r = 0; r < V; ++r) prim_off[r + 1] += prim_off[r];
  const int64_t E = prim_off[V];
  if (E >= (int64_t(1) << 31)) throw std::runtime_error("cpu rasteriser: too many tile entries");
  out.E = E;
  int32_t* tile_start = state_alloc<int32_t>(alloc, kTileStart, ntiles + 1);
  out.tile_start = tile_start;
  {
    int64_t run = 0;
    for (int t = 0; t < ntiles; ++t) {
      tile_start[t] = int32_t(run);
      for (int th = 0; th < nt; ++th) {
        int32_t& c = counts[size_t(th) * ntiles + t];
        const int32_t n = c;
        c = int32_t(run);  // becomes this chunk's write cursor
        run += n;
      }
    }
    tile_start[ntiles] = int32_t(run);
  }

  // 4. fill the tile lists; slot[pos] = where entry pos's gradients go in rank-major order.
  int32_t* entries = state_alloc<int32_t>(alloc, kEntries, E);
  int32_t* slot = state_alloc<int32_t>(alloc, kSlot, E);
  out.entries = entries, out.slot = slot;
#pragma omp parallel for num_threads(nt) schedule(static, 1)
  for (int t = 0; t < nt; ++t) {
    const int64_t r0 = V * t / nt, r1 = V * (t + 1) / nt;
    int32_t* cur = counts + size_t(t) * ntiles;
    for (int64_t r = r0; r < r1; ++r) {
      const uint8_t* recb = pack + r * stride;
      const int32_t* bb = lay.box(recb);
      const int tx0 = bb[0] / kTile, tx1 = (bb[1] - 1) / kTile + 1;
      const int ty0 = bb[2] / kTile, ty1 = (bb[3] - 1) / kTile + 1;
      const uint64_t bits = bits_of[order[r]];
      const bool retest = bits != ~uint64_t(0) && (tx1 - tx0) * (ty1 - ty0) > 64;
      const BinInfo bi{bb[0], bb[1], bb[2], bb[3], retest ? lay.cut(recb) : 0.f};
      int32_t j = prim_off[r];
      int jb = 0;
      for (int ty = ty0; ty < ty1; ++ty)
        for (int tx = tx0; tx < tx1; ++tx, ++jb) {
          const bool hit = retest ? tile_hit(lay.vals(recb), bi, tx, ty) : ((bits >> jb) & 1);
          if (hit) {
            const int32_t pos = cur[ty * g.tiles_x + tx]++;
            entries[pos] = int32_t(r);
            slot[pos] = j++;
          }
        }
    }
  }

  // heaviest tiles first for the dynamic schedule
  int32_t* tord = state_alloc<int32_t>(alloc, kTileOrder, ntiles);
  out.tile_order = tord;
  std::iota(tord, tord + ntiles, 0);
  std::stable_sort(tord, tord + ntiles, [tile_start](int32_t x, int32_t y) {
    return tile_start[x + 1] - tile_start[x] > tile_start[y + 1] - tile_start[y];
  });
  g_phase[kPhBin] = now() - t2;
  return out;
}

}  // namespace
}  // namespace splatk
