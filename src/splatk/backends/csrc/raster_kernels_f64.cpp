// float64 entry points of the CPU rasteriser kernels (see raster_impl.h). They serve the
// float64 gradcheck only, so they are optimised lightly: at -O3 GCC spends ~3x the compile
// time lowering the 16 x float64 vectors, which the first-use JIT build would pay.
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC optimize("O1")
#endif
#include "raster_impl.h"

namespace splatk {

void forward(const ForwardArgs<double>& args, StateAllocator& alloc) { forward_impl(args, alloc); }
void backward(const BackwardArgs<double>& args) { backward_impl(args); }

}  // namespace splatk
