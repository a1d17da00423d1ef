// Python binding of the native CPU rasteriser (module TORCH_EXTENSION_NAME, built by
// splatk/backends/cpu_native.py). Checks inputs, allocates the tensors and calls the torch-free
// kernels in raster_kernels.cpp. Only light torch headers here: torch/extension.h alone costs
// more compile time than all the kernels.
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/csrc/utils/pybind.h>

#include <vector>

#include "raster_kernels.h"

namespace splatk {
namespace {

// The backward state lives in tensors so autograd can save it between the passes.
struct TensorAllocator : StateAllocator {
  std::vector<at::Tensor> tensors = std::vector<at::Tensor>(kNumStateBuffers);
  void* allocate(int which, int64_t count, int elem_bytes) override {
    tensors[which] = at::empty({count}, at::TensorOptions().dtype(elem_bytes == 1 ? at::kByte
                                                                                     : at::kInt));
    return tensors[which].data_ptr();
  }
};

void check_inputs(const at::Tensor& means2d, const at::Tensor& conics,
                  const at::Tensor& opacities, const at::Tensor& colors, const at::Tensor& depths,
                  const at::Tensor& params, const at::Tensor& background, int64_t kind,
                  int64_t width, int64_t height) {
  const auto dt = colors.scalar_type();
  TORCH_CHECK(dt == at::kFloat || dt == at::kDouble, "cpu rasteriser: float32/64 inputs only");
  for (const at::Tensor* t : {&means2d, &conics, &opacities, &colors, &params, &background}) {
    TORCH_CHECK(t->device().is_cpu(), "cpu rasteriser: CPU tensors only");
    TORCH_CHECK(t->scalar_type() == dt, "cpu rasteriser: all float inputs must share a dtype");
    TORCH_CHECK(t->is_contiguous(), "cpu rasteriser: contiguous tensors only");
  }
  TORCH_CHECK(depths.device().is_cpu() && depths.is_contiguous() &&
                  (depths.scalar_type() == at::kFloat || depths.scalar_type() == at::kDouble),
              "cpu rasteriser: depths must be a contiguous float32/64 CPU tensor");
  const int64_t n = means2d.size(0);
  TORCH_CHECK(means2d.dim() == 2 && means2d.size(1) == 2, "means2d must be [N, 2]");
  TORCH_CHECK(conics.dim() == 2 && conics.size(0) == n && conics.size(1) == 3,
              "conics must be [N, 3]");
  TORCH_CHECK(opacities.numel() == n && depths.numel() == n, "opacities and depths must be [N]");
  TORCH_CHECK(colors.dim() == 2 && colors.size(0) == n && colors.size(1) >= 1,
              "colors must be [N, C]");
  TORCH_CHECK(params.dim() == 2 && params.size(0) == n, "params must be [N, P]");
  TORCH_CHECK(background.numel() == colors.size(1), "background must be [C]");
  TORCH_CHECK(kind >= kGaussian && kind <= kTable, "unknown profile kind code ", kind);
  TORCH_CHECK(kind != kTable || params.size(1) >= 2, "table profile needs k >= 2 samples");
  TORCH_CHECK((kind != kBeta && kind != kStudentT) || params.size(1) == 1,
              "beta / student_t profiles need params [N, 1]");
  TORCH_CHECK(width >= 0 && height >= 0 && width < (1 << 20) && height < (1 << 20) &&
                  n < (int64_t(1) << 31),
              "cpu rasteriser: image or scene too large");
}

template <typename S>
std::vector<at::Tensor> forward_t(const at::Tensor& means2d, const at::Tensor& conics,
                                  const at::Tensor& opacities, const at::Tensor& colors,
                                  const at::Tensor& depths, const at::Tensor& params,
                                  int64_t kind, int64_t width, int64_t height,
                                  const at::Tensor& background, int64_t threads) {
  auto opt = colors.options();
  at::Tensor img = at::empty({height, width, colors.size(1)}, opt);
  at::Tensor alpha = at::empty({height, width, 1}, opt);
  at::Tensor T_final = at::empty({height, width}, opt);
  at::Tensor last = at::empty({height, width}, opt.dtype(at::kInt));
  ForwardArgs<S> a;
  a.N = means2d.size(0);
  a.W = int(width), a.H = int(height), a.C = int(colors.size(1)), a.P = int(params.size(1));
  a.kind = int(kind), a.threads = int(threads);
  a.means2d = means2d.data_ptr<S>();
  a.conics = conics.data_ptr<S>();
  a.opacities = opacities.data_ptr<S>();
  a.colors = colors.data_ptr<S>();
  a.params = params.data_ptr<S>();
  a.background = background.data_ptr<S>();
  a.depths = depths.data_ptr();
  a.depths_f32 = depths.scalar_type() == at::kFloat;
  a.img = img.data_ptr<S>();
  a.alpha = alpha.data_ptr<S>();
  a.T_final = T_final.data_ptr<S>();
  a.last = last.data_ptr<int32_t>();
  TensorAllocator alloc;
  {
    pybind11::gil_scoped_release nogil;
    forward(a, alloc);
  }
  std::vector<at::Tensor> out = {img, alpha, T_final, last};
  for (const at::Tensor& t : alloc.tensors) out.push_back(t);
  return out;
}

template <typename S>
std::vector<at::Tensor> backward_t(const std::vector<at::Tensor>& state, int64_t n, int64_t kind,
                                   int64_t width, int64_t height, const at::Tensor& background,
                                   const at::Tensor& v_img, const at::Tensor& v_alpha, int64_t C,
                                   int64_t P, int64_t threads) {
  auto opt = background.options();
  at::Tensor v_means = at::zeros({n, 2}, opt), v_conics = at::zeros({n, 3}, opt),
             v_opac = at::zeros({n}, opt), v_colors = at::zeros({n, C}, opt),
             v_params = at::zeros({n, P}, opt), v_bg = at::zeros({C}, opt);
  BackwardArgs<S> a;
  a.N = n;
  a.V = state[2 + kOrder].numel();
  a.E = state[2 + kEntries].numel();
  a.W = int(width), a.H = int(height), a.C = int(C), a.P = int(P);
  a.kind = int(kind), a.threads = int(threads);
  a.background = background.data_ptr<S>();
  a.T_final = state[0].data_ptr<S>();
  a.last = state[1].data_ptr<int32_t>();
  for (int i = 0; i < kNumStateBuffers; ++i) a.state[i] = state[2 + i].data_ptr();
  a.v_img = v_img.data_ptr<S>();
  a.v_alpha = v_alpha.data_ptr<S>();
  a.v_means2d = v_means.data_ptr<S>();
  a.v_conics = v_conics.data_ptr<S>();
  a.v_opacities = v_opac.data_ptr<S>();
  a.v_colors = v_colors.data_ptr<S>();
  a.v_params = v_params.data_ptr<S>();
  a.v_background = v_bg.data_ptr<S>();
  {
    pybind11::gil_scoped_release nogil;
    backward(a);
  }
  return {v_means, v_conics, v_opac, v_colors, v_params, v_bg};
}

std::vector<at::Tensor> rasterize_forward(const at::Tensor& means2d, const at::Tensor& conics,
                                          const at::Tensor& opacities, const at::Tensor& colors,
                                          const at::Tensor& depths, const at::Tensor& params,
                                          int64_t kind, int64_t width, int64_t height,
                                          const at::Tensor& background, int64_t threads) {
  check_inputs(means2d, conics, opacities, colors, depths, params, background, kind, width,
               height);
  if (colors.scalar_type() == at::kDouble)
    return forward_t<double>(means2d, conics, opacities, colors, depths, params, kind, width,
                             height, background, threads);
  return forward_t<float>(means2d, conics, opacities, colors, depths, params, kind, width, height,
                          background, threads);
}

std::vector<at::Tensor> rasterize_backward(const std::vector<at::Tensor>& state, int64_t n,
                                           int64_t kind, int64_t width, int64_t height,
                                           const at::Tensor& background, const at::Tensor& v_img,
                                           const at::Tensor& v_alpha, int64_t C, int64_t P,
                                           int64_t threads) {
  TORCH_CHECK(state.size() == size_t(2 + kNumStateBuffers), "cpu rasteriser: bad saved state");
  const auto dt = background.scalar_type();
  TORCH_CHECK(v_img.scalar_type() == dt && v_alpha.scalar_type() == dt &&
                  v_img.is_contiguous() && v_alpha.is_contiguous() &&
                  v_img.numel() == height * width * C && v_alpha.numel() == height * width,
              "cpu rasteriser: gradients must be contiguous [H, W, C] and [H, W, 1]");
  if (dt == at::kDouble)
    return backward_t<double>(state, n, kind, width, height, background, v_img, v_alpha, C, P,
                              threads);
  return backward_t<float>(state, n, kind, width, height, background, v_img, v_alpha, C, P,
                           threads);
}

}  // namespace

void register_ssim_ops(pybind11::module_& m);     // ssim_ops.cpp
void register_project_ops(pybind11::module_& m);  // project_ops.cpp
void register_sh_ops(pybind11::module_& m);       // sh_ops.cpp
void register_learned_ops(pybind11::module_& m);  // learned_ops.cpp
void register_planar_ops(pybind11::module_& m);   // planar_raster.cpp
void register_image_ops(pybind11::module_& m);    // image_splat.cpp

}  // namespace splatk

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "splatk native OpenMP CPU rasteriser";
  m.def("forward", &splatk::rasterize_forward,
        "forward(means2d, conics, opacities, colors, depths, params, kind, width, height, "
        "background, threads) -> [img, alpha, *state]");
  m.def("backward", &splatk::rasterize_backward,
        "backward(state, N, kind, width, height, background, v_img, v_alpha, C, P, threads) -> "
        "[v_means2d, v_conics, v_opacities, v_colors, v_params, v_background]");
  m.def(
      "last_timings",
      []() {
        double t[splatk::kNumPhases];
        splatk::last_timings(t);
        return std::vector<double>(t, t + splatk::kNumPhases);
      },
      "seconds in the last call's phases: bbox, sort, bin, raster, bwd raster, bwd reduce");
  m.def("set_cpu_clock", &splatk::set_cpu_clock,
        "time phases with the calling thread's CPU clock instead of wall time");
  m.def("simd_width", &splatk::simd_width, "vector width the kernels were compiled for (bits)");
  splatk::register_ssim_ops(m);
  splatk::register_project_ops(m);
  splatk::register_sh_ops(m);
  splatk::register_learned_ops(m);
  splatk::register_planar_ops(m);
  splatk::register_image_ops(m);
}
