#!/usr/bin/env bash
# The GPU figures, in about 10 minutes on one GPU machine, all outputs in one folder.
#
# Prepare here: `bash scripts/gpu_wheels.sh` (cmat's dependencies the GPU image lacks, and
# pytest, into .whl/). There, in the repository root, with .whl carried:
#   bash benchmarks/gpu.sh OUT
# Steps, most wanted first, each under its own time limit so that the whole stays within
# GPU_SECONDS (default 570; a step that would pass it is cut or skipped) and an interrupted step
# keeps the lines it printed. Training steps/s and peak host memory come from
# benchmarks/throughput.py (one process per line, each algorithm at its reference settings):
#   OUT/throughput_3s5z_vs_3s6z_large.log  CMAT, MAT and MAPPO on SMAX 3s5z_vs_3s6z at 8,192
#       environments; CMAT and MAT pass the 819,200-sample minibatch in 8 chunks
#       (`ppo.minibatch_chunks`: the same gradient in less memory), MAPPO whole;
#   OUT/throughput_27m_vs_30m.log          the same three on 27m_vs_30m at 1,024 environments;
#   OUT/scaling/ and scaling.log           the agent-scaling points of 3m, 27m_vs_30m and 100m
#       (benchmarks/agent_scaling.py; its table, PNG and JSON if the step ends in time) at 256
#       environments;
#   OUT/throughput_3s5z_vs_3s6z_small.log  3s5z_vs_3s6z at 1,024 environments;
#   OUT/tests.log                          the fast core of the test suite (networks, losses,
#       trainer, chunks);
#   OUT/gpu.log                            all of it in order, with the devices and exit codes.
# GPU_QUICK=1 runs the same steps at CPU sizes: a check of the script, not a figure.
set -uo pipefail
out=${1:?usage: gpu.sh OUT}
mkdir -p "$out"
exec > >(tee "$out/gpu.log") 2>&1
# shellcheck source=benchmarks/gpu_env.sh
source benchmarks/gpu_env.sh || exit 1
start=$(date +%s)
budget=${GPU_SECONDS:-570}

if [ "${GPU_QUICK:-0}" = 1 ]; then
  small=8 large=16 scaling_envs=8 teams=(3m 8m)
else
  small=1024 large=8192 scaling_envs=256 teams=(3m 27m_vs_30m 100m)
fi

step() {  # step NAME LIMIT COMMAND...: within LIMIT and the time left, output into OUT/NAME.log
  local name=$1 limit=$2
  shift 2
  local left=$(( budget - ($(date +%s) - start) ))
  (( left < limit )) && limit=$left
  if (( limit <= 5 )); then echo "== $name: skipped (time budget spent)"; return; fi
  echo "== $name (at most $limit s): $*"
  timeout "$limit" bash -c '"$@"' "$name" "$@" 2>&1 | tee "$out/$name.log"
  echo "== $name: exit code ${PIPESTATUS[0]} after $(( $(date +%s) - start )) s (124: time limit)"
}

compare() {  # compare ENV ENVS ALGO...: benchmarks/throughput.py's algorithm comparison
  local env=$1 envs=$2
  shift 2
  local lines=()
  for algo in "$@"; do lines+=(--algo "$algo"); done
  "$PY" benchmarks/throughput.py --compare-algorithms --env "smax:$env" "${lines[@]}" \
    --set "num_envs=$envs"
}
export -f compare
export PY

step throughput_3s5z_vs_3s6z_large 240 compare 3s5z_vs_3s6z "$large" \
  cmat:ppo.minibatch_chunks=8 mat:ppo.minibatch_chunks=8 mappo
step throughput_27m_vs_30m 110 compare 27m_vs_30m "$small" cmat mat mappo
step scaling 120 "$PY" benchmarks/agent_scaling.py --out "$out/scaling" --teams "${teams[@]}" \
  --envs "$scaling_envs" --updates 1
step throughput_3s5z_vs_3s6z_small 60 compare 3s5z_vs_3s6z "$small" cmat mat mappo
step tests 40 "$PY" -m pytest -q -o addopts= -m "not slow" -p no:cacheprovider \
  tests/test_network.py tests/test_training.py tests/test_minibatch_chunks.py \
  tests/test_cmat_options.py
echo "== done after $(( $(date +%s) - start )) s"
ls -la "$out"
