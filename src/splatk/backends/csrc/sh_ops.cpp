// Spherical-harmonics colour as one native op with a hand-written backward; splatk/functional/sh.py
// is its torch reference and tests/backends/test_fused_ops.py checks values and gradients against it.
#include "fused_common.h"

namespace splatk {
namespace {

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

}  // namespace

void register_sh_ops(pybind11::module_& m) {
  m.def("sh_forward", &sh_forward, "sh_forward(sh0, sh_rest, dirs, degree, threads) -> rgb[N,3]");
  m.def("sh_backward", &sh_backward,
        "sh_backward(sh0, sh_rest, dirs, degree, v_rgb, need_dirs, threads) -> "
        "[v_sh0, v_sh_rest, v_dirs]");
}

}  // namespace splatk
