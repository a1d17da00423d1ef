// Torch-free interface of the CPU rasteriser kernels (raster_kernels.cpp).
//
// Kept apart from the Python binding (rasterize_cpu.cpp) so the kernels compile without the
// torch headers and in parallel with the binding: the headers, not the kernels, dominate the
// first-use build time.
#pragma once

#include <cstdint>

namespace splatk {

enum ProfileKind : int { kGaussian = 0, kBeta = 1, kStudentT = 2, kTable = 3 };

// Buffers the forward pass keeps for the backward pass (allocated by the caller on request,
// since their sizes are only known after binning).
enum StateBuffer : int {
  kOrder = 0,  // [V] int32: depth rank -> primitive id (visible primitives only)
  kPack,       // [V * stride] bytes: per-rank records (bbox, geometry, params, colours)
  kPrimOff,    // [V + 1] int32: first rank-major gradient slot of each rank
  kTileStart,  // [ntiles + 1] int32: tile -> its range of entries
  kEntries,    // [E] int32: ranks, each tile's list in depth order
  kSlot,       // [E] int32: rank-major gradient slot of each entry
  kTileOrder,  // [ntiles] int32: tiles, heaviest first
  kNumStateBuffers
};

struct StateAllocator {
  // Uninitialised storage for `count` elements of `elem_bytes` bytes each (1 or 4).
  virtual void* allocate(int which, int64_t count, int elem_bytes) = 0;
  virtual ~StateAllocator() = default;
};

template <typename S>
struct ForwardArgs {
  int64_t N;
  int W, H, C, P, kind, threads;
  const S* means2d;     // [N, 2]
  const S* conics;      // [N, 3]
  const S* opacities;   // [N]
  const S* colors;      // [N, C]
  const S* params;      // [N, P]
  const S* background;  // [C]
  const void* depths;   // [N] float32 (depths_f32) or float64
  bool depths_f32;
  S* img;          // out [H, W, C]
  S* alpha;        // out [H, W]
  S* T_final;      // out [H, W]
  int32_t* last;   // out [H, W]: entries of the pixel's tile up to its last blended one
};

template <typename S>
struct BackwardArgs {
  int64_t N, V, E;
  int W, H, C, P, kind, threads;
  const S* background;
  const S* T_final;
  const int32_t* last;
  const void* state[kNumStateBuffers];
  const S* v_img;    // [H, W, C]
  const S* v_alpha;  // [H, W]
  S* v_means2d;      // out, zero-initialised by the caller: [N, 2]
  S* v_conics;       // [N, 3]
  S* v_opacities;    // [N]
  S* v_colors;       // [N, C]
  S* v_params;       // [N, P]
  S* v_background;   // [C]
};

void forward(const ForwardArgs<float>& args, StateAllocator& alloc);
void forward(const ForwardArgs<double>& args, StateAllocator& alloc);
void backward(const BackwardArgs<float>& args);
void backward(const BackwardArgs<double>& args);

// Seconds spent in the phases of the last call on this process: bbox, sort, bin, raster,
// backward raster, backward reduce.
constexpr int kNumPhases = 6;
void last_timings(double out[kNumPhases]);
// Time phases with the calling thread's CPU clock instead of wall time (1-thread profiling).
void set_cpu_clock(bool on);
int simd_width();

}  // namespace splatk
