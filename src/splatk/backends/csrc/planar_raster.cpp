// Native CPU rasteriser for planar (2DGS-style surfel) primitives: the ``cpu`` path of
// splatk/backends/planar.py. Semantics are those of the dense torch reference
// ``splatk.backends.planar_torch.rasterize_planar`` (the specification):
//
//   * per pixel centre (x, y) = (i + 0.5, j + 0.5) and splat with homography M (rows M0, M1, M2):
//     h_u = -M0 + x M2, h_v = -M1 + y M2, (u', v', w') = h_u x h_v, (u, v) = (u'/w', v'/w') / 3
//     (2DGS Eq. 9-10; the / 3 makes the 3-sigma disk the unit disk);
//   * k(u, v): ``gaussian_surfel`` exp(-4.5 r2) or a per-primitive G x G ``grid`` (bilinear at
//     nodes linspace(-1, 1, G), indexed [v, u], uv clamped to [-1, 1]); both 0 when r2 > 1;
//   * alpha = min(0.999, o k), pairs with alpha < 1/255 skipped, front to back in the order the
//     caller gives (already sorted by camera depth, stable), a pixel ends before the splat whose
//     T (1 - alpha) would fall below 1e-4 (T kept in float64, as the reference's log-space T).
//
// The caller (planar_cpu.py) passes only splats wholly in front of the camera
// (planar_torch.planar_in_front) with the pixel box [x0, x1) x [y0, y1) of their projected
// 3-sigma disk (exact ellipse box plus 1e-3 px): tiles and pixels outside it are skipped.
//
// Forward: binning into 16x16 tiles (a serial counting pass in primitive order, so every tile
// list stays in depth order), then OpenMP over tiles, scalar code, pixels of a tile one by one.
// Backward: 3DGS style, back to front per pixel from T_final, T_i = T_{i+1} / (1 - alpha_i),
//   dL/dalpha_i = T_i (g . c_i) + (T_final (dL/dA - g . bg) - W) / (1 - alpha_i),
// W = sum over the blended splats behind i of (g . c_j) alpha_j T_j.
// Gradient reduction is deterministic: every (primitive, tile) pair owns one slot (written by
// the single thread that owns the tile), then each primitive sums its slots in tile order. No
// atomics: results are bitwise reproducible for any thread count.
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <omp.h>
#include <torch/csrc/utils/pybind.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace splatk {
namespace {

constexpr int kPTile = 16;
constexpr double kPAlphaMax = 0.999;
constexpr double kPAlphaMin = 1.0 / 255.0;
constexpr double kPTMin = 1e-4;
enum PlanarKind : int { kSurfel = 0, kGrid = 1 };

// The kernel value at one (pixel, splat) pair and what the backward pass needs of it.
template <typename S>
struct PairEval {
  S hu[3], hv[3], c[3];  // the two planes and their cross product
  S u, v, r2;            // normalised (u, v), r2 = u^2 + v^2
  S k;                   // kernel value
  // grid only: cell and fractions
  int64_t base;
  S fu, fv;
};

// Evaluates (u, v) and k; false when the pair contributes nothing (ray parallel to the plane,
// outside the unit disk).
template <typename S>
inline bool eval_pair(const S* M, S x, S y, int kind, const S* table, int G, PairEval<S>& e) {
  for (int i = 0; i < 3; ++i) {
    e.hu[i] = -M[i] + x * M[6 + i];
    e.hv[i] = -M[3 + i] + y * M[6 + i];
  }
  e.c[0] = e.hu[1] * e.hv[2] - e.hu[2] * e.hv[1];
  e.c[1] = e.hu[2] * e.hv[0] - e.hu[0] * e.hv[2];
  e.c[2] = e.hu[0] * e.hv[1] - e.hu[1] * e.hv[0];
  if (!(e.c[2] != S(0))) return false;
  e.u = e.c[0] / e.c[2] / S(3);
  e.v = e.c[1] / e.c[2] / S(3);
  e.r2 = e.u * e.u + e.v * e.v;
  if (!(e.r2 <= S(1))) return false;  // also drops NaN
  if (kind == kSurfel) {
    e.k = std::exp(S(-4.5) * e.r2);
  } else {
    // bilinear(): t = (clamp(uv) + 1) * 0.5 * (G - 1), i0 = clamp(floor(t), 0, G - 2)
    const S tu = (std::min(std::max(e.u, S(-1)), S(1)) + S(1)) * S(0.5) * S(G - 1);
    const S tv = (std::min(std::max(e.v, S(-1)), S(1)) + S(1)) * S(0.5) * S(G - 1);
    const S iu = std::min(std::max(std::floor(tu), S(0)), S(G - 2));
    const S iv = std::min(std::max(std::floor(tv), S(0)), S(G - 2));
    e.fu = tu - iu;
    e.fv = tv - iv;
    e.base = int64_t(iv) * G + int64_t(iu);
    const S* t = table + e.base;
    e.k = (t[0] * (S(1) - e.fu) + t[1] * e.fu) * (S(1) - e.fv) +
          (t[G] * (S(1) - e.fu) + t[G + 1] * e.fu) * e.fv;
  }
  return true;
}

// The pixel lies in the splat's box [x0, x1) x [y0, y1) (a cheap test before the ray-plane
// intersection: the box is conservative, so pixels outside it have r2 > 1 anyway; the forward
// and backward passes skip the same pairs).
inline bool in_box(const int32_t* r, int px, int py) {
  return px >= r[0] && px < r[1] && py >= r[2] && py < r[3];
}

struct Bins {
  int tiles_x = 0, tiles_y = 0;
  at::Tensor tile_offsets;  // int64 [tiles + 1]
  at::Tensor entries;       // int32 [E] primitive of each tile entry (depth order per tile)
  at::Tensor slots;         // int64 [E] gradient slot of each entry (primitive-major)
  at::Tensor prim_offsets;  // int64 [N + 1] first slot of each primitive
};

Bins bin_tiles(const at::Tensor& bbox, int64_t width, int64_t height) {
  Bins b;
  const int64_t n = bbox.size(0);
  b.tiles_x = int((width + kPTile - 1) / kPTile);
  b.tiles_y = int((height + kPTile - 1) / kPTile);
  const int64_t ntiles = int64_t(b.tiles_x) * b.tiles_y;
  const int32_t* bb = bbox.data_ptr<int32_t>();
  auto i64 = at::TensorOptions().dtype(at::kLong);
  b.prim_offsets = at::empty({n + 1}, i64);
  b.tile_offsets = at::zeros({ntiles + 1}, i64);
  int64_t* po = b.prim_offsets.data_ptr<int64_t>();
  int64_t* to = b.tile_offsets.data_ptr<int64_t>();
  auto tile_range = [&](int64_t p, int& tx0, int& tx1, int& ty0, int& ty1) {
    const int32_t* r = bb + 4 * p;  // x0, x1, y0, y1 (clipped to the image)
    if (r[1] <= r[0] || r[3] <= r[2]) {
      tx0 = tx1 = ty0 = ty1 = 0;
      return;
    }
    tx0 = r[0] / kPTile, tx1 = (r[1] - 1) / kPTile + 1;
    ty0 = r[2] / kPTile, ty1 = (r[3] - 1) / kPTile + 1;
  };
  po[0] = 0;
  for (int64_t p = 0; p < n; ++p) {
    int tx0, tx1, ty0, ty1;
    tile_range(p, tx0, tx1, ty0, ty1);
    po[p + 1] = po[p] + int64_t(tx1 - tx0) * (ty1 - ty0);
    for (int ty = ty0; ty < ty1; ++ty)
      for (int tx = tx0; tx < tx1; ++tx) to[int64_t(ty) * b.tiles_x + tx + 1] += 1;
  }
  for (int64_t t = 0; t < ntiles; ++t) to[t + 1] += to[t];
  const int64_t E = to[ntiles];
  b.entries = at::empty({E}, at::TensorOptions().dtype(at::kInt));
  b.slots = at::empty({E}, i64);
  int32_t* ent = b.entries.data_ptr<int32_t>();
  int64_t* sl = b.slots.data_ptr<int64_t>();
  std::vector<int64_t> fill(to, to + ntiles);
  for (int64_t p = 0; p < n; ++p) {
    int tx0, tx1, ty0, ty1;
    tile_range(p, tx0, tx1, ty0, ty1);
    int64_t slot = po[p];
    for (int ty = ty0; ty < ty1; ++ty)
      for (int tx = tx0; tx < tx1; ++tx, ++slot) {
        const int64_t pos = fill[int64_t(ty) * b.tiles_x + tx]++;
        ent[pos] = int32_t(p);
        sl[pos] = slot;
      }
  }
  return b;
}

int planar_threads(int64_t requested) {
  return requested > 0 ? int(requested) : omp_get_max_threads();
}

template <typename S>
std::vector<at::Tensor> planar_forward_t(const at::Tensor& M, const at::Tensor& bbox,
                                         const at::Tensor& opac, const at::Tensor& colors,
                                         const at::Tensor& table, int64_t kind, int64_t width,
                                         int64_t height, const at::Tensor& background,
                                         int64_t threads) {
  const int64_t C = colors.size(1);
  const int G = kind == kGrid ? int(table.size(1)) : 0;
  Bins b = bin_tiles(bbox, width, height);
  auto opt = colors.options();
  at::Tensor img = at::empty({height, width, C}, opt);
  at::Tensor alpha = at::empty({height, width, 1}, opt);
  at::Tensor T_final = at::empty({height, width}, opt);
  at::Tensor last = at::empty({height, width}, at::TensorOptions().dtype(at::kInt));
  const S* Mp = M.data_ptr<S>();
  const S* op = opac.data_ptr<S>();
  const S* col = colors.data_ptr<S>();
  const S* tab = kind == kGrid ? table.data_ptr<S>() : nullptr;
  const S* bg = background.data_ptr<S>();
  S* im = img.data_ptr<S>();
  S* al = alpha.data_ptr<S>();
  S* tf = T_final.data_ptr<S>();
  int32_t* la = last.data_ptr<int32_t>();
  const int64_t* to = b.tile_offsets.data_ptr<int64_t>();
  const int32_t* ent = b.entries.data_ptr<int32_t>();
  const int32_t* bb = bbox.data_ptr<int32_t>();
  const int64_t ntiles = int64_t(b.tiles_x) * b.tiles_y;
  const int tiles_x = b.tiles_x;
  {
    pybind11::gil_scoped_release nogil;
#pragma omp parallel for schedule(dynamic, 1) num_threads(planar_threads(threads))
    for (int64_t t = 0; t < ntiles; ++t) {
      const int tx = int(t % tiles_x), ty = int(t / tiles_x);
      const int64_t e0 = to[t], e1 = to[t + 1];
      std::vector<S> acc(C);
      PairEval<S> e;
      for (int py = ty * kPTile; py < std::min<int64_t>(height, (ty + 1) * kPTile); ++py)
        for (int px = tx * kPTile; px < std::min<int64_t>(width, (tx + 1) * kPTile); ++px) {
          const S x = S(px) + S(0.5), y = S(py) + S(0.5);
          std::fill(acc.begin(), acc.end(), S(0));
          double T = 1.0;
          int32_t n_done = 0;
          for (int64_t i = e0; i < e1; ++i) {
            const int64_t p = ent[i];
            if (!in_box(bb + 4 * p, px, py)) continue;
            if (!eval_pair<S>(Mp + 9 * p, x, y, int(kind), tab ? tab + p * G * G : nullptr, G, e))
              continue;
            const S a = std::min(op[p] * e.k, S(kPAlphaMax));
            if (a < S(kPAlphaMin)) continue;
            const double Tn = T * (1.0 - double(a));
            if (Tn < kPTMin) break;
            const S w = S(double(a) * T);
            for (int64_t c = 0; c < C; ++c) acc[c] += w * col[p * C + c];
            T = Tn;
            n_done = int32_t(i - e0 + 1);
          }
          const int64_t pix = int64_t(py) * width + px;
          for (int64_t c = 0; c < C; ++c) im[pix * C + c] = acc[c] + S(T) * bg[c];
          al[pix] = S(1) - S(T);
          tf[pix] = S(T);
          la[pix] = n_done;
        }
    }
  }
  return {img, alpha, T_final, last, b.tile_offsets, b.entries, b.slots, b.prim_offsets};
}

template <typename S>
std::vector<at::Tensor> planar_backward_t(const at::Tensor& M, const at::Tensor& bbox,
                                          const at::Tensor& opac,
                                          const at::Tensor& colors, const at::Tensor& table,
                                          int64_t kind, int64_t width, int64_t height,
                                          const at::Tensor& background,
                                          const std::vector<at::Tensor>& state,
                                          const at::Tensor& v_img, const at::Tensor& v_alpha,
                                          int64_t threads) {
  const int64_t n = M.size(0), C = colors.size(1);
  const int G = kind == kGrid ? int(table.size(1)) : 0;
  const int64_t GG = int64_t(G) * G;
  const at::Tensor &T_final = state[0], &last = state[1], &tile_offsets = state[2],
                   &entries = state[3], &slots = state[4], &prim_offsets = state[5];
  const int64_t E = entries.numel();
  // One gradient record per (primitive, tile) slot: M (9), opacity (1), colours (C), table (GG).
  const int64_t R = 10 + C + GG;
  auto opt = colors.options();
  at::Tensor slot_grads = at::zeros({E, R}, opt);
  const int tiles_x = int((width + kPTile - 1) / kPTile);
  const int tiles_y = int((height + kPTile - 1) / kPTile);
  const int64_t ntiles = int64_t(tiles_x) * tiles_y;
  const S* Mp = M.data_ptr<S>();
  const S* op = opac.data_ptr<S>();
  const S* col = colors.data_ptr<S>();
  const S* tab = kind == kGrid ? table.data_ptr<S>() : nullptr;
  const S* bg = background.data_ptr<S>();
  const S* tf = T_final.data_ptr<S>();
  const int32_t* la = last.data_ptr<int32_t>();
  const int64_t* to = tile_offsets.data_ptr<int64_t>();
  const int32_t* ent = entries.data_ptr<int32_t>();
  const int32_t* bb = bbox.data_ptr<int32_t>();
  const int64_t* sl = slots.data_ptr<int64_t>();
  const int64_t* po = prim_offsets.data_ptr<int64_t>();
  const S* gi = v_img.data_ptr<S>();
  const S* ga = v_alpha.data_ptr<S>();
  S* sg = slot_grads.data_ptr<S>();
  at::Tensor v_M = at::zeros({n, 9}, opt), v_op = at::zeros({n}, opt),
             v_col = at::zeros({n, C}, opt), v_tab = at::zeros({n, std::max<int64_t>(GG, 0)}, opt);
  {
    pybind11::gil_scoped_release nogil;
    const int nt = planar_threads(threads);
#pragma omp parallel for schedule(dynamic, 1) num_threads(nt)
    for (int64_t t = 0; t < ntiles; ++t) {
      const int tx = int(t % tiles_x), ty = int(t / tiles_x);
      const int64_t e0 = to[t];
      PairEval<S> e;
      for (int py = ty * kPTile; py < std::min<int64_t>(height, (ty + 1) * kPTile); ++py)
        for (int px = tx * kPTile; px < std::min<int64_t>(width, (tx + 1) * kPTile); ++px) {
          const int64_t pix = int64_t(py) * width + px;
          const S x = S(px) + S(0.5), y = S(py) + S(0.5);
          const S* g = gi + pix * C;
          const double Tf = double(tf[pix]);
          double g_bg = 0.0;
          for (int64_t c = 0; c < C; ++c) g_bg += double(g[c]) * double(bg[c]);
          const double tail = Tf * (double(ga[pix]) - g_bg);
          double T = Tf, W = 0.0;
          for (int64_t i = e0 + la[pix] - 1; i >= e0; --i) {
            const int64_t p = ent[i];
            if (!in_box(bb + 4 * p, px, py)) continue;
            const S* Mi = Mp + 9 * p;
            if (!eval_pair<S>(Mi, x, y, int(kind), tab ? tab + p * GG : nullptr, G, e)) continue;
            const S ok = op[p] * e.k;
            const S a = std::min(ok, S(kPAlphaMax));
            if (a < S(kPAlphaMin)) continue;
            const double one_m = 1.0 - double(a);
            const double Ti = T / one_m;
            double gc = 0.0;
            for (int64_t c = 0; c < C; ++c) gc += double(g[c]) * double(col[p * C + c]);
            const double d_alpha = Ti * gc + (tail - W) / one_m;
            W += gc * double(a) * Ti;
            T = Ti;
            S* r = sg + sl[i] * R;
            const S w = S(double(a) * Ti);
            for (int64_t c = 0; c < C; ++c) r[10 + c] += w * g[c];
            if (!(ok <= S(kPAlphaMax))) continue;  // clamped: no gradient to o or k
            r[9] += S(d_alpha) * e.k;
            const S dk = S(d_alpha) * op[p];
            S du, dv;
            if (kind == kSurfel) {
              const S dr2 = dk * e.k * S(-4.5);
              du = dr2 * S(2) * e.u;
              dv = dr2 * S(2) * e.v;
            } else {
              const S* tb = tab + p * GG + e.base;
              S* rt = r + 10 + C + e.base;
              const S fu = e.fu, fv = e.fv;
              rt[0] += dk * (S(1) - fu) * (S(1) - fv);
              rt[1] += dk * fu * (S(1) - fv);
              rt[G] += dk * (S(1) - fu) * fv;
              rt[G + 1] += dk * fu * fv;
              const S dfu = (tb[1] - tb[0]) * (S(1) - fv) + (tb[G + 1] - tb[G]) * fv;
              const S dfv = (tb[G] * (S(1) - fu) + tb[G + 1] * fu) - (tb[0] * (S(1) - fu) + tb[1] * fu);
              // clamp(-1, 1) passes the gradient inside [-1, 1] (always, inside the disk)
              const S dt = S(0.5) * S(G - 1);
              du = dk * dfu * dt;
              dv = dk * dfv * dt;
            }
            // (u, v) = (c0, c1) / c2 / 3
            const S gc0 = du / e.c[2] / S(3), gc1 = dv / e.c[2] / S(3);
            const S gc2 = -(du * e.u + dv * e.v) / e.c[2];
            // c = hu x hv: dL/dhu = hv x gc, dL/dhv = gc x hu
            const S* hu = e.hu;
            const S* hv = e.hv;
            const S gA[3] = {hv[1] * gc2 - hv[2] * gc1, hv[2] * gc0 - hv[0] * gc2,
                             hv[0] * gc1 - hv[1] * gc0};
            const S gB[3] = {gc1 * hu[2] - gc2 * hu[1], gc2 * hu[0] - gc0 * hu[2],
                             gc0 * hu[1] - gc1 * hu[0]};
            for (int k = 0; k < 3; ++k) {
              r[k] -= gA[k];
              r[3 + k] -= gB[k];
              r[6 + k] += x * gA[k] + y * gB[k];
            }
          }
        }
    }
    // Deterministic reduction: each primitive sums its own slots in order.
    S* vM = v_M.data_ptr<S>();
    S* vo = v_op.data_ptr<S>();
    S* vc = v_col.data_ptr<S>();
    S* vt = v_tab.data_ptr<S>();
#pragma omp parallel for schedule(static) num_threads(nt)
    for (int64_t p = 0; p < n; ++p) {
      for (int64_t s = po[p]; s < po[p + 1]; ++s) {
        const S* r = sg + s * R;
        for (int k = 0; k < 9; ++k) vM[p * 9 + k] += r[k];
        vo[p] += r[9];
        for (int64_t c = 0; c < C; ++c) vc[p * C + c] += r[10 + c];
        for (int64_t k = 0; k < GG; ++k) vt[p * GG + k] += r[10 + C + k];
      }
    }
  }
  return {v_M, v_op, v_col, v_tab};
}

void check_planar(const at::Tensor& M, const at::Tensor& opac, const at::Tensor& colors,
                  const at::Tensor& table, int64_t kind, const at::Tensor& background) {
  const auto dt = colors.scalar_type();
  TORCH_CHECK(dt == at::kFloat || dt == at::kDouble, "planar rasteriser: float32/64 only");
  for (const at::Tensor* t : {&M, &opac, &colors, &table, &background})
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous() && t->scalar_type() == dt,
                "planar rasteriser: contiguous CPU tensors of one float dtype");
  const int64_t n = M.size(0);
  TORCH_CHECK(M.dim() == 2 && M.size(1) == 9, "planar rasteriser: M must be [N, 9]");
  TORCH_CHECK(opac.numel() == n, "planar rasteriser: opacities must be [N]");
  TORCH_CHECK(colors.dim() == 2 && colors.size(0) == n, "planar rasteriser: colors must be [N, C]");
  TORCH_CHECK(background.numel() == colors.size(1), "planar rasteriser: background must be [C]");
  TORCH_CHECK(kind == kSurfel || kind == kGrid, "planar rasteriser: unknown kind ", kind);
  if (kind == kGrid)
    TORCH_CHECK(table.dim() == 3 && table.size(0) == n && table.size(1) == table.size(2) &&
                    table.size(1) >= 2,
                "planar rasteriser: grid table must be [N, G, G], G >= 2");
}

std::vector<at::Tensor> planar_forward(const at::Tensor& M, const at::Tensor& bbox,
                                       const at::Tensor& opac, const at::Tensor& colors,
                                       const at::Tensor& table, int64_t kind, int64_t width,
                                       int64_t height, const at::Tensor& background,
                                       int64_t threads) {
  check_planar(M, opac, colors, table, kind, background);
  TORCH_CHECK(bbox.scalar_type() == at::kInt && bbox.is_contiguous() && bbox.dim() == 2 &&
                  bbox.size(0) == M.size(0) && bbox.size(1) == 4,
              "planar rasteriser: bbox must be int32 [N, 4]");
  if (colors.scalar_type() == at::kDouble)
    return planar_forward_t<double>(M, bbox, opac, colors, table, kind, width, height, background,
                                    threads);
  return planar_forward_t<float>(M, bbox, opac, colors, table, kind, width, height, background,
                                 threads);
}

std::vector<at::Tensor> planar_backward(const at::Tensor& M, const at::Tensor& bbox,
                                        const at::Tensor& opac,
                                        const at::Tensor& colors, const at::Tensor& table,
                                        int64_t kind, int64_t width, int64_t height,
                                        const at::Tensor& background,
                                        const std::vector<at::Tensor>& state,
                                        const at::Tensor& v_img, const at::Tensor& v_alpha,
                                        int64_t threads) {
  check_planar(M, opac, colors, table, kind, background);
  TORCH_CHECK(state.size() == 6, "planar rasteriser: bad saved state");
  TORCH_CHECK(bbox.scalar_type() == at::kInt && bbox.is_contiguous() && bbox.numel() == 4 * M.size(0),
              "planar rasteriser: bbox must be int32 [N, 4]");
  const auto dt = colors.scalar_type();
  TORCH_CHECK(v_img.scalar_type() == dt && v_alpha.scalar_type() == dt && v_img.is_contiguous() &&
                  v_alpha.is_contiguous() && v_img.numel() == height * width * colors.size(1) &&
                  v_alpha.numel() == height * width,
              "planar rasteriser: gradients must be contiguous [H, W, C] and [H, W, 1]");
  if (dt == at::kDouble)
    return planar_backward_t<double>(M, bbox, opac, colors, table, kind, width, height, background,
                                     state, v_img, v_alpha, threads);
  return planar_backward_t<float>(M, bbox, opac, colors, table, kind, width, height, background, state,
                                  v_img, v_alpha, threads);
}

}  // namespace

void register_planar_ops(pybind11::module_& m) {
  m.def("planar_forward", &planar_forward,
        "planar_forward(M[N,9], bbox int32[N,4], opacities[N], colors[N,C], table[N,G,G], kind, "
        "width, height, background[C], threads) -> [img, alpha, *state]");
  m.def("planar_backward", &planar_backward,
        "planar_backward(M, bbox, opacities, colors, table, kind, width, height, background, state, "
        "v_img, v_alpha, threads) -> [v_M, v_opacities, v_colors, v_table]");
}

}  // namespace splatk
