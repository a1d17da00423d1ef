// Shared by the fused native ops around the rasteriser (ssim_ops.cpp, project_ops.cpp,
// sh_ops.cpp, learned_ops.cpp): thread counts and input checks. In torch each of those ops is
// dozens of small ops and autograd nodes; at 50k primitives and 400x400 pixels they cost 4x the
// rasteriser itself (benchmarks/train_step.py). Each op is the exact formula of its torch
// reference with a hand-written backward; tests/backends/test_fused_ops.py checks both.
#pragma once

#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <omp.h>
#include <torch/csrc/utils/pybind.h>

#include <algorithm>
#include <cmath>
#include <initializer_list>
#include <optional>
#include <string>
#include <utility>
#include <vector>

namespace splatk {
namespace {

inline int nthreads(int64_t requested, int64_t work, int64_t min_work) {
  if (work < min_work) return 1;
  return requested > 0 ? int(requested) : omp_get_max_threads();
}

inline void check_cpu_float(const at::Tensor& t, at::ScalarType dt, const char* what) {
  TORCH_CHECK(t.device().is_cpu() && t.is_contiguous() && t.scalar_type() == dt, what,
              " must be a contiguous CPU tensor of the inputs' dtype");
}

// Every tensor a contiguous CPU float32 / float64 tensor of the first one's dtype.
inline void check_float_inputs(const char* op,
                        std::initializer_list<std::pair<const at::Tensor*, const char*>> inputs) {
  const auto dt = inputs.begin()->first->scalar_type();
  TORCH_CHECK(dt == at::kFloat || dt == at::kDouble, op, ": float32/64 only");
  for (const auto& [t, name] : inputs) check_cpu_float(*t, dt, (std::string(op) + ": " + name).c_str());
}

}  // namespace
}  // namespace splatk
