// 16-lane SIMD wrappers for the CPU rasteriser (one lane per pixel of a 16-pixel tile row).
//
//   SimdOf<S>::V  16 lanes of S       (arithmetic, comparisons -> M)
//   SimdOf<S>::M  16-lane mask        (&, |, ~, any, all, select)
//   SimdOf<S>::I  16 integer lanes    (per-pixel counters, table indices)
//   SimdOf<S>::T  float64 transmittance for 16 lanes
//
// float on AVX-512: __m512 / __mmask16 intrinsics (masks stay in k registers; exp via
// vscalefps). Everywhere else (float without AVX-512, and all float64, which only serves the
// float64 gradcheck) GCC/Clang vector extensions, which the compiler lowers to whatever the
// target has. float exp/log are Cephes polynomials (about 1 ulp); float64 calls libm per lane so
// finite differences see an exact function.
#pragma once

#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>
#if defined(__AVX512F__)
#include <immintrin.h>
#endif

namespace splatk {
namespace simd {

constexpr int kLanes = 16;

typedef float vf __attribute__((vector_size(64)));
typedef int32_t vi __attribute__((vector_size(64)));
typedef double vd __attribute__((vector_size(128)));
typedef int64_t vl __attribute__((vector_size(128)));
typedef float vf8 __attribute__((vector_size(32)));
typedef int32_t vi8 __attribute__((vector_size(32)));
typedef double vd8 __attribute__((vector_size(64)));
typedef int64_t vl8 __attribute__((vector_size(64)));

// ============================================================================================
// Generic lanes over vector extensions.
template <typename MT>
struct GMask {
  MT m;
  GMask() = default;
  explicit GMask(MT x) : m(x) {}
  friend GMask operator&(GMask a, GMask b) { return GMask(a.m & b.m); }
  friend GMask operator|(GMask a, GMask b) { return GMask(a.m | b.m); }
  friend GMask operator~(GMask a) { return GMask(~a.m); }
  GMask& operator&=(GMask b) { m &= b.m; return *this; }
  GMask& operator|=(GMask b) { m |= b.m; return *this; }
  static GMask none() { return GMask(MT{}); }
  bool lane(int i) const { return m[i] != 0; }
};

template <typename MT>
inline bool any(GMask<MT> a) {
  auto r = a.m[0];
  for (int i = 1; i < kLanes; ++i) r |= a.m[i];
  return r != 0;
}
template <typename MT>
inline bool all(GMask<MT> a) {
  auto r = a.m[0];
  for (int i = 1; i < kLanes; ++i) r &= a.m[i];
  return r != 0;
}

template <typename IS, typename MT>
struct GInt {
  using Mask = GMask<MT>;
  MT v;
  GInt() = default;
  GInt(IS s) : v(MT{} + s) {}
  explicit GInt(MT x) : v(x) {}
  friend GInt operator+(GInt a, GInt b) { return GInt(a.v + b.v); }
  friend Mask operator<(GInt a, GInt b) { return Mask(a.v < b.v); }
  friend Mask operator>=(GInt a, GInt b) { return Mask(a.v >= b.v); }
  friend Mask operator==(GInt a, GInt b) { return Mask(a.v == b.v); }
  IS operator[](int i) const { return v[i]; }
  void store(IS* p) const { std::memcpy(p, &v, sizeof(MT)); }
  static GInt loadu(const IS* p) {
    GInt r;
    std::memcpy(&r.v, p, sizeof(MT));
    return r;
  }
  static GInt iota() {
    GInt r;
    for (int i = 0; i < kLanes; ++i) r.v[i] = i;
    return r;
  }
};

template <typename S, typename VT, typename MT, typename IS>
struct GVec {
  using Mask = GMask<MT>;
  using Int = GInt<IS, MT>;
  VT v;
  GVec() = default;
  GVec(S s) : v(VT{} + s) {}
  explicit GVec(VT x) : v(x) {}
  friend GVec operator+(GVec a, GVec b) { return GVec(a.v + b.v); }
  friend GVec operator-(GVec a, GVec b) { return GVec(a.v - b.v); }
  friend GVec operator*(GVec a, GVec b) { return GVec(a.v * b.v); }
  friend GVec operator/(GVec a, GVec b) { return GVec(a.v / b.v); }
  friend GVec operator-(GVec a) { return GVec(-a.v); }
  GVec& operator+=(GVec b) { v += b.v; return *this; }
  friend Mask operator<(GVec a, GVec b) { return Mask(a.v < b.v); }
  friend Mask operator<=(GVec a, GVec b) { return Mask(a.v <= b.v); }
  friend Mask operator>(GVec a, GVec b) { return Mask(a.v > b.v); }
  friend Mask operator>=(GVec a, GVec b) { return Mask(a.v >= b.v); }
  S operator[](int i) const { return v[i]; }
  void store(S* p) const { std::memcpy(p, &v, sizeof(VT)); }
  static GVec from_int(Int a) { return GVec(__builtin_convertvector(a.v, VT)); }
  static GVec loadu(const S* p) {
    GVec r;
    std::memcpy(&r.v, p, sizeof(VT));
    return r;
  }
};

template <typename S, typename VT, typename MT, typename IS>
inline GVec<S, VT, MT, IS> select(GMask<MT> m, GVec<S, VT, MT, IS> a, GVec<S, VT, MT, IS> b) {
  return GVec<S, VT, MT, IS>(m.m ? a.v : b.v);
}
template <typename IS, typename MT>
inline GInt<IS, MT> select(GMask<MT> m, GInt<IS, MT> a, GInt<IS, MT> b) {
  return GInt<IS, MT>(m.m ? a.v : b.v);
}
template <typename S, typename VT, typename MT, typename IS>
inline GVec<S, VT, MT, IS> maskz(GMask<MT> m, GVec<S, VT, MT, IS> a) {
  return GVec<S, VT, MT, IS>(m.m ? a.v : VT{});
}
// a * b + c (unfused here; the AVX-512 float version fuses). Built with -ffp-contract=off,
// so plain expressions round like the reference's separate torch ops.
template <typename S, typename VT, typename MT, typename IS>
inline GVec<S, VT, MT, IS> fmadd(GVec<S, VT, MT, IS> a, GVec<S, VT, MT, IS> b,
                                 GVec<S, VT, MT, IS> c) {
  return GVec<S, VT, MT, IS>(a.v * b.v + c.v);
}
template <typename S, typename VT, typename MT, typename IS>
inline GVec<S, VT, MT, IS> vmin(GVec<S, VT, MT, IS> a, GVec<S, VT, MT, IS> b) {
  return GVec<S, VT, MT, IS>(a.v < b.v ? a.v : b.v);
}
template <typename S, typename VT, typename MT, typename IS>
inline GVec<S, VT, MT, IS> vmax(GVec<S, VT, MT, IS> a, GVec<S, VT, MT, IS> b) {
  return GVec<S, VT, MT, IS>(a.v > b.v ? a.v : b.v);
}
template <typename S, typename VT, typename MT, typename IS>
inline GVec<S, VT, MT, IS> recip(GVec<S, VT, MT, IS> a) {
  return GVec<S, VT, MT, IS>(S(1) / a.v);
}
template <typename S, typename VT, typename MT, typename IS>
inline S hsum(GVec<S, VT, MT, IS> a) {
  S s = 0;
  for (int i = 0; i < kLanes; ++i) s += a.v[i];
  return s;
}
template <typename IS, typename MT>
inline int64_t hmax(GInt<IS, MT> a) {
  int64_t r = a.v[0];
  for (int i = 1; i < kLanes; ++i) r = a.v[i] > r ? a.v[i] : r;
  return r;
}
// truncation toward zero (floor for the non-negative inputs it gets)
template <typename S, typename VT, typename MT, typename IS>
inline GInt<IS, MT> trunc_int(GVec<S, VT, MT, IS> a) {
  return GInt<IS, MT>(__builtin_convertvector(a.v, MT));
}
template <typename S, typename VT, typename MT, typename IS>
inline GVec<S, VT, MT, IS> permute(GVec<S, VT, MT, IS> tab, GInt<IS, MT> idx) {
  return GVec<S, VT, MT, IS>(__builtin_shuffle(tab.v, idx.v));
}
template <typename S, typename VT, typename MT, typename IS>
inline GVec<S, VT, MT, IS> vsqrt(GVec<S, VT, MT, IS> a) {
  GVec<S, VT, MT, IS> r;
  for (int i = 0; i < kLanes; ++i) r.v[i] = std::sqrt(a.v[i]);
  return r;
}

using GF = GVec<float, vf, vi, int32_t>;
using GD = GVec<double, vd, vl, int64_t>;

inline GD vexp(GD x) {
  for (int i = 0; i < kLanes; ++i) x.v[i] = std::exp(x.v[i]);
  return x;
}
inline GD vlog1p(GD x) {
  for (int i = 0; i < kLanes; ++i) x.v[i] = std::log1p(x.v[i]);
  return x;
}

// Cephes expf: x = n ln2 + r, |r| <= ln2/2, degree-6 polynomial; x clamped to [-87.3, 88].
inline GF vexp(GF xx) {
  vf x = xx.v;
  const vf lo = vf{} - 87.3f, hi = vf{} + 88.0f;
  x = x < lo ? lo : x;
  x = x > hi ? hi : x;
  const float magic = 12582912.0f;  // 1.5 * 2^23: adding it rounds to an integer
  const vf t = x * 1.44269504088896341f + magic;
  const vf n = t - magic;
  const vi ni = (vi)t - (vi)(vf{} + magic);
  vf r = x - n * 0.693359375f;
  r = r - n * -2.12194440e-4f;
  vf p = vf{} + 1.9875691500e-4f;
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  const vf y = p * (r * r) + r + 1.0f;
  return GF(y * (vf)((ni + 127) << 23));
}

// Cephes logf for normal x > 0.
inline vf vlog_raw(vf x) {
  const vi xi = (vi)x;
  vi e = ((xi >> 23) & 0xff) - 126;
  vf m = (vf)((xi & 0x007fffff) | 0x3f000000);  // mantissa in [0.5, 1)
  const vi small = m < 0.70710678118654752f;
  e = e + small;  // masks are -1
  m = (small ? m + m : m) - 1.0f;
  const vf ef = __builtin_convertvector(e, vf);
  const vf z = m * m;
  vf p = vf{} + 7.0376836292e-2f;
  p = p * m - 1.1514610310e-1f;
  p = p * m + 1.1676998740e-1f;
  p = p * m - 1.2420140846e-1f;
  p = p * m + 1.4249322787e-1f;
  p = p * m - 1.6668057665e-1f;
  p = p * m + 2.0000714765e-1f;
  p = p * m - 2.4999993993e-1f;
  p = p * m + 3.3333331174e-1f;
  vf y = p * m * z;
  y = y + ef * -2.12194440e-4f;
  y = y - 0.5f * z;
  return m + y + ef * 0.693359375f;
}

// log1p(x), x > -1, accurate for small x (Goldberg: log(u) * x / (u - 1), u = 1 + x).
inline GF vlog1p(GF xx) {
  const vf x = xx.v;
  const vf u = x + 1.0f;
  const vf d = u - 1.0f;
  const vi exact = d == 0.0f;
  const vf dd = exact ? vf{} + 1.0f : d;
  const vf r = vlog_raw(u) * (x / dd);
  return GF(exact ? x : r);
}

// float64 transmittance for the generic float path: two 8-lane halves (GCC scalarises
// 1024-bit vectors).
struct GT16 {
  vd8 lo, hi;
};
inline GT16 t_one(GF) { return GT16{vd8{} + 1.0, vd8{} + 1.0}; }
inline GMask<vi> t_step(const GT16& T, GF al, GT16& Tn, double tmin) {
  const vf8 alo = __builtin_shufflevector(al.v, al.v, 0, 1, 2, 3, 4, 5, 6, 7);
  const vf8 ahi = __builtin_shufflevector(al.v, al.v, 8, 9, 10, 11, 12, 13, 14, 15);
  Tn.lo = T.lo * (1.0 - __builtin_convertvector(alo, vd8));
  Tn.hi = T.hi * (1.0 - __builtin_convertvector(ahi, vd8));
  const vi8 mlo = __builtin_convertvector(Tn.lo < (vd8{} + tmin), vi8);
  const vi8 mhi = __builtin_convertvector(Tn.hi < (vd8{} + tmin), vi8);
  return GMask<vi>(
      __builtin_shufflevector(mlo, mhi, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15));
}
inline void t_select(GMask<vi> m, GT16& T, const GT16& Tn) {
  const vl8 mlo =
      __builtin_convertvector(__builtin_shufflevector(m.m, m.m, 0, 1, 2, 3, 4, 5, 6, 7), vl8);
  const vl8 mhi = __builtin_convertvector(
      __builtin_shufflevector(m.m, m.m, 8, 9, 10, 11, 12, 13, 14, 15), vl8);
  T.lo = mlo ? Tn.lo : T.lo;
  T.hi = mhi ? Tn.hi : T.hi;
}
inline GF t_value(const GT16& T) {
  const vf8 lo = __builtin_convertvector(T.lo, vf8), hi = __builtin_convertvector(T.hi, vf8);
  return GF(__builtin_shufflevector(lo, hi, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15));
}
inline double t_lane(const GT16& T, int l) { return l < 8 ? T.lo[l] : T.hi[l - 8]; }

// float64 path: T is just a vector of doubles.
inline GD t_one(GD) { return GD(1.0); }
inline GMask<vl> t_step(const GD& T, GD al, GD& Tn, double tmin) {
  Tn = T * (1.0 - al);
  return Tn < GD(tmin);
}
inline void t_select(GMask<vl> m, GD& T, const GD& Tn) { T = select(m, Tn, T); }
inline GD t_value(const GD& T) { return T; }
inline double t_lane(const GD& T, int l) { return T[l]; }

// ============================================================================================
#if defined(__AVX512F__)
// float on AVX-512.
struct KMask {
  __mmask16 k;
  KMask() = default;
  explicit KMask(__mmask16 x) : k(x) {}
  friend KMask operator&(KMask a, KMask b) { return KMask(__mmask16(a.k & b.k)); }
  friend KMask operator|(KMask a, KMask b) { return KMask(__mmask16(a.k | b.k)); }
  friend KMask operator~(KMask a) { return KMask(__mmask16(~a.k)); }
  KMask& operator&=(KMask b) { k &= b.k; return *this; }
  KMask& operator|=(KMask b) { k |= b.k; return *this; }
  static KMask none() { return KMask(0); }
  bool lane(int i) const { return (k >> i) & 1; }
};
inline bool any(KMask a) { return a.k != 0; }
inline bool all(KMask a) { return a.k == 0xFFFF; }

struct ZInt {
  __m512i v;
  ZInt() = default;
  ZInt(int32_t s) : v(_mm512_set1_epi32(s)) {}
  explicit ZInt(__m512i x) : v(x) {}
  friend ZInt operator+(ZInt a, ZInt b) { return ZInt(_mm512_add_epi32(a.v, b.v)); }
  friend KMask operator<(ZInt a, ZInt b) {
    return KMask(_mm512_cmp_epi32_mask(a.v, b.v, _MM_CMPINT_LT));
  }
  friend KMask operator>=(ZInt a, ZInt b) {
    return KMask(_mm512_cmp_epi32_mask(a.v, b.v, _MM_CMPINT_NLT));
  }
  friend KMask operator==(ZInt a, ZInt b) {
    return KMask(_mm512_cmp_epi32_mask(a.v, b.v, _MM_CMPINT_EQ));
  }
  int32_t operator[](int i) const {
    alignas(64) int32_t t[16];
    _mm512_store_si512(t, v);
    return t[i];
  }
  void store(int32_t* p) const { _mm512_storeu_si512(p, v); }
  static ZInt loadu(const int32_t* p) { return ZInt(_mm512_loadu_si512(p)); }
  static ZInt iota() {
    return ZInt(_mm512_set_epi32(15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0));
  }
};

struct ZVec {
  using Mask = KMask;
  using Int = ZInt;
  __m512 v;
  ZVec() = default;
  ZVec(float s) : v(_mm512_set1_ps(s)) {}
  explicit ZVec(__m512 x) : v(x) {}
  friend ZVec operator+(ZVec a, ZVec b) { return ZVec(_mm512_add_ps(a.v, b.v)); }
  friend ZVec operator-(ZVec a, ZVec b) { return ZVec(_mm512_sub_ps(a.v, b.v)); }
  friend ZVec operator*(ZVec a, ZVec b) { return ZVec(_mm512_mul_ps(a.v, b.v)); }
  friend ZVec operator/(ZVec a, ZVec b) { return ZVec(_mm512_div_ps(a.v, b.v)); }
  friend ZVec operator-(ZVec a) {
    return ZVec(_mm512_castsi512_ps(
        _mm512_xor_si512(_mm512_castps_si512(a.v), _mm512_set1_epi32(int32_t(0x80000000u)))));
  }
  ZVec& operator+=(ZVec b) { v = _mm512_add_ps(v, b.v); return *this; }
  friend KMask operator<(ZVec a, ZVec b) { return KMask(_mm512_cmp_ps_mask(a.v, b.v, _CMP_LT_OQ)); }
  friend KMask operator<=(ZVec a, ZVec b) { return KMask(_mm512_cmp_ps_mask(a.v, b.v, _CMP_LE_OQ)); }
  friend KMask operator>(ZVec a, ZVec b) { return KMask(_mm512_cmp_ps_mask(a.v, b.v, _CMP_GT_OQ)); }
  friend KMask operator>=(ZVec a, ZVec b) { return KMask(_mm512_cmp_ps_mask(a.v, b.v, _CMP_GE_OQ)); }
  float operator[](int i) const {
    alignas(64) float t[16];
    _mm512_store_ps(t, v);
    return t[i];
  }
  void store(float* p) const { _mm512_storeu_ps(p, v); }
  static ZVec from_int(ZInt a) { return ZVec(_mm512_cvtepi32_ps(a.v)); }
  static ZVec loadu(const float* p) { return ZVec(_mm512_loadu_ps(p)); }
};

inline ZVec select(KMask m, ZVec a, ZVec b) { return ZVec(_mm512_mask_blend_ps(m.k, b.v, a.v)); }
inline ZInt select(KMask m, ZInt a, ZInt b) { return ZInt(_mm512_mask_blend_epi32(m.k, b.v, a.v)); }
inline ZVec maskz(KMask m, ZVec a) { return ZVec(_mm512_maskz_mov_ps(m.k, a.v)); }
inline ZVec fmadd(ZVec a, ZVec b, ZVec c) { return ZVec(_mm512_fmadd_ps(a.v, b.v, c.v)); }
// vmin / vmax return b when either lane is NaN (as the generic versions do).
inline ZVec vmin(ZVec a, ZVec b) { return ZVec(_mm512_min_ps(a.v, b.v)); }
inline ZVec vmax(ZVec a, ZVec b) { return ZVec(_mm512_max_ps(a.v, b.v)); }
// 1 / a: 14-bit estimate + one Newton step (about 1 ulp; vdivps is several times slower)
inline ZVec recip(ZVec a) {
  const __m512 r = _mm512_rcp14_ps(a.v);
  return ZVec(_mm512_mul_ps(r, _mm512_fnmadd_ps(a.v, r, _mm512_set1_ps(2.0f))));
}
inline float hsum(ZVec a) { return _mm512_reduce_add_ps(a.v); }
inline int64_t hmax(ZInt a) { return _mm512_reduce_max_epi32(a.v); }
inline ZInt trunc_int(ZVec a) { return ZInt(_mm512_cvttps_epi32(a.v)); }
inline ZVec permute(ZVec tab, ZInt idx) { return ZVec(_mm512_permutexvar_ps(idx.v, tab.v)); }
inline ZVec vsqrt(ZVec a) { return ZVec(_mm512_sqrt_ps(a.v)); }

// exp: Cephes polynomial on r = x - n ln2, then vscalefps multiplies by 2^n.
inline ZVec vexp(ZVec xx) {
  __m512 x = _mm512_max_ps(xx.v, _mm512_set1_ps(-87.3f));
  x = _mm512_min_ps(x, _mm512_set1_ps(88.0f));
  const __m512 n = _mm512_roundscale_ps(_mm512_mul_ps(x, _mm512_set1_ps(1.44269504088896341f)),
                                        _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  __m512 r = _mm512_fnmadd_ps(n, _mm512_set1_ps(0.693359375f), x);
  r = _mm512_fnmadd_ps(n, _mm512_set1_ps(-2.12194440e-4f), r);
  __m512 p = _mm512_set1_ps(1.9875691500e-4f);
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(1.3981999507e-3f));
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(8.3334519073e-3f));
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(4.1665795894e-2f));
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(1.6666665459e-1f));
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(5.0000001201e-1f));
  const __m512 y =
      _mm512_add_ps(_mm512_fmadd_ps(p, _mm512_mul_ps(r, r), r), _mm512_set1_ps(1.0f));
  return ZVec(_mm512_scalef_ps(y, n));
}

inline ZVec vlog1p(ZVec x) {
  GF g;
  std::memcpy(&g.v, &x.v, 64);
  g = vlog1p(g);
  ZVec r;
  std::memcpy(&r.v, &g.v, 64);
  return r;
}

struct ZT16 {
  __m512d lo, hi;
};
inline ZT16 t_one(ZVec) { return ZT16{_mm512_set1_pd(1.0), _mm512_set1_pd(1.0)}; }
inline KMask t_step(const ZT16& T, ZVec al, ZT16& Tn, double tmin) {
  const __m512d alo = _mm512_cvtps_pd(_mm512_castps512_ps256(al.v));
  const __m512d ahi = _mm512_cvtps_pd(
      _mm256_castpd_ps(_mm512_extractf64x4_pd(_mm512_castps_pd(al.v), 1)));
  Tn.lo = _mm512_fnmadd_pd(T.lo, alo, T.lo);  // T (1 - alpha)
  Tn.hi = _mm512_fnmadd_pd(T.hi, ahi, T.hi);
  const __m512d tm = _mm512_set1_pd(tmin);
  const __mmask8 klo = _mm512_cmp_pd_mask(Tn.lo, tm, _CMP_LT_OQ);
  const __mmask8 khi = _mm512_cmp_pd_mask(Tn.hi, tm, _CMP_LT_OQ);
  return KMask(__mmask16(klo | (unsigned(khi) << 8)));
}
inline void t_select(KMask m, ZT16& T, const ZT16& Tn) {
  T.lo = _mm512_mask_mov_pd(T.lo, __mmask8(m.k & 0xFF), Tn.lo);
  T.hi = _mm512_mask_mov_pd(T.hi, __mmask8(m.k >> 8), Tn.hi);
}
inline ZVec t_value(const ZT16& T) {
  const __m256 lo = _mm512_cvtpd_ps(T.lo), hi = _mm512_cvtpd_ps(T.hi);
  return ZVec(_mm512_castpd_ps(_mm512_insertf64x4(_mm512_castps_pd(_mm512_castps256_ps512(lo)),
                                                  _mm256_castps_pd(hi), 1)));
}
inline double t_lane(const ZT16& T, int l) {
  alignas(64) double t[16];
  _mm512_store_pd(t, T.lo);
  _mm512_store_pd(t + 8, T.hi);
  return t[l];
}
#endif

// ============================================================================================
template <typename S>
struct SimdOf;
template <>
struct SimdOf<float> {
#if defined(__AVX512F__)
  using V = ZVec;
  using T = ZT16;
#else
  using V = GF;
  using T = GT16;
#endif
  using M = V::Mask;
  using I = V::Int;
  using IS = int32_t;
};
template <>
struct SimdOf<double> {
  using V = GD;
  using T = GD;
  using M = V::Mask;
  using I = V::Int;
  using IS = int64_t;
};

}  // namespace simd
}  // namespace splatk
