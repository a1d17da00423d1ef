// A small MLP (linear layers, leaky ReLU between them) evaluated row by row in bf16 with
// AVX-512 BF16 dot products (vdpbf16ps), for the learned kernel's Phi_proj in renders without
// gradients. It computes what torch's CPU autocast computes for nn.Linear stacks: inputs and
// weights and biases rounded to bf16, products accumulated in fp32, each layer's output rounded
// to bf16. Only the order of the fp32 sums, and the leaky ReLU applied before that rounding
// rather than after it, differ.
//
// Why by hand: torch runs each layer as its own GEMM, with the leaky ReLU and the dtype casts
// as separate passes over [M, 64] tensors; at 96k visible primitives that took ~7 ms per view
// on 2 cores, more than half of it in the casts and activations. Here a few primitives'
// activations stay in L1 and registers between layers, and the weights (~20 KB) stay in L1.
//
// Layout: for output block ob (16 outputs, one zmm of fp32 accumulators) and input pair kp,
// the packed weights hold 32 bf16: lane j's pair (W[16 ob + j][2 kp], W[16 ob + j][2 kp + 1]).
// vdpbf16ps(acc, broadcast(x[2 kp], x[2 kp + 1]), packed) then adds both products to lane j.
#pragma once

#include <cstdint>
#include <cstring>
#include <vector>

#if defined(__AVX512F__) && defined(__AVX512BF16__) && defined(__AVX512VL__)
#include <immintrin.h>
#define SPLATK_HAS_BF16_MLP 1
#else
#define SPLATK_HAS_BF16_MLP 0
#endif

namespace splatk {

// fp32 -> bf16 bits, round to nearest even (what vcvtneps2bf16 and torch's casts do)
inline uint16_t bf16_bits(float f) {
  uint32_t u;
  std::memcpy(&u, &f, 4);
  if ((u & 0x7fffffffu) > 0x7f800000u) return uint16_t((u >> 16) | 0x40u);  // quiet NaN
  u += 0x7fffu + ((u >> 16) & 1u);
  return uint16_t(u >> 16);
}

inline float bf16_round(float f) {
  const uint32_t u = uint32_t(bf16_bits(f)) << 16;
  float r;
  std::memcpy(&r, &u, 4);
  return r;
}

// One linear layer, packed as above; outputs padded to whole blocks of 16 (zero weights and
// bias, so padded outputs are exactly 0 and feed zeros into the next layer).
struct PackedLinear {
  int din = 0, dout = 0, pairs = 0, blocks = 0;
  std::vector<uint16_t> w;  // [blocks][pairs][16][2]
  std::vector<float> b;     // [blocks * 16]

  PackedLinear(const float* weight, const float* bias, int din_, int dout_)
      : din(din_), dout(dout_), pairs((din_ + 1) / 2), blocks((dout_ + 15) / 16),
        w(size_t(blocks) * pairs * 32, 0), b(size_t(blocks) * 16, 0.0f) {
    for (int o = 0; o < dout; ++o) {
      b[o] = bf16_round(bias[o]);
      const int ob = o / 16, lane = o % 16;
      for (int k = 0; k < din; ++k)
        w[((size_t(ob) * pairs + k / 2) * 16 + lane) * 2 + (k % 2)] = bf16_bits(weight[o * din + k]);
    }
  }
};

#if SPLATK_HAS_BF16_MLP
constexpr int kMlpRows = 8;  // rows (primitives) sharing each load of a weight vector
constexpr int kMlpGroup = 16 / kMlpRows;  // output blocks per pass: kMlpRows x kMlpGroup accumulators
// linear_rows dispatches a pass of 1 or kMlpGroup blocks (a layer's last pass may be short)
static_assert(kMlpGroup == 2, "linear_rows handles passes of 1 or 2 output blocks");

// Where a layer's input rows are: bf16 pairs, row r's pair kp at in[r * row + kp * pair].
struct PairRows {
  const uint32_t* in;
  int row, pair;
};

// acc[r][j] = bias + W[16 (ob0 + j) .. +16] . in[r] for NB output blocks and kMlpRows rows.
template <int NB>
inline void linear_blocks(const PackedLinear& L, int ob0, PairRows x,
                          __m512 out[kMlpRows][kMlpGroup]) {
  // local accumulators: ``out`` may alias the (may_alias) vector loads below, which would make
  // the compiler keep it in memory
  __m512 acc[kMlpRows][NB];
  for (int r = 0; r < kMlpRows; ++r)
    for (int j = 0; j < NB; ++j) acc[r][j] = _mm512_loadu_ps(&L.b[(ob0 + j) * 16]);
  const uint16_t* wk = &L.w[size_t(ob0) * L.pairs * 32];
  for (int kp = 0; kp < L.pairs; ++kp, wk += 32) {
    __m512bh w[NB];
    for (int j = 0; j < NB; ++j) w[j] = (__m512bh)_mm512_loadu_si512(wk + size_t(j) * L.pairs * 32);
    for (int r = 0; r < kMlpRows; ++r) {
      const __m512bh xr = (__m512bh)_mm512_set1_epi32(int(x.in[r * x.row + kp * x.pair]));
      for (int j = 0; j < NB; ++j) acc[r][j] = _mm512_dpbf16_ps(acc[r][j], xr, w[j]);
    }
  }
  for (int r = 0; r < kMlpRows; ++r)
    for (int j = 0; j < NB; ++j) out[r][j] = acc[r][j];
}

// One layer for kMlpRows rows: ``x`` -> ``out`` bf16 pairs (after the leaky ReLU, when
// ``activate``) or fp32 values ``out_f`` (the last layer, rounded to bf16 like autocast's
// output), each output row ``stride`` uint32 / floats apart.
inline void linear_rows(const PackedLinear& L, PairRows x, int stride, bool activate,
                        float slope, uint32_t* out, float* out_f) {
  const __m512 vs = _mm512_set1_ps(slope);
  for (int ob0 = 0; ob0 < L.blocks; ob0 += kMlpGroup) {
    const int nb = L.blocks - ob0 < kMlpGroup ? L.blocks - ob0 : kMlpGroup;
    __m512 acc[kMlpRows][kMlpGroup];
    if (nb == 1) linear_blocks<1>(L, ob0, x, acc);
    else linear_blocks<kMlpGroup>(L, ob0, x, acc);
    for (int r = 0; r < kMlpRows; ++r)
      for (int j = 0; j < nb; ++j) {
        __m512 v = acc[r][j];
        if (activate) v = _mm512_max_ps(v, _mm512_mul_ps(v, vs));  // leaky ReLU, 0 <= slope < 1
        const __m256bh h = _mm512_cvtneps_pbh(v);
        if (out) {
          _mm256_storeu_si256((__m256i*)(out + r * stride + (ob0 + j) * 8), (__m256i)h);
        } else {
          // back to fp32 from the bf16 bits: the value autocast hands on
          const __m512i wide = _mm512_slli_epi32(_mm512_cvtepu16_epi32((__m256i)h), 16);
          _mm512_storeu_ps(out_f + r * stride + (ob0 + j) * 16, _mm512_castsi512_ps(wide));
        }
      }
  }
}
#endif

}  // namespace splatk
