// Fused native versions of the per-iteration torch ops around the rasteriser: the D-SSIM loss,
// EWA projection and spherical-harmonics colour. In torch each is dozens of small ops and
// autograd nodes; at 50k primitives and 400x400 pixels they cost 4x the rasteriser itself
// (benchmarks/train_step.py). Each function here is the exact formula of its torch reference
// (splatk/metrics/ssim.py, splatk/functional/projection.py, splatk/functional/sh.py) with a
// hand-written backward; tests/backends/test_fused_ops.py checks both against those references.
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <omp.h>
#include <torch/csrc/utils/pybind.h>

#include "bf16_mlp.h"
#include "simd.h"

#include <algorithm>
#include <cmath>
#include <initializer_list>
#include <optional>
#include <string>
#include <utility>
#include <vector>

namespace splatk {
namespace {

int nthreads(int64_t requested, int64_t work, int64_t min_work) {
  if (work < min_work) return 1;
  return requested > 0 ? int(requested) : omp_get_max_threads();
}

void check_cpu_float(const at::Tensor& t, at::ScalarType dt, const char* what) {
  TORCH_CHECK(t.device().is_cpu() && t.is_contiguous() && t.scalar_type() == dt, what,
              " must be a contiguous CPU tensor of the inputs' dtype");
}

// Every tensor a contiguous CPU float32 / float64 tensor of the first one's dtype.
void check_float_inputs(const char* op,
                        std::initializer_list<std::pair<const at::Tensor*, const char*>> inputs) {
  const auto dt = inputs.begin()->first->scalar_type();
  TORCH_CHECK(dt == at::kFloat || dt == at::kDouble, op, ": float32/64 only");
  for (const auto& [t, name] : inputs) check_cpu_float(*t, dt, (std::string(op) + ": " + name).c_str());
}

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

// ------------------------------------------------------------------------------------------
// EWA projection (splatk/functional/projection.py): camera transform, Jacobian evaluated at
// the clamped tangent, Sigma_2D = J R_c S S^T R_c^T J^T + blur I, conic = inverse / support^2.
// ------------------------------------------------------------------------------------------
struct Camera {
  double R[9], t[3], fx, fy, cx, cy;
  int width, height;
  double support2, near, blur;
};

template <typename S>
inline void quat_to_rot(const S* q, S R[9], S qn[4], S& norm) {
  norm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  const S inv = S(1) / std::max(norm, S(1e-12));
  for (int i = 0; i < 4; ++i) qn[i] = q[i] * inv;
  const S w = qn[0], x = qn[1], y = qn[2], z = qn[3];
  R[0] = 1 - 2 * (y * y + z * z), R[1] = 2 * (x * y - w * z), R[2] = 2 * (x * z + w * y);
  R[3] = 2 * (x * y + w * z), R[4] = 1 - 2 * (x * x + z * z), R[5] = 2 * (y * z - w * x);
  R[6] = 2 * (x * z - w * y), R[7] = 2 * (y * z + w * x), R[8] = 1 - 2 * (x * x + y * y);
}

// Everything the backward pass needs is recomputed from the inputs (cheap per primitive).
template <typename S>
struct ProjectLocal {
  S mc[3], zc, tx, ty, J[6], Rc[9], M[9], cov[9], a, b, c, det;
  bool det_clamped, tx_in, ty_in;
  S qn[4], qnorm;
};

template <typename S>
inline void project_one(const Camera& cam, const S* mean, const S* quat, const S* scale,
                        ProjectLocal<S>& L) {
  for (int i = 0; i < 3; ++i)
    L.mc[i] = S(cam.R[3 * i]) * mean[0] + S(cam.R[3 * i + 1]) * mean[1] +
              S(cam.R[3 * i + 2]) * mean[2] + S(cam.t[i]);
  const S fx = S(cam.fx), fy = S(cam.fy), cx = S(cam.cx), cy = S(cam.cy);
  L.zc = std::max(L.mc[2], S(cam.near));
  const S lox = (-cx - S(0.15) * cam.width) / fx, hix = (cam.width - cx + S(0.15) * cam.width) / fx;
  const S loy = (-cy - S(0.15) * cam.height) / fy, hiy = (cam.height - cy + S(0.15) * cam.height) / fy;
  const S rx = L.mc[0] / L.zc, ry = L.mc[1] / L.zc;
  L.tx_in = rx >= lox && rx <= hix;
  L.ty_in = ry >= loy && ry <= hiy;
  L.tx = std::min(std::max(rx, lox), hix);
  L.ty = std::min(std::max(ry, loy), hiy);
  L.J[0] = fx / L.zc, L.J[1] = 0, L.J[2] = -fx * L.tx / L.zc;
  L.J[3] = 0, L.J[4] = fy / L.zc, L.J[5] = -fy * L.ty / L.zc;
  S Rq[9];
  quat_to_rot(quat, Rq, L.qn, L.qnorm);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      L.Rc[3 * i + j] = S(cam.R[3 * i]) * Rq[j] + S(cam.R[3 * i + 1]) * Rq[3 + j] +
                        S(cam.R[3 * i + 2]) * Rq[6 + j];
      L.M[3 * i + j] = L.Rc[3 * i + j] * scale[j];
    }
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      L.cov[3 * i + j] = L.M[3 * i] * L.M[3 * j] + L.M[3 * i + 1] * L.M[3 * j + 1] +
                         L.M[3 * i + 2] * L.M[3 * j + 2];
  S JS[6];  // J @ cov
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j)
      JS[3 * i + j] = L.J[3 * i] * L.cov[j] + L.J[3 * i + 1] * L.cov[3 + j] +
                      L.J[3 * i + 2] * L.cov[6 + j];
  L.a = JS[0] * L.J[0] + JS[1] * L.J[1] + JS[2] * L.J[2] + S(cam.blur);
  L.b = JS[0] * L.J[3] + JS[1] * L.J[4] + JS[2] * L.J[5];
  L.c = JS[3] * L.J[3] + JS[4] * L.J[4] + JS[5] * L.J[5] + S(cam.blur);
  const S det = L.a * L.c - L.b * L.b;
  L.det_clamped = !(det >= S(1e-12));
  L.det = L.det_clamped ? S(1e-12) : det;
}

Camera make_camera(const at::Tensor& viewmat, const at::Tensor& K, int64_t width, int64_t height,
                   double support_sigmas, double near, double blur) {
  at::Tensor v = viewmat.to(at::kDouble).contiguous(), k = K.to(at::kDouble).contiguous();
  const double* vm = v.data_ptr<double>();
  const double* kk = k.data_ptr<double>();
  Camera cam;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) cam.R[3 * i + j] = vm[4 * i + j];
    cam.t[i] = vm[4 * i + 3];
  }
  cam.fx = kk[0], cam.fy = kk[4], cam.cx = kk[2], cam.cy = kk[5];
  cam.width = int(width), cam.height = int(height);
  cam.support2 = support_sigmas * support_sigmas, cam.near = near, cam.blur = blur;
  return cam;
}

template <typename S>
std::vector<at::Tensor> project_forward_t(const at::Tensor& means, const at::Tensor& quats,
                                          const at::Tensor& scales, const Camera& cam,
                                          double support_sigmas, bool want_view,
                                          int64_t threads) {
  const int64_t N = means.size(0);
  auto opt = means.options();
  at::Tensor means2d = at::empty({N, 2}, opt), conics = at::empty({N, 3}, opt),
             depths = at::empty({N}, opt), visible = at::empty({N}, opt.dtype(at::kBool));
  // camera-space centres and rotations (the learned kernel's Phi_proj inputs), if asked for
  at::Tensor means_cam = at::empty({want_view ? N : 0, 3}, opt);
  at::Tensor rot_cam = at::empty({want_view ? N : 0, 3, 3}, opt);
  S* mcam = want_view ? means_cam.data_ptr<S>() : nullptr;
  S* rcam = want_view ? rot_cam.data_ptr<S>() : nullptr;
  const S* m = means.data_ptr<S>();
  const S* q = quats.data_ptr<S>();
  const S* s = scales.data_ptr<S>();
  S* m2 = means2d.data_ptr<S>();
  S* co = conics.data_ptr<S>();
  S* dp = depths.data_ptr<S>();
  bool* vis = visible.data_ptr<bool>();
  const S s2 = S(cam.support2), sig = S(support_sigmas);
  pybind11::gil_scoped_release nogil;
#pragma omp parallel for num_threads(nthreads(threads, N, 4096)) schedule(static)
  for (int64_t n = 0; n < N; ++n) {
    ProjectLocal<S> L;
    project_one(cam, m + 3 * n, q + 4 * n, s + 3 * n, L);
    co[3 * n] = L.c / L.det / s2;
    co[3 * n + 1] = -L.b / L.det / s2;
    co[3 * n + 2] = L.a / L.det / s2;
    const S u = S(cam.fx) * L.mc[0] / L.zc + S(cam.cx);
    const S v = S(cam.fy) * L.mc[1] / L.zc + S(cam.cy);
    m2[2 * n] = u, m2[2 * n + 1] = v;
    dp[n] = L.mc[2];
    if (mcam) {
      std::copy(L.mc, L.mc + 3, mcam + 3 * n);
      std::copy(L.Rc, L.Rc + 9, rcam + 9 * n);
    }
    const S hx = sig * std::sqrt(L.a), hy = sig * std::sqrt(L.c);
    vis[n] = (L.mc[2] > S(cam.near)) && (u + hx > 0) && (u - hx < S(cam.width)) &&
             (v + hy > 0) && (v - hy < S(cam.height)) && std::isfinite(u) && std::isfinite(v);
  }
  return {means2d, conics, depths, visible, means_cam, rot_cam};
}

template <typename S>
std::vector<at::Tensor> project_backward_t(const at::Tensor& means, const at::Tensor& quats,
                                           const at::Tensor& scales, const Camera& cam,
                                           const at::Tensor& v_means2d, const at::Tensor& v_conics,
                                           const at::Tensor& v_depths, const at::Tensor& v_means_cam,
                                           const at::Tensor& v_rot_cam, int64_t threads) {
  const int64_t N = means.size(0);
  auto opt = means.options();
  at::Tensor v_means = at::empty({N, 3}, opt), v_quats = at::empty({N, 4}, opt),
             v_scales = at::empty({N, 3}, opt);
  const S* m = means.data_ptr<S>();
  const S* q = quats.data_ptr<S>();
  const S* s = scales.data_ptr<S>();
  const S* gm2 = v_means2d.data_ptr<S>();
  const S* gco = v_conics.data_ptr<S>();
  const S* gdp = v_depths.data_ptr<S>();
  const S* gmc = v_means_cam.numel() ? v_means_cam.data_ptr<S>() : nullptr;
  const S* grc = v_rot_cam.numel() ? v_rot_cam.data_ptr<S>() : nullptr;
  S* vm = v_means.data_ptr<S>();
  S* vq = v_quats.data_ptr<S>();
  S* vs = v_scales.data_ptr<S>();
  const S s2 = S(cam.support2), fx = S(cam.fx), fy = S(cam.fy);
  pybind11::gil_scoped_release nogil;
#pragma omp parallel for num_threads(nthreads(threads, N, 4096)) schedule(static)
  for (int64_t n = 0; n < N; ++n) {
    const S g0 = gco[3 * n] / s2, g1 = gco[3 * n + 1] / s2, g2 = gco[3 * n + 2] / s2;
    const S gu = gm2[2 * n], gv = gm2[2 * n + 1];
    bool view_zero = true;
    if (gmc)
      for (int j = 0; j < 3; ++j) view_zero = view_zero && gmc[3 * n + j] == 0;
    if (grc)
      for (int j = 0; j < 9; ++j) view_zero = view_zero && grc[9 * n + j] == 0;
    if (g0 == 0 && g1 == 0 && g2 == 0 && gu == 0 && gv == 0 && gdp[n] == 0 && view_zero) {
      std::fill(vm + 3 * n, vm + 3 * n + 3, S(0));
      std::fill(vq + 4 * n, vq + 4 * n + 4, S(0));
      std::fill(vs + 3 * n, vs + 3 * n + 3, S(0));
      continue;
    }
    ProjectLocal<S> L;
    project_one(cam, m + 3 * n, q + 4 * n, s + 3 * n, L);
    // conic_i = n_i / det with n = (c, -b, a), det = a c - b^2 (constant where clamped)
    const S det = L.det;
    const S kk = (g0 * L.c - g1 * L.b + g2 * L.a) / (det * det);
    const S dda = L.det_clamped ? 0 : L.c, ddb = L.det_clamped ? 0 : -2 * L.b,
            ddc = L.det_clamped ? 0 : L.a;
    const S va = g2 / det - kk * dda, vb = -g1 / det - kk * ddb, vc = g0 / det - kk * ddc;
    // cov2d = J cov J^T; only entries (0,0), (0,1), (1,1) are read: G = [[va, vb], [0, vc]],
    // Gs = G + G^T. dL/dJ = Gs J cov, dL/dM = J^T Gs J M (cov = M M^T).
    const S Gs[4] = {2 * va, vb, vb, 2 * vc};
    S GJ[6];  // Gs @ J
    for (int i = 0; i < 2; ++i)
      for (int j = 0; j < 3; ++j) GJ[3 * i + j] = Gs[2 * i] * L.J[j] + Gs[2 * i + 1] * L.J[3 + j];
    S vJ[6];
    for (int i = 0; i < 2; ++i)
      for (int j = 0; j < 3; ++j)
        vJ[3 * i + j] = GJ[3 * i] * L.cov[j] + GJ[3 * i + 1] * L.cov[3 + j] +
                        GJ[3 * i + 2] * L.cov[6 + j];
    S JGJ[9];  // J^T Gs J
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) JGJ[3 * i + j] = L.J[i] * GJ[j] + L.J[3 + i] * GJ[3 + j];
    S vM[9];
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j)
        vM[3 * i + j] = JGJ[3 * i] * L.M[j] + JGJ[3 * i + 1] * L.M[3 + j] +
                        JGJ[3 * i + 2] * L.M[6 + j];
    // M = Rc diag(s), Rc = Rw R
    const S* sc = s + 3 * n;
    S vRc[9];
    for (int j = 0; j < 3; ++j) {
      vs[3 * n + j] = vM[j] * L.Rc[j] + vM[3 + j] * L.Rc[3 + j] + vM[6 + j] * L.Rc[6 + j];
      for (int i = 0; i < 3; ++i) vRc[3 * i + j] = vM[3 * i + j] * sc[j];
    }
    if (grc)
      for (int j = 0; j < 9; ++j) vRc[j] += grc[9 * n + j];
    S G[9];  // dL/dR = Rw^T dL/dRc
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j)
        G[3 * i + j] = S(cam.R[i]) * vRc[j] + S(cam.R[3 + i]) * vRc[3 + j] +
                       S(cam.R[6 + i]) * vRc[6 + j];
    const S w = L.qn[0], x = L.qn[1], y = L.qn[2], z = L.qn[3];
    S vqn[4];
    vqn[0] = 2 * (-z * G[1] + y * G[2] + z * G[3] - x * G[5] - y * G[6] + x * G[7]);
    vqn[1] = 2 * (y * G[1] + z * G[2] + y * G[3] - 2 * x * G[4] - w * G[5] + z * G[6] +
                  w * G[7] - 2 * x * G[8]);
    vqn[2] = 2 * (-2 * y * G[0] + x * G[1] + w * G[2] + x * G[3] + z * G[5] - w * G[6] +
                  z * G[7] - 2 * y * G[8]);
    vqn[3] = 2 * (-2 * z * G[0] - w * G[1] + x * G[2] + w * G[3] - 2 * z * G[4] + y * G[5] +
                  x * G[6] + y * G[7]);
    // q_hat = q / max(|q|, eps)
    const S qdot = vqn[0] * w + vqn[1] * x + vqn[2] * y + vqn[3] * z;
    const bool qclamped = !(L.qnorm > S(1e-12));
    const S qinv = S(1) / std::max(L.qnorm, S(1e-12));
    for (int i = 0; i < 4; ++i) vq[4 * n + i] = (vqn[i] - (qclamped ? 0 : L.qn[i] * qdot)) * qinv;
    // J and means2d -> camera-space centre
    const S zc = L.zc, zc2 = zc * zc;
    S vx = gu * fx / zc, vy = gv * fy / zc;
    S vzc = -gu * fx * L.mc[0] / zc2 - gv * fy * L.mc[1] / zc2;
    vzc += -fx / zc2 * vJ[0] + fx * L.tx / zc2 * vJ[2] - fy / zc2 * vJ[4] + fy * L.ty / zc2 * vJ[5];
    const S vtx = -fx / zc * vJ[2], vty = -fy / zc * vJ[5];
    if (L.tx_in) vx += vtx / zc, vzc += -vtx * L.mc[0] / zc2;
    if (L.ty_in) vy += vty / zc, vzc += -vty * L.mc[1] / zc2;
    S vz = gdp[n] + (L.mc[2] >= S(cam.near) ? vzc : S(0));
    if (gmc) vx += gmc[3 * n], vy += gmc[3 * n + 1], vz += gmc[3 * n + 2];
    for (int j = 0; j < 3; ++j)
      vm[3 * n + j] = S(cam.R[j]) * vx + S(cam.R[3 + j]) * vy + S(cam.R[6 + j]) * vz;
  }
  return {v_means, v_quats, v_scales};
}

void check_project(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales) {
  check_float_inputs("project", {{&means, "means"}, {&quats, "quats"}, {&scales, "scales"}});
  const int64_t n = means.size(0);
  TORCH_CHECK(means.dim() == 2 && means.size(1) == 3, "project: means must be [N, 3]");
  TORCH_CHECK(quats.dim() == 2 && quats.size(0) == n && quats.size(1) == 4,
              "project: quats must be [N, 4]");
  TORCH_CHECK(scales.dim() == 2 && scales.size(0) == n && scales.size(1) == 3,
              "project: scales must be [N, 3]");
}

std::vector<at::Tensor> project_forward(const at::Tensor& means, const at::Tensor& quats,
                                        const at::Tensor& scales, const at::Tensor& viewmat,
                                        const at::Tensor& K, int64_t width, int64_t height,
                                        double support_sigmas, double near, double blur,
                                        bool want_view, int64_t threads) {
  check_project(means, quats, scales);
  Camera cam = make_camera(viewmat, K, width, height, support_sigmas, near, blur);
  if (means.scalar_type() == at::kDouble)
    return project_forward_t<double>(means, quats, scales, cam, support_sigmas, want_view, threads);
  return project_forward_t<float>(means, quats, scales, cam, support_sigmas, want_view, threads);
}

std::vector<at::Tensor> project_backward(const at::Tensor& means, const at::Tensor& quats,
                                         const at::Tensor& scales, const at::Tensor& viewmat,
                                         const at::Tensor& K, int64_t width, int64_t height,
                                         double support_sigmas, double near, double blur,
                                         const at::Tensor& v_means2d, const at::Tensor& v_conics,
                                         const at::Tensor& v_depths, const at::Tensor& v_means_cam,
                                         const at::Tensor& v_rot_cam, int64_t threads) {
  check_project(means, quats, scales);
  const auto dt = means.scalar_type();
  const int64_t n = means.size(0);
  check_float_inputs("project", {{&means, "means"}, {&v_means2d, "v_means2d"}, {&v_conics, "v_conics"},
                                 {&v_depths, "v_depths"}, {&v_means_cam, "v_means_cam"},
                                 {&v_rot_cam, "v_rot_cam"}});
  TORCH_CHECK(v_means_cam.numel() == 0 || v_means_cam.numel() == 3 * n, "project: v_means_cam size");
  TORCH_CHECK(v_rot_cam.numel() == 0 || v_rot_cam.numel() == 9 * n, "project: v_rot_cam size");
  Camera cam = make_camera(viewmat, K, width, height, support_sigmas, near, blur);
  if (dt == at::kDouble)
    return project_backward_t<double>(means, quats, scales, cam, v_means2d, v_conics, v_depths,
                                      v_means_cam, v_rot_cam, threads);
  return project_backward_t<float>(means, quats, scales, cam, v_means2d, v_conics, v_depths,
                                   v_means_cam, v_rot_cam, threads);
}

// ------------------------------------------------------------------------------------------
// Spherical harmonics colour, degree 0..3: rgb = max(sum_b basis_b(d / |d|) coeff_b + 0.5, 0).
// ------------------------------------------------------------------------------------------
constexpr double kC0 = 0.28209479177387814, kC1 = 0.4886025119029199;
constexpr double kC2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
                           -1.0925484305920792, 0.5462742152960396};
constexpr double kC3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
                           0.3731763325901154,  -0.4570457994644658, 1.445305721320277,
                           -0.5900435899266435};

// basis values and, if dB != nullptr, their derivatives d basis_b / d(x, y, z) as dB[3b + k]
template <typename S>
inline void sh_basis_grad(S x, S y, S z, int degree, S* B, S* dB) {
  B[0] = S(kC0);
  if (dB) dB[0] = dB[1] = dB[2] = 0;
  if (degree < 1) return;
  const S c1 = S(kC1);
  B[1] = -c1 * y, B[2] = c1 * z, B[3] = -c1 * x;
  if (dB) {
    S d[9] = {0, -c1, 0, 0, 0, c1, -c1, 0, 0};
    std::copy(d, d + 9, dB + 3);
  }
  if (degree < 2) return;
  const S xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  const S* c2 = nullptr;
  S c2v[5];
  for (int i = 0; i < 5; ++i) c2v[i] = S(kC2[i]);
  c2 = c2v;
  B[4] = c2[0] * xy, B[5] = c2[1] * yz, B[6] = c2[2] * (2 * zz - xx - yy), B[7] = c2[3] * xz,
  B[8] = c2[4] * (xx - yy);
  if (dB) {
    S d[15] = {c2[0] * y, c2[0] * x, 0,
               0, c2[1] * z, c2[1] * y,
               -2 * x * c2[2], -2 * y * c2[2], 4 * z * c2[2],
               c2[3] * z, 0, c2[3] * x,
               2 * x * c2[4], -2 * y * c2[4], 0};
    std::copy(d, d + 15, dB + 12);
  }
  if (degree < 3) return;
  S c3[7];
  for (int i = 0; i < 7; ++i) c3[i] = S(kC3[i]);
  B[9] = c3[0] * y * (3 * xx - yy);
  B[10] = c3[1] * xy * z;
  B[11] = c3[2] * y * (4 * zz - xx - yy);
  B[12] = c3[3] * z * (2 * zz - 3 * xx - 3 * yy);
  B[13] = c3[4] * x * (4 * zz - xx - yy);
  B[14] = c3[5] * z * (xx - yy);
  B[15] = c3[6] * x * (xx - 3 * yy);
  if (dB) {
    S d[21] = {6 * xy * c3[0], c3[0] * (3 * xx - 3 * yy), 0,
               c3[1] * yz, c3[1] * xz, c3[1] * xy,
               -2 * xy * c3[2], c3[2] * (4 * zz - xx - 3 * yy), 8 * yz * c3[2],
               -6 * xz * c3[3], -6 * yz * c3[3], c3[3] * (6 * zz - 3 * xx - 3 * yy),
               c3[4] * (4 * zz - 3 * xx - yy), -2 * xy * c3[4], 8 * xz * c3[4],
               2 * xz * c3[5], -2 * yz * c3[5], c3[5] * (xx - yy),
               c3[6] * (3 * xx - 3 * yy), -6 * xy * c3[6], 0};
    std::copy(d, d + 21, dB + 27);
  }
}

template <typename S>
inline void unit_dir(const S* d, S u[3], S& norm) {
  norm = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
  const S inv = S(1) / std::max(norm, S(1e-12));
  for (int k = 0; k < 3; ++k) u[k] = d[k] * inv;
}

template <typename S>
at::Tensor sh_forward_t(const at::Tensor& sh0, const at::Tensor& sh_rest, const at::Tensor& dirs,
                        int degree, int64_t threads) {
  const int64_t N = dirs.size(0);
  const int rest = int(sh_rest.size(1)), nb = (degree + 1) * (degree + 1);
  at::Tensor rgb = at::empty({N, 3}, dirs.options());
  const S* c0 = sh0.data_ptr<S>();
  const S* cr = sh_rest.data_ptr<S>();
  const S* d = dirs.data_ptr<S>();
  S* out = rgb.data_ptr<S>();
  pybind11::gil_scoped_release nogil;
#pragma omp parallel for num_threads(nthreads(threads, N, 4096)) schedule(static)
  for (int64_t n = 0; n < N; ++n) {
    S u[3], norm, B[16];
    unit_dir(d + 3 * n, u, norm);
    sh_basis_grad<S>(u[0], u[1], u[2], degree, B, nullptr);
    for (int ch = 0; ch < 3; ++ch) {
      S acc = B[0] * c0[3 * n + ch];
      for (int b = 1; b < nb; ++b) acc += B[b] * cr[(n * rest + b - 1) * 3 + ch];
      out[3 * n + ch] = std::max(acc + S(0.5), S(0));
    }
  }
  return rgb;
}

template <typename S>
std::vector<at::Tensor> sh_backward_t(const at::Tensor& sh0, const at::Tensor& sh_rest,
                                      const at::Tensor& dirs, int degree, const at::Tensor& v_rgb,
                                      bool need_dirs, int64_t threads) {
  const int64_t N = dirs.size(0);
  const int rest = int(sh_rest.size(1)), nb = (degree + 1) * (degree + 1);
  at::Tensor v0 = at::empty({N, 1, 3}, dirs.options());
  at::Tensor vr = at::zeros({N, rest, 3}, dirs.options());
  at::Tensor vd = at::empty({N, 3}, dirs.options());
  const S* c0 = sh0.data_ptr<S>();
  const S* cr = sh_rest.data_ptr<S>();
  const S* d = dirs.data_ptr<S>();
  const S* g = v_rgb.data_ptr<S>();
  S* pv0 = v0.data_ptr<S>();
  S* pvr = vr.data_ptr<S>();
  S* pvd = vd.data_ptr<S>();
  pybind11::gil_scoped_release nogil;
#pragma omp parallel for num_threads(nthreads(threads, N, 4096)) schedule(static)
  for (int64_t n = 0; n < N; ++n) {
    S u[3], norm, B[16], dB[48];
    unit_dir(d + 3 * n, u, norm);
    sh_basis_grad<S>(u[0], u[1], u[2], degree, B, need_dirs ? dB : nullptr);
    S gp[3];  // gradient of the pre-clamp value (clamp_min passes where value >= 0)
    for (int ch = 0; ch < 3; ++ch) {
      S acc = B[0] * c0[3 * n + ch];
      for (int b = 1; b < nb; ++b) acc += B[b] * cr[(n * rest + b - 1) * 3 + ch];
      gp[ch] = acc + S(0.5) >= 0 ? g[3 * n + ch] : S(0);
      pv0[3 * n + ch] = B[0] * gp[ch];
      for (int b = 1; b < nb; ++b) pvr[(n * rest + b - 1) * 3 + ch] = B[b] * gp[ch];
    }
    if (!need_dirs) continue;
    S vu[3] = {0, 0, 0};
    for (int b = 1; b < nb; ++b) {
      const S* cb = cr + (n * rest + b - 1) * 3;
      const S vb = gp[0] * cb[0] + gp[1] * cb[1] + gp[2] * cb[2];
      for (int k = 0; k < 3; ++k) vu[k] += vb * dB[3 * b + k];
    }
    const S dot = vu[0] * u[0] + vu[1] * u[1] + vu[2] * u[2];
    const bool clamped = !(norm > S(1e-12));
    const S inv = S(1) / std::max(norm, S(1e-12));
    for (int k = 0; k < 3; ++k) pvd[3 * n + k] = (vu[k] - (clamped ? 0 : u[k] * dot)) * inv;
  }
  return {v0, vr, vd};
}

void check_sh(const at::Tensor& sh0, const at::Tensor& sh_rest, const at::Tensor& dirs,
              int64_t degree) {
  check_float_inputs("sh", {{&dirs, "dirs"}, {&sh0, "sh0"}, {&sh_rest, "sh_rest"}});
  const int64_t n = dirs.size(0);
  TORCH_CHECK(dirs.dim() == 2 && dirs.size(1) == 3, "sh: dirs must be [N, 3]");
  TORCH_CHECK(sh0.dim() == 3 && sh0.size(0) == n && sh0.size(1) == 1 && sh0.size(2) == 3,
              "sh: sh0 must be [N, 1, 3]");
  TORCH_CHECK(sh_rest.dim() == 3 && sh_rest.size(0) == n && sh_rest.size(2) == 3,
              "sh: sh_rest must be [N, B, 3]");
  TORCH_CHECK(degree >= 0 && degree <= 3 && (degree + 1) * (degree + 1) - 1 <= sh_rest.size(1),
              "sh: degree out of range for the coefficients");
}

at::Tensor sh_forward(const at::Tensor& sh0, const at::Tensor& sh_rest, const at::Tensor& dirs,
                      int64_t degree, int64_t threads) {
  check_sh(sh0, sh_rest, dirs, degree);
  if (dirs.scalar_type() == at::kDouble)
    return sh_forward_t<double>(sh0, sh_rest, dirs, int(degree), threads);
  return sh_forward_t<float>(sh0, sh_rest, dirs, int(degree), threads);
}

std::vector<at::Tensor> sh_backward(const at::Tensor& sh0, const at::Tensor& sh_rest,
                                    const at::Tensor& dirs, int64_t degree,
                                    const at::Tensor& v_rgb, bool need_dirs, int64_t threads) {
  check_sh(sh0, sh_rest, dirs, degree);
  check_float_inputs("sh", {{&dirs, "dirs"}, {&v_rgb, "v_rgb"}});
  if (dirs.scalar_type() == at::kDouble)
    return sh_backward_t<double>(sh0, sh_rest, dirs, int(degree), v_rgb, need_dirs, threads);
  return sh_backward_t<float>(sh0, sh_rest, dirs, int(degree), v_rgb, need_dirs, threads);
}


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

void register_fused_ops(pybind11::module_& m) {
  m.def("ssim_forward", &ssim_forward,
        "ssim_forward(x[C,H,W], y, window[K], need_grad, threads) -> [mean, partials[3,C,H,W]]");
  m.def("ssim_backward", &ssim_backward,
        "ssim_backward(x, y, window, partials, v_mean, threads) -> v_x[C,H,W]");
  m.def("project_forward", &project_forward,
        "project_forward(means, quats, scales, viewmat, K, width, height, support_sigmas, near, "
        "blur, want_view, threads) -> [means2d, conics, depths, visible, means_cam, rot_cam]");
  m.def("project_backward", &project_backward,
        "project_backward(means, quats, scales, viewmat, K, width, height, support_sigmas, near, "
        "blur, v_means2d, v_conics, v_depths, v_means_cam, v_rot_cam, threads) -> "
        "[v_means, v_quats, v_scales]");
  m.def("sh_forward", &sh_forward, "sh_forward(sh0, sh_rest, dirs, degree, threads) -> rgb[N,3]");
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
  m.def("sh_backward", &sh_backward,
        "sh_backward(sh0, sh_rest, dirs, degree, v_rgb, need_dirs, threads) -> "
        "[v_sh0, v_sh_rest, v_dirs]");
}

}  // namespace splatk
