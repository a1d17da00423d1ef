#!/usr/bin/env bash
# The real-scene benchmark in one command: the kernel grid at two equal-memory budgets on lego,
# fox, cup and bonsai (issue #4's table, issue #6's speed-accuracy charts), then the stability
# matrix on lego, fox and cup (issue #6's heat maps), then every chart and table redrawn.
#
#   benchmarks/bench_real.sh [OUT] [DATA_DIR]
#
# OUT defaults to benchmarks/results/real5, DATA_DIR to ../shared/data. Resumable: finished runs
# are skipped. Settings are chosen so the whole thing fits in about an hour and a half on 2 cores:
#   grid:      presets/bench_kernels.yaml (gaussian, beta, student_t, learned k=2/4/8 at 1 MB and
#              4 MB), 4000 iterations (schedules and 30k-tuned LRs scaled), 1/4 resolution
#              (lego 1/2: it is 400x400)
#   stability: presets/bench_stability.yaml, 1000 iterations, 1/8 resolution (lego 1/4), 5000
#              primitives
# Override with ITERS, DOWNSCALE, STAB_ITERS, STAB_DOWNSCALE, STAB_BUDGET, SCENES, STAB_SCENES.
set -uo pipefail

out=${1:-benchmarks/results/real5}
data=${2:-../shared/data}
iters=${ITERS:-4000}
downscale=${DOWNSCALE:-4}
stab_iters=${STAB_ITERS:-1000}
stab_downscale=${STAB_DOWNSCALE:-8}
stab_budget=${STAB_BUDGET:-5000}
scenes=${SCENES:-"lego fox cup bonsai"}
stab_scenes=${STAB_SCENES:-"lego fox cup"}

# lego is already small (400x400): half the downscale of the photo scenes
half() { python3 -c "print(max(1.0, $1 / 2))"; }

status=0
for s in $scenes; do
  ds=$downscale
  [ "$s" = lego ] && ds=$(half "$downscale")
  splatk bench "$data/$s" --out "$out" --preset bench_kernels --iters "$iters" --downscale "$ds" \
    --metrics psnr,ssim || status=1
done
for s in $stab_scenes; do
  ds=$stab_downscale
  [ "$s" = lego ] && ds=$(half "$stab_downscale")
  splatk bench "$data/$s" --out "$out" --stability --preset bench_stability --iters "$stab_iters" \
    --downscale "$ds" --budget "$stab_budget" --metrics psnr || status=1
done
splatk bench --out "$out" --charts-only || status=1
python3 "$(dirname "$0")/kernel_table.py" "$out" || status=1   # issue #4's table + kernel_table.json
exit $status
