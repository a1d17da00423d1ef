// float32 entry points of the CPU rasteriser kernels (see raster_impl.h), plus the shared
// phase timers.
#include "raster_impl.h"

namespace splatk {

double g_phase[kNumPhases] = {0};
bool g_cpu_clock = false;

void forward(const ForwardArgs<float>& args, StateAllocator& alloc) { forward_impl(args, alloc); }
void backward(const BackwardArgs<float>& args) { backward_impl(args); }

void last_timings(double out[kNumPhases]) {
  for (int i = 0; i < kNumPhases; ++i) out[i] = g_phase[i];
}
void set_cpu_clock(bool on) { g_cpu_clock = on; }
int simd_width() {
#if defined(__AVX512F__)
  return 512;
#elif defined(__AVX2__)
  return 256;
#else
  return 128;
#endif
}

}  // namespace splatk
