// EWA projection as one native op with a hand-written backward; splatk/functional/projection.py
// is its torch reference and tests/backends/test_fused_ops.py checks values and gradients against it.
#include "fused_common.h"

namespace splatk {
namespace {

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

}  // namespace

void register_project_ops(pybind11::module_& m) {
  m.def("project_forward", &project_forward,
        "project_forward(means, quats, scales, viewmat, K, width, height, support_sigmas, near, "
        "blur, want_view, threads) -> [means2d, conics, depths, visible, means_cam, rot_cam]");
  m.def("project_backward", &project_backward,
        "project_backward(means, quats, scales, viewmat, K, width, height, support_sigmas, near, "
        "blur, v_means2d, v_conics, v_depths, v_means_cam, v_rot_cam, threads) -> "
        "[v_means, v_quats, v_scales]");
}

}  // namespace splatk
