#!/usr/bin/env bash
# The accelerator check of docs/performance.md, run from the repository root on a GPU machine with JAX:
# the step and gradient benchmarks (experiments/bench_gpu.py), then default fits of the reference drop
# (2D, float64, at half its dx and float32) and hanging plate (3D), each timed, then bench_batch.py on the
# device. Every stage shares one wall-clock budget so the script ends inside it; its outputs (8 files:
# what the device machine sends back) go to OUTDIR.
# Usage: experiments/gpu_check.sh OUTDIR [BUDGET_S, default 560]
set -u
out=${1:?usage: experiments/gpu_check.sh OUTDIR [BUDGET_S]}
budget=${2:-560}
mkdir -p "$out"
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1
# Buffers are taken as needed (several processes run one after another on one card).
export XLA_PYTHON_CLIENT_PREALLOCATE=false
py=${PYTHON:-python3}
t0=$(date +%s)
log="$out/log.txt"

left() { echo $((budget - ($(date +%s) - t0))); }

stage() {  # stage NAME LIMIT_S CMD...: run CMD under min(LIMIT_S, time left), log its wall time and exit code
  local name=$1 limit=$2; shift 2
  local rest; rest=$(left)
  [ "$rest" -lt "$limit" ] && limit=$rest
  if [ "$limit" -lt 20 ]; then echo "== $name: skipped, ${rest} s of the budget left" | tee -a "$log"; return 0; fi
  echo "== $name: start (limit ${limit} s): $*" | tee -a "$log"
  local s=$EPOCHREALTIME
  timeout "$limit" "$@" 2>&1 | tee -a "$log"
  local rc=${PIPESTATUS[0]}
  echo "== $name: exit $rc after $(awk "BEGIN{printf \"%.1f\", $EPOCHREALTIME - $s}") s wall" | tee -a "$log"
  return "$rc"
}

{ date -u; nvidia-smi -L; nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm --format=csv
  "$py" -c "import jax, jaxlib, numpy, h5py; print('jax', jax.__version__, 'jaxlib', jaxlib.__version__, 'numpy', numpy.__version__, 'h5py', h5py.__version__); print(jax.devices())"
} 2>&1 | tee -a "$log"

stage step 170 "$py" -m experiments bench_gpu --only step --out "$out/step"
rc=$?
rm -f "$out"/*.md  # the tables are rebuilt from the json (--report)
# A failure in the first minute is a broken setup, not a slow case: stop so the run can be repeated.
if [ "$rc" -ne 0 ] && [ "$rc" -ne 124 ] && [ $(( $(date +%s) - t0 )) -lt 60 ]; then echo "== stopping: the first stage failed at once" | tee -a "$log"; exit 1; fi

data=experiments/reference/data
stage fit_drop_2d 130 "$py" -m jaxfoam fit "$data/drop_2d_set0.h5" --out "$out/fit_drop_2d.json" \
  --log /tmp/fit_drop_2d.fitlog.h5 --no-plots
stage grad 110 "$py" -m experiments bench_gpu --only grad --out "$out/grad"
rm -f "$out"/*.md
stage fit_plate_3d 150 "$py" -m jaxfoam fit "$data/hanging_plate_3d_set0.h5" --out "$out/fit_plate_3d.json" \
  --log /tmp/fit_plate_3d.fitlog.h5 --no-plots
# Half the drop's default dx (0.3 m / 64 / 2).
stage fit_drop_2d_halfdx 120 "$py" -m jaxfoam fit "$data/drop_2d_set0.h5" --dx 0.00234375 \
  --out "$out/fit_drop_2d_halfdx.json" --log /tmp/fit_drop_2d_halfdx.fitlog.h5 --no-plots
stage fit_drop_2d_f32 100 "$py" -m jaxfoam fit "$data/drop_2d_set0.h5" --out "$out/fit_drop_2d_f32.json" \
  --log /tmp/fit_drop_2d_f32.fitlog.h5 --no-plots --dtype float32
# Batched fit-sized rollouts against the 8,192-particle step on this device (bench_batch.py).
stage batch 120 "$py" -m experiments bench_batch --devices 1 --quick --name bench_batch_gpu \
  && cp experiments/results/bench_batch_gpu_quick.json "$out/batch.json"
echo "== done, $(( $(date +%s) - t0 )) s" | tee -a "$log"
