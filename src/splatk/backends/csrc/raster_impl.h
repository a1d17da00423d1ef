// Native OpenMP CPU rasteriser for splatk (the ``cpu`` backend): the kernels, torch-free,
// included by raster_kernels.cpp (float32) and raster_kernels_f64.cpp (float64).
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

#include "raster_kernels.h"

#include <omp.h>
#include <time.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <numeric>
#include <stdexcept>
#include <type_traits>
#include <vector>

#include "simd.h"

namespace splatk {
namespace {

using namespace simd;

constexpr int kTile = 16;     // tile side == vector lanes (one tile row per vector)
constexpr int kPrefetch = 4;  // tile entries to prefetch ahead
static_assert(kTile == kLanes, "one vector per tile row");
constexpr double kAlphaMax = 0.999;
constexpr double kAlphaMin = 1.0 / 255.0;
constexpr double kTMin = 1e-4;
constexpr double kGaussS2 = 9.0;    // GAUSSIAN_SUPPORT_SIGMAS ** 2
constexpr double kStudentS2 = 9.0;  // STUDENT_T_SUPPORT_SIGMAS ** 2

// Compile-time profile variants (tables: k == 2, k <= 16 via an in-register shuffle, any k).
enum Variant : int { vGauss = 0, vBeta, vStudent, vTable2, vTable16, vTableN };

}  // namespace

// Seconds spent in the phases of the last call (benchmarks/raster.py --profile); defined in
// raster_kernels.cpp.
extern double g_phase[kNumPhases];
extern bool g_cpu_clock;  // time phases by the calling thread's CPU clock (1-thread profiling)

namespace {

inline double now() {
  if (!g_cpu_clock) return omp_get_wtime();
  timespec ts;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return ts.tv_sec + 1e-9 * ts.tv_nsec;
}
enum Phase { kPhBbox = 0, kPhSort, kPhBin, kPhRaster, kPhBwdRaster, kPhBwdReduce };

int omp_threads(int64_t requested) {
  return requested > 0 ? static_cast<int>(requested) : omp_get_max_threads();
}

// Threads for a phase with `work` items: small phases run on the calling thread, since a
// parallel region costs a barrier, which on a busy machine can wait a whole scheduler slice.
inline int threads_for(int64_t work, int64_t min_work, int nt) { return work >= min_work ? nt : 1; }
constexpr int64_t kMinPrimsPerRegion = 4096;  // per-primitive passes (~50-100 ns each)
constexpr int64_t kMinEntriesPerRegion = 1024;  // tile passes (~0.2-1 us per entry)

// ---------------------------------------------------------------------------------------------
// Per-thread scratch that survives between calls (no page faults, no allocator churn).
struct BinInfo {
  int32_t x0, x1, y0, y1;  // pixel bbox [x0, x1) x [y0, y1), shrunk to the alpha cut, clipped
  float cut;               // ellipse-vs-tile test threshold on q (with margin)
};

struct Workspace {
  std::vector<uint32_t> keys, keys2;
  std::vector<int32_t> idx, idx2, counts;
  std::vector<uint8_t> vis, stage;
  std::vector<int32_t> hits;
  std::vector<uint64_t> hitbits;
  std::vector<char> grad_bytes;
};
Workspace& workspace() {
  static thread_local Workspace ws;
  return ws;
}

// ---------------------------------------------------------------------------------------------
// Profiles. `Prim` holds one primitive's per-entry constants; value() works on a vector of
// squared radii r2 in [0, 1) (lanes outside the support are zeroed by the caller).
template <typename S, int VAR>
struct Prim {
  using V = typename SimdOf<S>::V;
  using I = typename SimdOf<S>::I;
  using IS = typename SimdOf<S>::IS;
  S mx, my, a, b, c, o;
  S p0 = 0, p1 = 0, p2 = 0;  // beta | nu, 9/nu, -(nu+2)/2 | table d0, d1
  const S* par = nullptr;
  int k = 0;
  S km1 = 0;
  V tab;

  Prim(const S* rec, int k_) : k(k_) {
    mx = rec[0], my = rec[1], a = rec[2], b = rec[3], c = rec[4], o = rec[5];
    par = rec + 6;
    if constexpr (VAR == vBeta) {
      p0 = par[0];
    } else if constexpr (VAR == vStudent) {
      p0 = par[0];
      p1 = S(kStudentS2) / p0;
      p2 = S(-0.5) * (p0 + S(2));
    } else if constexpr (VAR == vTable2) {
      p0 = par[0], p1 = par[1];
      km1 = S(1);
    } else if constexpr (VAR == vTable16) {
      km1 = S(k - 1);
      alignas(64) S t[kLanes];
      for (int i = 0; i < kLanes; ++i) t[i] = par[i < k ? i : k - 1];
      tab = V::loadu(t);
    } else if constexpr (VAR == vTableN) {
      km1 = S(k - 1);
    }
  }

  // torch_ref: r = sqrt(max(r2, 1e-20)), t = r (k - 1), idx = clamp(floor(t), 0, k - 2),
  // lam = t - idx, profile = (1 - lam) d[idx] + lam d[idx + 1].
  inline void table_lookup(V r2, V& r, V& lam, I& idx, V& d0, V& d1) const {
    r = vsqrt(vmax(V(S(1e-20)), r2));
    const V t = r * km1;
    if constexpr (VAR == vTable2) {
      idx = I(IS(0));
      lam = t;
      d0 = V(p0), d1 = V(p1);
    } else {
      idx = trunc_int(t);  // t >= 0: truncation is floor
      idx = select(idx >= I(IS(k - 1)), I(IS(k - 2)), idx);
      lam = t - V::from_int(idx);
      if constexpr (VAR == vTable16) {
        d0 = permute(tab, idx);
        d1 = permute(tab, idx + I(IS(1)));
      } else {
        alignas(64) IS ii[kLanes];
        alignas(64) S x0[kLanes], x1[kLanes];
        idx.store(ii);
        for (int l = 0; l < kLanes; ++l) x0[l] = par[ii[l]], x1[l] = par[ii[l] + 1];
        d0 = V::loadu(x0), d1 = V::loadu(x1);
      }
    }
  }

  inline V value(V r2) const {
    if constexpr (VAR == vGauss) {
      return vexp(r2 * S(-0.5 * kGaussS2));
    } else if constexpr (VAR == vBeta) {
      return vexp(vlog1p(-r2) * p0);
    } else if constexpr (VAR == vStudent) {
      return vexp(vlog1p(r2 * p1) * p2);
    } else {
      V r, lam, d0, d1;
      I idx;
      table_lookup(r2, r, lam, idx, d0, d1);
      return (S(1) - lam) * d0 + lam * d1;
    }
  }
};

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
