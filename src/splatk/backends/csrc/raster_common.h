// The CPU rasteriser's shared pieces (see raster_impl.h): constants, phase timers, per-thread
// scratch and the compile-time profiles (Prim: one primitive's per-entry constants).
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

}  // namespace
}  // namespace splatk
