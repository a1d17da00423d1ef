// The D-SSIM loss as one native op with a hand-written backward; splatk/metrics/ssim.py is its
// torch reference and tests/backends/test_fused_ops.py checks values and gradients against it.
#include "fused_common.h"

namespace splatk {
namespace {

// ------------------------------------------------------------------------------------------
// SSIM with an R-radius separable Gaussian window, zero padding ("same"), C1 = 0.01^2,
// C2 = 0.03^2, mean over every pixel and channel. Gradient with respect to x only (the render;
// y is the photo).
//
// With m = G*x, e_xx = G*x^2, e_xy = G*xy (and the same for y):
//   A1 = 2 m_x m_y + C1, A2 = 2 (e_xy - m_x m_y) + C2, B1 = m_x^2 + m_y^2 + C1,
//   B2 = (e_xx - m_x^2) + (e_yy - m_y^2) + C2, S = A1 A2 / (B1 B2)
// and dS/dm_x, dS/de_xx, dS/de_xy are the three per-pixel maps saved for the backward pass:
//   dL/dx = G*(w dS/dm_x) + 2 x G*(w dS/de_xx) + y G*(w dS/de_xy)   (G symmetric, zero padding)
// ------------------------------------------------------------------------------------------
// Vertical pass for output row i of channel c: m[s][j] = sum_k g[k] maps[s][c][i + k - R][j]
// for each of the ``nmaps`` horizontally blurred maps (stride apart), zero padding.
template <typename S>
void blur_column_v(const S* maps, int64_t stride, int nmaps, int c, int i, int H, int W,
                   const S* g, int R, std::vector<S>* m) {
  for (int s = 0; s < nmaps; ++s) std::fill(m[s].begin(), m[s].end(), S(0));
  const int64_t plane = int64_t(H) * W;
  const int k0 = std::max(0, R - i), k1 = std::min(2 * R, R + H - 1 - i);
  for (int k = k0; k <= k1; ++k) {
    const int64_t src = int64_t(c) * plane + int64_t(i + k - R) * W;
    const S gk = g[k];
    for (int s = 0; s < nmaps; ++s) {
      const S* h = maps + s * stride + src;
      S* mv = m[s].data();
      for (int j = 0; j < W; ++j) mv[j] += gk * h[j];
    }
  }
}

template <typename S>
void blur_row_h(const S* in, S* out, S* pad, int W, const S* g, int R) {
  // pad has W + 2R entries; the borders stay zero (zero padding)
  std::copy(in, in + W, pad + R);
  // tap-outer order: the inner loop runs over contiguous pixels and vectorises
  std::fill(out, out + W, S(0));
  for (int k = 0; k <= 2 * R; ++k) {
    const S gk = g[k];
    const S* src = pad + k;
    for (int j = 0; j < W; ++j) out[j] += gk * src[j];
  }
}

template <typename S>
std::vector<at::Tensor> ssim_forward_t(const at::Tensor& x, const at::Tensor& y,
                                       const at::Tensor& window, bool need_grad,
                                       int64_t threads) {
  const int C = int(x.size(0)), H = int(x.size(1)), W = int(x.size(2));
  const int K = int(window.numel()), R = K / 2;
  const S* g = window.data_ptr<S>();
  const S* X = x.data_ptr<S>();
  const S* Y = y.data_ptr<S>();
  auto opt = x.options();
  const int64_t plane = int64_t(H) * W;
  at::Tensor hblur = at::empty({5, C, H, W}, opt);  // horizontally blurred x, y, xx, yy, xy
  at::Tensor partials = need_grad ? at::empty({3, C, H, W}, opt) : at::empty({0}, opt);
  S* HB = hblur.data_ptr<S>();
  S* P = need_grad ? partials.data_ptr<S>() : nullptr;
  const int64_t stride5 = int64_t(C) * plane;
  const S C1 = S(0.01 * 0.01), C2 = S(0.03 * 0.03);
  const int nt = nthreads(threads, int64_t(C) * H, 64);
  double total = 0;
  {
    pybind11::gil_scoped_release nogil;
#pragma omp parallel num_threads(nt) reduction(+ : total)
    {
      std::vector<S> pad(W + 2 * R, S(0)), prod(W);
#pragma omp for schedule(static)
      for (int64_t row = 0; row < int64_t(C) * H; ++row) {
        const S* xr = X + row * W;
        const S* yr = Y + row * W;
        blur_row_h(xr, HB + 0 * stride5 + row * W, pad.data(), W, g, R);
        blur_row_h(yr, HB + 1 * stride5 + row * W, pad.data(), W, g, R);
        for (int j = 0; j < W; ++j) prod[j] = xr[j] * xr[j];
        blur_row_h(prod.data(), HB + 2 * stride5 + row * W, pad.data(), W, g, R);
        for (int j = 0; j < W; ++j) prod[j] = yr[j] * yr[j];
        blur_row_h(prod.data(), HB + 3 * stride5 + row * W, pad.data(), W, g, R);
        for (int j = 0; j < W; ++j) prod[j] = xr[j] * yr[j];
        blur_row_h(prod.data(), HB + 4 * stride5 + row * W, pad.data(), W, g, R);
      }
      std::vector<S> m[5];
      for (auto& v : m) v.assign(W, S(0));
#pragma omp for schedule(static)
      for (int64_t row = 0; row < int64_t(C) * H; ++row) {
        blur_column_v(HB, stride5, 5, int(row / H), int(row % H), H, W, g, R, m);
        const int64_t o = row * W;
        for (int j = 0; j < W; ++j) {
          const S mx = m[0][j], my = m[1][j];
          const S A1 = 2 * mx * my + C1, A2 = 2 * (m[4][j] - mx * my) + C2;
          const S B1 = mx * mx + my * my + C1;
          const S B2 = (m[2][j] - mx * mx) + (m[3][j] - my * my) + C2;
          const S BB = B1 * B2;
          const S s = A1 * A2 / BB;
          total += double(s);
          if (P) {
            // d/dm_x of A1 A2 / (B1 B2): A1' = 2 m_y, A2' = -2 m_y, B1' = 2 m_x, B2' = -2 m_x
            P[o + j] = (2 * my * A2 - 2 * my * A1) / BB - s * (2 * mx / B1 - 2 * mx / B2);
            P[stride5 + o + j] = -s / B2;
            P[2 * stride5 + o + j] = 2 * A1 / BB;
          }
        }
      }
    }
  }
  at::Tensor mean = at::empty({}, opt);
  mean.fill_(total / double(C * plane));
  return {mean, partials};
}

template <typename S>
at::Tensor ssim_backward_t(const at::Tensor& x, const at::Tensor& y, const at::Tensor& window,
                           const at::Tensor& partials, double v_mean, int64_t threads) {
  const int C = int(x.size(0)), H = int(x.size(1)), W = int(x.size(2));
  const int K = int(window.numel()), R = K / 2;
  const S* g = window.data_ptr<S>();
  const S* X = x.data_ptr<S>();
  const S* Y = y.data_ptr<S>();
  const S* P = partials.data_ptr<S>();
  const int64_t plane = int64_t(H) * W, stride3 = int64_t(C) * plane;
  const S w = S(v_mean / double(C * plane));
  auto opt = x.options();
  at::Tensor hblur = at::empty({3, C, H, W}, opt);
  at::Tensor v_x = at::empty({C, H, W}, opt);
  S* HB = hblur.data_ptr<S>();
  S* VX = v_x.data_ptr<S>();
  const int nt = nthreads(threads, int64_t(C) * H, 64);
  pybind11::gil_scoped_release nogil;
#pragma omp parallel num_threads(nt)
  {
    std::vector<S> pad(W + 2 * R, S(0));
#pragma omp for schedule(static)
    for (int64_t row = 0; row < int64_t(C) * H; ++row)
      for (int s = 0; s < 3; ++s)
        blur_row_h(P + s * stride3 + row * W, HB + s * stride3 + row * W, pad.data(), W, g, R);
    std::vector<S> m[3];
    for (auto& v : m) v.assign(W, S(0));
#pragma omp for schedule(static)
    for (int64_t row = 0; row < int64_t(C) * H; ++row) {
      blur_column_v(HB, stride3, 3, int(row / H), int(row % H), H, W, g, R, m);
      const int64_t o = row * W;
      for (int j = 0; j < W; ++j)
        VX[o + j] = w * (m[0][j] + 2 * X[o + j] * m[1][j] + Y[o + j] * m[2][j]);
    }
  }
  return v_x;
}

std::vector<at::Tensor> ssim_forward(const at::Tensor& x, const at::Tensor& y,
                                     const at::Tensor& window, bool need_grad, int64_t threads) {
  check_float_inputs("ssim", {{&x, "x"}, {&y, "y"}, {&window, "window"}});
  TORCH_CHECK(x.dim() == 3 && x.sizes() == y.sizes(), "ssim: x and y must be [C, H, W] alike");
  TORCH_CHECK(window.numel() % 2 == 1, "ssim: odd window only");
  if (x.scalar_type() == at::kDouble) return ssim_forward_t<double>(x, y, window, need_grad, threads);
  return ssim_forward_t<float>(x, y, window, need_grad, threads);
}

at::Tensor ssim_backward(const at::Tensor& x, const at::Tensor& y, const at::Tensor& window,
                         const at::Tensor& partials, double v_mean, int64_t threads) {
  if (x.scalar_type() == at::kDouble)
    return ssim_backward_t<double>(x, y, window, partials, v_mean, threads);
  return ssim_backward_t<float>(x, y, window, partials, v_mean, threads);
}

}  // namespace

void register_ssim_ops(pybind11::module_& m) {
  m.def("ssim_forward", &ssim_forward,
        "ssim_forward(x[C,H,W], y, window[K], need_grad, threads) -> [mean, partials[3,C,H,W]]");
  m.def("ssim_backward", &ssim_backward,
        "ssim_backward(x, y, window, partials, v_mean, threads) -> v_x[C,H,W]");
}

}  // namespace splatk
