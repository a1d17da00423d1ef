#!/usr/bin/env bash
# Run `splatk bench` over every scene folder in DATA_DIR into one OUT, then redraw the charts.
#
#   benchmarks/bench_grid.sh DATA_DIR OUT [splatk bench options...]
#
# Examples:
#   benchmarks/bench_grid.sh ../shared/data /tmp/bench --preset bench_kernels --downscale 2 --iters 1000
#   SCENES="lego fox cup" benchmarks/bench_grid.sh ../shared/data /tmp/bench --preset bench_kernels
#   benchmarks/bench_grid.sh ../shared/data /tmp/stab --stability --preset bench_stability --downscale 4
#
# Resumable like `splatk bench` itself: run it again after an interruption and finished runs are
# skipped. A scene that fails is reported and the loop goes on. SCENES limits the loop to those
# folder names; folders that are not scenes (no sparse/ and no transforms*.json) are skipped.
set -uo pipefail

if [ $# -lt 2 ]; then
  sed -n '2,14p' "$0" >&2
  exit 2
fi
data=$1
out=$2
shift 2

status=0
for dir in "$data"/*/; do
  dir=${dir%/}
  name=$(basename "$dir")
  if [ -n "${SCENES:-}" ] && [[ " $SCENES " != *" $name "* ]]; then
    continue
  fi
  if [ ! -d "$dir/sparse" ] && ! compgen -G "$dir/transforms*.json" > /dev/null; then
    echo "skip $dir (not a scene folder)" >&2
    continue
  fi
  echo "== $name" >&2
  if ! splatk bench "$dir" --out "$out" "$@"; then
    echo "splatk bench failed on $dir; continuing" >&2
    status=1
  fi
done
# one set of charts over every result in OUT (the grid; --stability draws its heat maps per scene)
case " $* " in
  *" --stability "*) ;;
  *) splatk bench --out "$out" --charts-only > /dev/null ;;
esac
exit $status
