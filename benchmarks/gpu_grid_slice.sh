#!/usr/bin/env bash
# A slice of an experiment grid (GPU_SPEC, default smax_benchmark, the results
# page's; cmat/experiments/specs/dispatch_large.yaml holds the 500- and 1,000-vehicle fleets) on one GPU
# machine in about 10 minutes, brought back as one archive per run directory.
#
# Prepare here: `bash scripts/gpu_wheels.sh` (cmat's dependencies the GPU image lacks, into
# .whl/). There, in the repository root, with .whl carried:
#   bash benchmarks/gpu_grid_slice.sh OUT 'smax_2s3z/default/pmat-*' 'smax_2s3z/default/happo-*'
# It runs `cmat experiment ... --only PATTERN...` into GPU_GRID_DIR (default OUT/grid; give a
# folder outside OUT, such as .gpu_grid, and a second call on the same warm machine resumes
# the first call's runs and reuses its compilation cache) for at most GPU_SLICE_SECONDS
# (default 480) with GPU_PARALLEL runs at once (default 7, as many as one call brings back:
# one grid run's batches are far too small to fill the GPU; each run's host side gets its own
# share of the machine's cores, and JAX's preallocation is off so that the runs share the GPU's
# memory; on an H200 the seven PMAT cells, 1M env steps each, finished together in 422 s), then
# writes OUT/RUN.tar.gz for each run directory in the grid folder (at most 7, the rest of the 8
# files a call brings back is OUT/slice.log). Unpack the archives into the CPU grid's directory
# (`tar -xzf RUN.tar.gz -C DIR/runs`): complete runs are reused there, runs cut by the time
# limit resume from their last checkpoint.
# GPU_GRID_FROM=DIR (a grid's runs folder, such as the committed
# experiments/results/smax_benchmark/runs) first copies the run directories there that match
# the patterns and are not yet in the grid, so that runs carried with their checkpoints resume
# on the GPU instead of starting over. Only run directories that changed since this grid last
# archived them are archived, so a second call brings back what the first one could not.
set -uo pipefail
out=${1:?usage: gpu_grid_slice.sh OUT PATTERN...}
shift
[ $# -gt 0 ] || { echo "usage: gpu_grid_slice.sh OUT PATTERN..." >&2; exit 2; }
limit=${GPU_SLICE_SECONDS:-480}
mkdir -p "$out"
exec > >(tee "$out/slice.log") 2>&1
# shellcheck source=benchmarks/gpu_env.sh
source benchmarks/gpu_env.sh || exit 1
start=$(date +%s)
grid=${GPU_GRID_DIR:-$out/grid}
mkdir -p "$grid/runs" "$grid/.archived"
if [ -n "${GPU_GRID_FROM:-}" ]; then
  for pattern in "$@"; do
    for run in "$GPU_GRID_FROM"/$pattern; do
      [ -f "$run/config.yaml" ] || continue
      rel=${run#"$GPU_GRID_FROM"/}
      [ -e "$grid/runs/$rel" ] && continue
      mkdir -p "$grid/runs/$(dirname "$rel")" && cp -r "$run" "$grid/runs/$rel" || exit 1
      touch "$grid/.archived/$(echo "$rel" | sed 's:/:__:g')"
      echo "copied from $GPU_GRID_FROM: $rel"
    done
  done
fi
export XLA_PYTHON_CLIENT_PREALLOCATE=false
timeout "$limit" "$PY" -m cmat experiment "${GPU_SPEC:-smax_benchmark}" --out "$grid" \
  --parallel "${GPU_PARALLEL:-7}" --only "$@"
code=$?
echo "experiment exit code $code after $(( $(date +%s) - start )) s (124: the time limit)"
count=0
for run in "$grid"/runs/*/*/*/; do
  [ -f "$run/config.yaml" ] || continue
  name=$(echo "${run#"$grid"/runs/}" | sed 's:/$::; s:/:__:g')
  stamp=$grid/.archived/$name
  if [ -e "$stamp" ] && [ -z "$(find "$run" -newer "$stamp" -print -quit)" ]; then continue; fi
  if [ $count -ge 7 ]; then echo "not archived (8 files come back at most): $name"; continue; fi
  touch "$stamp"
  tar -czf "$out/$name.tar.gz" -C "$grid/runs" "${run#"$grid"/runs/}"
  count=$((count + 1))
done
ls -la "$out"
