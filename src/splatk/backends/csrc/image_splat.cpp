// Native CPU renderer for 2D image splats (`splatk image`): the ``cpu`` path of
// splatk/image/model.py. Semantics are those of ``Splats2D.render`` on the torch path (the
// specification), for the transformed parameters it packs:
//
//   * the image is the plain sum I(x) = sum_i c_i k_i(u, v) (GaussianImage, no compositing);
//   * pixel centre (x, y) = (i + 0.5, j + 0.5); u = (x - mx) / l11, v = (y - my - l21 u) / l22
//     (L^-1 (x - mu), L = [[l11, 0], [l21, l22]]), then (u, v) /= 3 so the 3-sigma ellipse is the
//     unit disk; pairs with u^2 + v^2 > 1 add nothing;
//   * k = E(u, v) = exp(-4.5 (u^2 + v^2)) times, per kind:
//       gaussian: 1
//       gabor:    W_u W_v, W_d = sum_k a_{d,k} cos(pi f_{d,k} d); extras row = [a (2 x K), f (2 x K)]
//       table:    bilinear in a per-splat G x G table at nodes linspace(-1, 1, G), indexed [v, u],
//                 (u, v) clamped to [-1, 1] (planar_torch.bilinear); extras row = the table;
//   * only the pixels of each splat's box (bbox row: x0, y0, x1, y1, exclusive ends, computed by
//     the caller exactly as the torch path lists its pairs) are visited.
//
// Forward: splats are binned into 16x16 tiles in splat order (a serial counting pass), then
// OpenMP over tiles; each tile adds its splats in order, so the image is bitwise reproducible
// for any thread count. Backward: OpenMP over splats; each splat sums its own pixels' terms
// (the image gradient is read only), so there is nothing to reduce and no atomics.
#include <ATen/ops/zeros.h>
#include <ATen/ops/zeros_like.h>
#include <omp.h>
#include <torch/csrc/utils/pybind.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace splatk {
namespace {

constexpr int kImgTile = 16;
enum ImageKind : int { kImgGaussian = 0, kImgGabor = 1, kImgTable = 2 };

// One (pixel, splat) pair: the local coordinates and the kernel's value and partials.
template <typename S>
struct ImagePair {
  S u, v;        // L^-1 (x - mu), before the / 3
  S U, V;        // normalised: the unit disk is the support
  S env;         // exp(-4.5 r2)
  S shape;       // the kind's factor (1, W_u W_v, or the bilinear value)
  S w;           // env * shape
  // gabor: the two wave sums; table: the cell and its fractions
  S wu, wv;
  int64_t cell;
  S fu, fv;
};

// Evaluates the pair; false when the pixel lies outside the splat's unit disk.
template <typename S>
inline bool eval_image_pair(S x, S y, const S* mean, const S* chol, int kind, const S* extra,
                            int K, int G, ImagePair<S>& e) {
  const S dx = x - mean[0], dy = y - mean[1];
  e.u = dx / chol[0];
  e.v = (dy - chol[1] * e.u) / chol[2];
  const S third = S(1) / S(3);
  e.U = e.u * third;
  e.V = e.v * third;
  const S r2 = e.U * e.U + e.V * e.V;
  if (!(r2 <= S(1))) return false;
  e.env = std::exp(S(-4.5) * r2);
  if (kind == kImgGaussian) {
    e.shape = S(1);
  } else if (kind == kImgGabor) {
    const S pi = S(M_PI);
    const S* a = extra;          // [2, K]
    const S* f = extra + 2 * K;  // [2, K]
    S wu = 0, wv = 0;
    for (int k = 0; k < K; ++k) {
      wu += a[k] * std::cos(pi * f[k] * e.U);
      wv += a[K + k] * std::cos(pi * f[K + k] * e.V);
    }
    e.wu = wu;
    e.wv = wv;
    e.shape = wu * wv;
  } else {
    const S half = S(0.5) * S(G - 1);
    const S tu = (std::min(std::max(e.U, S(-1)), S(1)) + S(1)) * half;
    const S tv = (std::min(std::max(e.V, S(-1)), S(1)) + S(1)) * half;
    const S iu = std::min(std::max(std::floor(tu), S(0)), S(G - 2));
    const S iv = std::min(std::max(std::floor(tv), S(0)), S(G - 2));
    e.fu = tu - iu;
    e.fv = tv - iv;
    e.cell = static_cast<int64_t>(iv) * G + static_cast<int64_t>(iu);
    const S* t = extra + e.cell;
    e.shape = (t[0] * (S(1) - e.fu) + t[1] * e.fu) * (S(1) - e.fv) +
              (t[G] * (S(1) - e.fu) + t[G + 1] * e.fu) * e.fv;
  }
  e.w = e.env * e.shape;
  return true;
}

struct ImageDims {
  int64_t n, E;  // splats, extras per splat
  int K, G;      // gabor waves, table nodes per axis
};

ImageDims image_dims(const at::Tensor& means, const at::Tensor& chol, const at::Tensor& colors,
                     const at::Tensor& extras, const at::Tensor& bbox, int64_t kind, int64_t aux) {
  const auto dt = means.scalar_type();
  TORCH_CHECK(dt == at::kFloat || dt == at::kDouble, "image splats: float32/64 only");
  for (const at::Tensor* t : {&means, &chol, &colors, &extras})
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous() && t->scalar_type() == dt,
                "image splats: contiguous CPU tensors of one float dtype");
  const int64_t n = means.size(0);
  TORCH_CHECK(means.dim() == 2 && means.size(1) == 2, "image splats: means must be [N, 2]");
  TORCH_CHECK(chol.dim() == 2 && chol.size(0) == n && chol.size(1) == 3, "image splats: chol must be [N, 3]");
  TORCH_CHECK(colors.dim() == 2 && colors.size(0) == n && colors.size(1) == 3,
              "image splats: colors must be [N, 3]");
  TORCH_CHECK(bbox.scalar_type() == at::kInt && bbox.is_contiguous() && bbox.dim() == 2 &&
                  bbox.size(0) == n && bbox.size(1) == 4,
              "image splats: bbox must be int32 [N, 4]");
  TORCH_CHECK(extras.dim() == 2 && extras.size(0) == n, "image splats: extras must be [N, E]");
  ImageDims d{n, extras.size(1), 0, 0};
  if (kind == kImgGabor) {
    d.K = static_cast<int>(aux);
    TORCH_CHECK(d.K >= 1 && d.E == 4 * d.K, "image splats: gabor extras must be [N, 4 K]");
  } else if (kind == kImgTable) {
    d.G = static_cast<int>(aux);
    TORCH_CHECK(d.G >= 2 && d.E == int64_t(d.G) * d.G, "image splats: table extras must be [N, G*G]");
  } else {
    TORCH_CHECK(kind == kImgGaussian, "image splats: unknown kind ", kind);
  }
  return d;
}

template <typename S>
at::Tensor image_forward_t(const at::Tensor& means, const at::Tensor& chol, const at::Tensor& colors,
                           const at::Tensor& extras, const at::Tensor& bbox, int64_t kind,
                           int64_t aux, int64_t width, int64_t height, int64_t threads) {
  const ImageDims d = image_dims(means, chol, colors, extras, bbox, kind, aux);
  at::Tensor img = at::zeros({height, width, 3}, means.options());
  const int64_t tw = (width + kImgTile - 1) / kImgTile, th = (height + kImgTile - 1) / kImgTile;
  const int64_t ntiles = tw * th;
  const int32_t* bb = bbox.data_ptr<int32_t>();
  // Serial binning in splat order (counting sort): every tile list keeps splat order.
  auto tile_range = [&](int64_t i, int64_t& tx0, int64_t& ty0, int64_t& tx1, int64_t& ty1) {
    const int64_t x0 = std::max<int64_t>(bb[4 * i], 0), y0 = std::max<int64_t>(bb[4 * i + 1], 0);
    const int64_t x1 = std::min<int64_t>(bb[4 * i + 2], width), y1 = std::min<int64_t>(bb[4 * i + 3], height);
    if (x0 >= x1 || y0 >= y1) return false;
    tx0 = x0 / kImgTile, ty0 = y0 / kImgTile, tx1 = (x1 - 1) / kImgTile + 1, ty1 = (y1 - 1) / kImgTile + 1;
    return true;
  };
  std::vector<int64_t> offs(ntiles + 1, 0);
  for (int64_t i = 0; i < d.n; ++i) {
    int64_t tx0, ty0, tx1, ty1;
    if (!tile_range(i, tx0, ty0, tx1, ty1)) continue;
    for (int64_t ty = ty0; ty < ty1; ++ty)
      for (int64_t tx = tx0; tx < tx1; ++tx) ++offs[ty * tw + tx + 1];
  }
  for (int64_t t = 0; t < ntiles; ++t) offs[t + 1] += offs[t];
  std::vector<int32_t> lists(offs[ntiles]);
  {
    std::vector<int64_t> fill(offs.begin(), offs.end() - 1);
    for (int64_t i = 0; i < d.n; ++i) {
      int64_t tx0, ty0, tx1, ty1;
      if (!tile_range(i, tx0, ty0, tx1, ty1)) continue;
      for (int64_t ty = ty0; ty < ty1; ++ty)
        for (int64_t tx = tx0; tx < tx1; ++tx) lists[fill[ty * tw + tx]++] = static_cast<int32_t>(i);
    }
  }
  const S* mp = means.data_ptr<S>();
  const S* cp = chol.data_ptr<S>();
  const S* colp = colors.data_ptr<S>();
  const S* xp = extras.data_ptr<S>();
  S* out = img.data_ptr<S>();
  const int nt = static_cast<int>(std::max<int64_t>(1, threads));
#pragma omp parallel for schedule(dynamic, 1) num_threads(nt)
  for (int64_t t = 0; t < ntiles; ++t) {
    const int64_t ox = (t % tw) * kImgTile, oy = (t / tw) * kImgTile;
    const int64_t ex = std::min<int64_t>(ox + kImgTile, width), ey = std::min<int64_t>(oy + kImgTile, height);
    ImagePair<S> e;
    for (int64_t s = offs[t]; s < offs[t + 1]; ++s) {
      const int64_t i = lists[s];
      const int64_t x0 = std::max<int64_t>(bb[4 * i], ox), y0 = std::max<int64_t>(bb[4 * i + 1], oy);
      const int64_t x1 = std::min<int64_t>(bb[4 * i + 2], ex), y1 = std::min<int64_t>(bb[4 * i + 3], ey);
      const S* c = colp + 3 * i;
      for (int64_t y = y0; y < y1; ++y)
        for (int64_t x = x0; x < x1; ++x) {
          if (!eval_image_pair<S>(S(x) + S(0.5), S(y) + S(0.5), mp + 2 * i, cp + 3 * i, int(kind),
                                  xp + i * d.E, d.K, d.G, e))
            continue;
          S* o = out + (y * width + x) * 3;
          o[0] += e.w * c[0];
          o[1] += e.w * c[1];
          o[2] += e.w * c[2];
        }
    }
  }
  return img;
}

template <typename S>
std::vector<at::Tensor> image_backward_t(const at::Tensor& means, const at::Tensor& chol,
                                         const at::Tensor& colors, const at::Tensor& extras,
                                         const at::Tensor& bbox, int64_t kind, int64_t aux,
                                         const at::Tensor& v_img, int64_t threads) {
  const ImageDims d = image_dims(means, chol, colors, extras, bbox, kind, aux);
  const int64_t height = v_img.size(0), width = v_img.size(1);
  at::Tensor v_means = at::zeros_like(means), v_chol = at::zeros_like(chol);
  at::Tensor v_colors = at::zeros_like(colors), v_extras = at::zeros_like(extras);
  const int32_t* bb = bbox.data_ptr<int32_t>();
  const S* mp = means.data_ptr<S>();
  const S* cp = chol.data_ptr<S>();
  const S* colp = colors.data_ptr<S>();
  const S* xp = extras.data_ptr<S>();
  const S* g = v_img.data_ptr<S>();
  S* vm = v_means.data_ptr<S>();
  S* vch = v_chol.data_ptr<S>();
  S* vc = v_colors.data_ptr<S>();
  S* vx = v_extras.data_ptr<S>();
  const int nt = static_cast<int>(std::max<int64_t>(1, threads));
  const S pi = S(M_PI);
#pragma omp parallel for schedule(dynamic, 16) num_threads(nt)
  for (int64_t i = 0; i < d.n; ++i) {
    const int64_t x0 = std::max<int64_t>(bb[4 * i], 0), y0 = std::max<int64_t>(bb[4 * i + 1], 0);
    const int64_t x1 = std::min<int64_t>(bb[4 * i + 2], width), y1 = std::min<int64_t>(bb[4 * i + 3], height);
    const S* c = colp + 3 * i;
    const S* ch = cp + 3 * i;
    const S* ex = xp + i * d.E;
    S* gx = vx + i * d.E;
    const S l11 = ch[0], l21 = ch[1], l22 = ch[2];
    S gmx = 0, gmy = 0, g11 = 0, g21 = 0, g22 = 0, gc0 = 0, gc1 = 0, gc2 = 0;
    ImagePair<S> e;
    for (int64_t y = y0; y < y1; ++y)
      for (int64_t x = x0; x < x1; ++x) {
        if (!eval_image_pair<S>(S(x) + S(0.5), S(y) + S(0.5), mp + 2 * i, ch, int(kind), ex, d.K,
                                d.G, e))
          continue;
        const S* gp = g + (y * width + x) * 3;
        gc0 += e.w * gp[0];
        gc1 += e.w * gp[1];
        gc2 += e.w * gp[2];
        const S gw = gp[0] * c[0] + gp[1] * c[1] + gp[2] * c[2];
        if (gw == S(0)) continue;
        // dw/dU and dw/dV: the envelope's part, then the shape's
        S dU = S(-9) * e.U * e.w, dV = S(-9) * e.V * e.w;
        if (kind == kImgGabor) {
          const int K = d.K;
          const S* a = ex;
          const S* f = ex + 2 * K;
          S dwu = 0, dwv = 0;
          for (int k = 0; k < K; ++k) {
            const S cu = std::cos(pi * f[k] * e.U), su = std::sin(pi * f[k] * e.U);
            const S cv = std::cos(pi * f[K + k] * e.V), sv = std::sin(pi * f[K + k] * e.V);
            dwu -= a[k] * pi * f[k] * su;
            dwv -= a[K + k] * pi * f[K + k] * sv;
            gx[k] += gw * e.env * cu * e.wv;
            gx[K + k] += gw * e.env * e.wu * cv;
            gx[2 * K + k] -= gw * e.env * e.wv * a[k] * su * pi * e.U;
            gx[3 * K + k] -= gw * e.env * e.wu * a[K + k] * sv * pi * e.V;
          }
          dU += e.env * dwu * e.wv;
          dV += e.env * e.wu * dwv;
        } else if (kind == kImgTable) {
          const int G = d.G;
          const S* t = ex + e.cell;
          const S half = S(0.5) * S(G - 1);
          // the clamp to [-1, 1] passes no gradient outside (never inside the unit disk but at
          // its very edge)
          if (e.U > S(-1) && e.U < S(1))
            dU += e.env * ((t[1] - t[0]) * (S(1) - e.fv) + (t[G + 1] - t[G]) * e.fv) * half;
          if (e.V > S(-1) && e.V < S(1))
            dV += e.env * ((t[G] - t[0]) * (S(1) - e.fu) + (t[G + 1] - t[1]) * e.fu) * half;
          S* gt = gx + e.cell;
          const S ge = gw * e.env;
          gt[0] += ge * (S(1) - e.fu) * (S(1) - e.fv);
          gt[1] += ge * e.fu * (S(1) - e.fv);
          gt[G] += ge * (S(1) - e.fu) * e.fv;
          gt[G + 1] += ge * e.fu * e.fv;
        }
        // chain through U = u / 3, V = v / 3, u = dx / l11, v = (dy - l21 u) / l22
        const S gu = gw * dU / S(3), gv = gw * dV / S(3);
        const S gu_all = gu - gv * l21 / l22;
        gmx -= gu_all / l11;
        gmy -= gv / l22;
        g11 -= gu_all * e.u / l11;
        g21 -= gv * e.u / l22;
        g22 -= gv * e.v / l22;
      }
    vm[2 * i] = gmx;
    vm[2 * i + 1] = gmy;
    vch[3 * i] = g11;
    vch[3 * i + 1] = g21;
    vch[3 * i + 2] = g22;
    vc[3 * i] = gc0;
    vc[3 * i + 1] = gc1;
    vc[3 * i + 2] = gc2;
  }
  return {v_means, v_chol, v_colors, v_extras};
}

at::Tensor image_forward(const at::Tensor& means, const at::Tensor& chol, const at::Tensor& colors,
                         const at::Tensor& extras, const at::Tensor& bbox, int64_t kind, int64_t aux,
                         int64_t width, int64_t height, int64_t threads) {
  if (means.scalar_type() == at::kDouble)
    return image_forward_t<double>(means, chol, colors, extras, bbox, kind, aux, width, height, threads);
  return image_forward_t<float>(means, chol, colors, extras, bbox, kind, aux, width, height, threads);
}

std::vector<at::Tensor> image_backward(const at::Tensor& means, const at::Tensor& chol,
                                       const at::Tensor& colors, const at::Tensor& extras,
                                       const at::Tensor& bbox, int64_t kind, int64_t aux,
                                       const at::Tensor& v_img, int64_t threads) {
  TORCH_CHECK(v_img.dim() == 3 && v_img.size(2) == 3 && v_img.is_contiguous() &&
                  v_img.scalar_type() == means.scalar_type(),
              "image splats: the image gradient must be contiguous [H, W, 3] of the splats' dtype");
  if (means.scalar_type() == at::kDouble)
    return image_backward_t<double>(means, chol, colors, extras, bbox, kind, aux, v_img, threads);
  return image_backward_t<float>(means, chol, colors, extras, bbox, kind, aux, v_img, threads);
}

}  // namespace

void register_image_ops(pybind11::module_& m) {
  m.def("image_forward", &image_forward,
        "image_forward(means[N,2], chol[N,3], colors[N,3], extras[N,E], bbox int32[N,4], kind, aux, "
        "width, height, threads) -> img[H,W,3]");
  m.def("image_backward", &image_backward,
        "image_backward(means, chol, colors, extras, bbox, kind, aux, v_img[H,W,3], threads) -> "
        "[v_means, v_chol, v_colors, v_extras]");
}

}  // namespace splatk
