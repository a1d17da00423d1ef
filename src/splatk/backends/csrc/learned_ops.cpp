// The learned kernel's inference ops (no gradients): input encoding, Phi_dec at the table radii
// and the whole profile; splatk/kernels/learned.py is their torch reference and
// tests/backends/test_fused_ops.py checks them against it.
#include "fused_common.h"
#include "bf16_mlp.h"
#include "simd.h"

namespace splatk {
namespace {

// ------------------------------------------------------------------------------------------
// The learned kernel's per-primitive work around Phi_proj, for renders without gradients
// (kernels/learned.py is the specification): the input encoding, Phi_dec at the table radii,
// and learned_profile, which does both around Phi_proj itself (bf16, bf16_mlp.h) in one pass.
// ------------------------------------------------------------------------------------------
struct EncodeSpec {
  bool use_mu, use_s, use_R;
  double dist_scale, angle_shift, angle_scale;
  int64_t width(int64_t L) const { return L + (use_mu ? 4 : 0) + (use_s ? 3 : 0) + (use_R ? 9 : 0); }
};

// Phi_proj's input row of primitive n: [z | mu_cam / rho, log(rho) / dist_scale | (log(s) -
// log(rho) + shift) / angle_scale | R_cam row-major], each group present when asked for.
template <typename S>
inline void encode_row(const S* z, int64_t L, const S* m, const S* sc, const S* rot,
                       const EncodeSpec& e, S* row) {
  for (int64_t l = 0; l < L; ++l) *row++ = z[l];
  const S rho = std::max(std::sqrt(m[0] * m[0] + m[1] * m[1] + m[2] * m[2]), S(1e-12));
  const S log_rho = std::log(rho);
  if (e.use_mu) {
    for (int k = 0; k < 3; ++k) *row++ = m[k] / rho;
    *row++ = log_rho * S(1.0 / e.dist_scale);
  }
  if (e.use_s)
    for (int k = 0; k < 3; ++k)
      *row++ = (std::log(sc[k]) - log_rho + S(e.angle_shift)) * S(1.0 / e.angle_scale);
  if (e.use_R)
    for (int k = 0; k < 9; ++k) *row++ = rot[k];
}

// Phi_dec's weights: w1 [W, 1 + L] (column 0 multiplies r^2), w2 [V, W], w3 [V], b3 scalar.
template <typename S>
struct DecoderWeights {
  const S *w1, *b1, *w2, *b2, *w3;
  S b3;
  int64_t L, W, V;
};

// Phi_dec at P radii of one primitive: d[p] = sigmoid(w3 . h2 + b3), h2 = lrelu(W2 h1 + b2),
// h1 = lrelu(W1[:, 1:] z2d + b1 + r2[p] W1[:, 0]) (the same order of operations as phi_dec).
template <typename S>
inline void decode_row(const S* z, const DecoderWeights<S>& d, const S* r2, int64_t P, S slope,
                       S* out) {
  auto lrelu = [slope](S v) { return v >= S(0) ? v : v * slope; };
  S a[64], h1[64];
  for (int64_t w = 0; w < d.W; ++w) {
    S acc = S(0);
    for (int64_t l = 0; l < d.L; ++l) acc += z[l] * d.w1[w * (d.L + 1) + 1 + l];
    a[w] = acc + d.b1[w];
  }
  for (int64_t p = 0; p < P; ++p) {
    for (int64_t w = 0; w < d.W; ++w) h1[w] = lrelu(a[w] + r2[p] * d.w1[w * (d.L + 1)]);
    S o = S(0);
    for (int64_t v = 0; v < d.V; ++v) {
      S acc = S(0);
      for (int64_t w = 0; w < d.W; ++w) acc += h1[w] * d.w2[v * d.W + w];
      o += lrelu(acc + d.b2[v]) * d.w3[v];
    }
    out[p] = S(1) / (S(1) + std::exp(-(o + d.b3)));
  }
}

template <typename S>
DecoderWeights<S> decoder_weights(int64_t L, const at::Tensor& w1, const at::Tensor& b1,
                                  const at::Tensor& w2, const at::Tensor& b2, const at::Tensor& w3,
                                  const at::Tensor& b3) {
  return {w1.data_ptr<S>(), b1.data_ptr<S>(), w2.data_ptr<S>(), b2.data_ptr<S>(), w3.data_ptr<S>(),
          b3.data_ptr<S>()[0], L, w1.size(0), w2.size(0)};
}

void check_decoder(const char* op, int64_t L, const at::Tensor& w1, const at::Tensor& b1,
                   const at::Tensor& w2, const at::Tensor& b2, const at::Tensor& w3,
                   const at::Tensor& b3, const at::Tensor& radii2) {
  const int64_t W = w1.size(0), V = w2.size(0);
  TORCH_CHECK(w1.dim() == 2 && w1.size(1) == L + 1 && b1.numel() == W && w2.dim() == 2 &&
                  w2.size(1) == W && b2.numel() == V && w3.numel() == V && b3.numel() == 1 &&
                  radii2.dim() == 1,
              op, ": Phi_dec's weight shapes do not match z2d [M, ", L, "]");
  TORCH_CHECK(W <= 64 && V <= 64, op, ": Phi_dec hidden width above 64");
}

void check_view(const char* op, const at::Tensor& means_cam, const at::Tensor& scales,
                const at::Tensor& rotmats_cam, at::Tensor& z) {
  check_float_inputs(op, {{&means_cam, "means_cam"}, {&scales, "scales"}, {&rotmats_cam, "rotmats_cam"}});
  const int64_t M = means_cam.size(0);
  TORCH_CHECK(means_cam.dim() == 2 && means_cam.size(1) == 3 && scales.sizes() == means_cam.sizes() &&
                  rotmats_cam.numel() == 9 * M,
              op, ": means_cam, scales [M, 3] and rotmats_cam [M, 3, 3]");
  if (z.defined()) {
    check_float_inputs(op, {{&means_cam, "means_cam"}, {&z, "z"}});
    TORCH_CHECK(z.dim() == 2 && z.size(0) == M, op, ": z must be [M, L]");
  }
}

template <typename S>
void learned_encode_t(const at::Tensor& z, const at::Tensor& mu, const at::Tensor& sc,
                      const at::Tensor& rot, const EncodeSpec& e, at::Tensor& x, int64_t threads) {
  const int64_t M = mu.size(0), D = x.size(1);
  const int64_t L = z.defined() ? z.size(1) : 0;
  const S* pz = z.defined() ? z.data_ptr<S>() : nullptr;
  const S *pm = mu.data_ptr<S>(), *ps = sc.data_ptr<S>(), *pr = rot.data_ptr<S>();
  S* px = x.data_ptr<S>();
  pybind11::gil_scoped_release nogil;
#pragma omp parallel for num_threads(nthreads(threads, M, 4096)) schedule(static)
  for (int64_t n = 0; n < M; ++n)
    encode_row(pz + n * L, L, pm + 3 * n, ps + 3 * n, pr + 9 * n, e, px + n * D);
}

at::Tensor learned_encode(const std::optional<at::Tensor>& z, const at::Tensor& means_cam,
                          const at::Tensor& scales, const at::Tensor& rotmats_cam, bool use_mu,
                          bool use_s, bool use_R, double dist_scale, double angle_shift,
                          double angle_scale, int64_t threads) {
  at::Tensor zz = z.has_value() ? *z : at::Tensor();
  check_view("learned_encode", means_cam, scales, rotmats_cam, zz);
  const EncodeSpec e{use_mu, use_s, use_R, dist_scale, angle_shift, angle_scale};
  const int64_t D = e.width(zz.defined() ? zz.size(1) : 0);
  TORCH_CHECK(D > 0, "learned_encode: no inputs");
  at::Tensor x = at::empty({means_cam.size(0), D}, means_cam.options());
  if (means_cam.scalar_type() == at::kDouble)
    learned_encode_t<double>(zz, means_cam, scales, rotmats_cam, e, x, threads);
  else
    learned_encode_t<float>(zz, means_cam, scales, rotmats_cam, e, x, threads);
  return x;
}

template <typename S>
void learned_decode_t(const at::Tensor& z2d, const DecoderWeights<S>& d, const at::Tensor& r2,
                      double slope, at::Tensor& out, int64_t threads) {
  const int64_t M = z2d.size(0), P = r2.size(0);
  const S *pz = z2d.data_ptr<S>(), *pr = r2.data_ptr<S>();
  S* po = out.data_ptr<S>();
  pybind11::gil_scoped_release nogil;
#pragma omp parallel for num_threads(nthreads(threads, M, 4096)) schedule(static)
  for (int64_t n = 0; n < M; ++n) decode_row(pz + n * d.L, d, pr, P, S(slope), po + n * P);
}

at::Tensor learned_decode(const at::Tensor& z2d, const at::Tensor& w1, const at::Tensor& b1,
                          const at::Tensor& w2, const at::Tensor& b2, const at::Tensor& w3,
                          const at::Tensor& b3, const at::Tensor& radii2, double slope,
                          int64_t threads) {
  check_float_inputs("learned_decode", {{&z2d, "z2d"}, {&w1, "w1"}, {&b1, "b1"}, {&w2, "w2"},
                                        {&b2, "b2"}, {&w3, "w3"}, {&b3, "b3"}, {&radii2, "radii2"}});
  TORCH_CHECK(z2d.dim() == 2, "learned_decode: z2d must be [M, L]");
  check_decoder("learned_decode", z2d.size(1), w1, b1, w2, b2, w3, b3, radii2);
  at::Tensor out = at::empty({z2d.size(0), radii2.size(0)}, z2d.options());
  if (z2d.scalar_type() == at::kDouble)
    learned_decode_t<double>(z2d, decoder_weights<double>(z2d.size(1), w1, b1, w2, b2, w3, b3), radii2, slope, out, threads);
  else
    learned_decode_t<float>(z2d, decoder_weights<float>(z2d.size(1), w1, b1, w2, b2, w3, b3), radii2, slope, out, threads);
  return out;
}

bool has_bf16_mlp() { return SPLATK_HAS_BF16_MLP; }

#if SPLATK_HAS_BF16_MLP
constexpr int kLanes = 16;

// encode_row for 16 primitives n0.. (one per lane; a short block repeats its last row),
// straight into Phi_proj's first-layer input: bf16 pairs laid out [pair][lane]. The logs and
// square roots run across lanes (simd.h's Cephes log, ~1 ulp from std::log).
inline void encode_lanes(const float* z, int64_t L, const float* mu, const float* sc,
                         const float* rot, const EncodeSpec& e, int64_t n0, int rows,
                         float (*x)[kLanes], uint32_t* pairs) {
  using simd::vf;
  int64_t n[kLanes];
  for (int r = 0; r < kLanes; ++r) n[r] = n0 + std::min(r, rows - 1);
  int64_t d = 0;
  for (int64_t l = 0; l < L; ++l, ++d)
    for (int r = 0; r < kLanes; ++r) x[d][r] = z[n[r] * L + l];
  if (e.use_mu || e.use_s) {
    alignas(64) float m[3][kLanes];
    for (int k = 0; k < 3; ++k)
      for (int r = 0; r < kLanes; ++r) m[k][r] = mu[3 * n[r] + k];
    vf m0, m1, m2;
    std::memcpy(&m0, m[0], 64), std::memcpy(&m1, m[1], 64), std::memcpy(&m2, m[2], 64);
    vf rho = m0 * m0 + m1 * m1 + m2 * m2;
    __m512 rv;
    std::memcpy(&rv, &rho, 64);
    rv = _mm512_max_ps(_mm512_sqrt_ps(rv), _mm512_set1_ps(1e-12f));
    std::memcpy(&rho, &rv, 64);
    const vf log_rho = simd::vlog_raw(rho);
    if (e.use_mu) {
      const vf q0 = m0 / rho, q1 = m1 / rho, q2 = m2 / rho, ld = log_rho * float(1.0 / e.dist_scale);
      std::memcpy(x[d++], &q0, 64), std::memcpy(x[d++], &q1, 64), std::memcpy(x[d++], &q2, 64);
      std::memcpy(x[d++], &ld, 64);
    }
    if (e.use_s)
      for (int k = 0; k < 3; ++k, ++d) {
        alignas(64) float s[kLanes];
        for (int r = 0; r < kLanes; ++r) s[r] = sc[3 * n[r] + k];
        vf sv;
        std::memcpy(&sv, s, 64);
        const vf a = (simd::vlog_raw(sv) - log_rho + float(e.angle_shift)) * float(1.0 / e.angle_scale);
        std::memcpy(x[d], &a, 64);
      }
  }
  if (e.use_R)
    for (int k = 0; k < 9; ++k, ++d)
      for (int r = 0; r < kLanes; ++r) x[d][r] = rot[9 * n[r] + k];
  for (int r = 0; r < kLanes; ++r) x[d][r] = 0.0f;  // pads an odd width to whole pairs
  for (int64_t kp = 0; kp < (d + 1) / 2; ++kp) {
    const __m512i lo = _mm512_cvtepu16_epi32((__m256i)_mm512_cvtneps_pbh(_mm512_loadu_ps(x[2 * kp])));
    const __m512i hi = _mm512_cvtepu16_epi32((__m256i)_mm512_cvtneps_pbh(_mm512_loadu_ps(x[2 * kp + 1])));
    _mm512_storeu_si512(pairs + kp * kLanes, _mm512_or_si512(lo, _mm512_slli_epi32(hi, 16)));
  }
}

// decode_row for 16 primitives at once, one per lane: ``rows`` (<= 16) rows of z2d, ``stride``
// floats apart -> out [rows, P]. Phi_dec is a few dozen flops per radius, so across lanes is
// the only way to keep the vector units busy (and exp is the vector one of simd.h).
inline void decode_lanes(const float* z2d, int stride, int rows, const DecoderWeights<float>& d,
                         const float* r2, int64_t P, float slope, float* out) {
  const __m512 vs = _mm512_set1_ps(slope), one = _mm512_set1_ps(1.0f);
  auto lrelu = [vs](__m512 v) { return _mm512_max_ps(v, _mm512_mul_ps(v, vs)); };
  alignas(64) float zt[kLanes];
  __m512 a[64], h1[64];
  for (int64_t w = 0; w < d.W; ++w) a[w] = _mm512_setzero_ps();
  for (int64_t l = 0; l < d.L; ++l) {
    for (int r = 0; r < kLanes; ++r) zt[r] = z2d[std::min(r, rows - 1) * stride + l];
    const __m512 zl = _mm512_load_ps(zt);
    for (int64_t w = 0; w < d.W; ++w)
      a[w] = _mm512_add_ps(a[w], _mm512_mul_ps(zl, _mm512_set1_ps(d.w1[w * (d.L + 1) + 1 + l])));
  }
  for (int64_t w = 0; w < d.W; ++w) a[w] = _mm512_add_ps(a[w], _mm512_set1_ps(d.b1[w]));
  alignas(64) float res[kLanes];
  for (int64_t p = 0; p < P; ++p) {
    const __m512 rp = _mm512_set1_ps(r2[p]);
    for (int64_t w = 0; w < d.W; ++w)
      h1[w] = lrelu(_mm512_add_ps(a[w], _mm512_mul_ps(rp, _mm512_set1_ps(d.w1[w * (d.L + 1)]))));
    __m512 o = _mm512_setzero_ps();
    for (int64_t v = 0; v < d.V; ++v) {
      __m512 acc = _mm512_setzero_ps();
      for (int64_t w = 0; w < d.W; ++w)
        acc = _mm512_add_ps(acc, _mm512_mul_ps(h1[w], _mm512_set1_ps(d.w2[v * d.W + w])));
      o = _mm512_add_ps(o, _mm512_mul_ps(lrelu(_mm512_add_ps(acc, _mm512_set1_ps(d.b2[v]))),
                                         _mm512_set1_ps(d.w3[v])));
    }
    const __m512 e = simd::vexp(simd::ZVec(_mm512_sub_ps(_mm512_setzero_ps(), _mm512_add_ps(o, _mm512_set1_ps(d.b3))))).v;
    _mm512_store_ps(res, _mm512_div_ps(one, _mm512_add_ps(one, e)));
    for (int r = 0; r < rows; ++r) out[r * P + p] = res[r];
  }
}
#endif

// The whole no-gradient profile of the learned kernel: encode -> Phi_proj (bf16, the layers
// ``proj_w`` / ``proj_b`` with leaky ReLU between them) -> Phi_dec at ``radii2``: [M, P].
// Rows go kMlpRows at a time so each weight vector loaded serves several primitives.
at::Tensor learned_profile(const std::optional<at::Tensor>& z, const at::Tensor& means_cam,
                           const at::Tensor& scales, const at::Tensor& rotmats_cam, bool use_mu,
                           bool use_s, bool use_R, double dist_scale, double angle_shift,
                           double angle_scale, const std::vector<at::Tensor>& proj_w,
                           const std::vector<at::Tensor>& proj_b, const at::Tensor& w1,
                           const at::Tensor& b1, const at::Tensor& w2, const at::Tensor& b2,
                           const at::Tensor& w3, const at::Tensor& b3, const at::Tensor& radii2,
                           double slope, int64_t threads) {
#if SPLATK_HAS_BF16_MLP
  at::Tensor zz = z.has_value() ? *z : at::Tensor();
  check_view("learned_profile", means_cam, scales, rotmats_cam, zz);
  TORCH_CHECK(means_cam.scalar_type() == at::kFloat, "learned_profile: float32 only");
  const EncodeSpec e{use_mu, use_s, use_R, dist_scale, angle_shift, angle_scale};
  const int64_t M = means_cam.size(0), L = zz.defined() ? zz.size(1) : 0, D = e.width(L);
  TORCH_CHECK(!proj_w.empty() && proj_w.size() == proj_b.size(), "learned_profile: Phi_proj layers");
  constexpr int kMaxWidth = 256;  // activations per row, in the stack buffers below
  std::vector<PackedLinear> layers;
  int64_t din = D;
  for (size_t i = 0; i < proj_w.size(); ++i) {
    const at::Tensor &w = proj_w[i], &b = proj_b[i];
    check_float_inputs("learned_profile", {{&means_cam, "means_cam"}, {&w, "Phi_proj weight"}, {&b, "Phi_proj bias"}});
    TORCH_CHECK(w.dim() == 2 && w.size(1) == din && b.numel() == w.size(0) && w.size(0) <= kMaxWidth &&
                    din <= kMaxWidth,
                "learned_profile: Phi_proj layer ", i, " is [", w.size(0), ", ", w.size(1),
                "], expected [<= 256, ", din, "]");
    layers.emplace_back(w.data_ptr<float>(), b.data_ptr<float>(), int(din), int(w.size(0)));
    din = w.size(0);
  }
  check_float_inputs("learned_profile", {{&means_cam, "means_cam"}, {&w1, "w1"}, {&b1, "b1"}, {&w2, "w2"},
                                         {&b2, "b2"}, {&w3, "w3"}, {&b3, "b3"}, {&radii2, "radii2"}});
  check_decoder("learned_profile", din, w1, b1, w2, b2, w3, b3, radii2);
  const DecoderWeights<float> dec = decoder_weights<float>(din, w1, b1, w2, b2, w3, b3);
  const int64_t P = radii2.size(0);
  at::Tensor out = at::empty({M, P}, means_cam.options());
  const float* pz = zz.defined() ? zz.data_ptr<float>() : nullptr;
  const float *pm = means_cam.data_ptr<float>(), *ps = scales.data_ptr<float>();
  const float *pr = rotmats_cam.data_ptr<float>(), *pr2 = radii2.data_ptr<float>();
  float* po = out.data_ptr<float>();
  const float sl = float(slope);
  const int64_t nblocks = (M + kLanes - 1) / kLanes;
  pybind11::gil_scoped_release nogil;
#pragma omp parallel for num_threads(nthreads(threads, M, 2048)) schedule(static)
  for (int64_t blk = 0; blk < nblocks; ++blk) {
    constexpr int stride = kMaxWidth;  // uint32 pairs / floats per row: room for any layer
    alignas(64) uint32_t first[kMaxWidth / 2 + 1][kLanes], buf_a[kMlpRows * stride], buf_b[kMlpRows * stride];
    alignas(64) float x[kMaxWidth + 1][kLanes], z2d[kLanes * stride];
    const int64_t n0 = blk * kLanes;
    const int rows = int(std::min<int64_t>(kLanes, M - n0));
    encode_lanes(pz, L, pm, ps, pr, e, n0, rows, x, first[0]);
    for (int r0 = 0; r0 < kLanes; r0 += kMlpRows) {
      PairRows in{first[0] + r0, 1, kLanes};
      uint32_t *cur = buf_a, *next = buf_b;
      for (size_t i = 0; i < layers.size(); ++i) {
        const bool last = i + 1 == layers.size();
        linear_rows(layers[i], in, stride, !last, sl, last ? nullptr : cur, last ? z2d + r0 * stride : nullptr);
        in = PairRows{cur, stride, 1};
        std::swap(cur, next);
      }
    }
    decode_lanes(z2d, stride, rows, dec, pr2, P, sl, po + n0 * P);
  }
  return out;
#else
  TORCH_CHECK(false, "learned_profile: this build has no AVX-512 BF16 (see has_bf16_mlp())");
#endif
}

}  // namespace

void register_learned_ops(pybind11::module_& m) {
  m.def("learned_encode", &learned_encode,
        "learned_encode(z?, means_cam, scales, rotmats_cam, use_mu, use_s, use_R, dist_scale, "
        "angle_shift, angle_scale, threads) -> x[M, D] (no gradients)");
  m.def("learned_decode", &learned_decode,
        "learned_decode(z2d, w1, b1, w2, b2, w3, b3, radii2, slope, threads) -> d[M, P] (no gradients)");
  m.def("has_bf16_mlp", &has_bf16_mlp, "whether learned_profile is built (AVX-512 BF16)");
  m.def("learned_profile", &learned_profile,
        "learned_profile(z?, means_cam, scales, rotmats_cam, use_mu, use_s, use_R, dist_scale, "
        "angle_shift, angle_scale, proj_w, proj_b, w1, b1, w2, b2, w3, b3, radii2, slope, threads) "
        "-> d[M, P] (Phi_proj in bf16; no gradients)");
}

}  // namespace splatk
