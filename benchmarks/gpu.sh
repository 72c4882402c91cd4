#!/usr/bin/env bash
# The GPU figures on one GPU machine, in 10-minute calls, all outputs in one folder.
#
# Prepare here: `bash scripts/gpu_wheels.sh` (cmat's dependencies the GPU image lacks, and
# pytest, into .whl/). There, in the repository root, with .whl carried:
#   bash benchmarks/gpu.sh OUT
# Steps, most wanted first, each under its own time limit so that the whole stays within
# GPU_SECONDS (default 570; a step that would pass it is cut or skipped) and an interrupted step
# keeps the lines it printed. Everything goes to OUT/gpu.log, each step under a "== NAME" line
# with its command, exit code and the seconds since the start. Training steps/s, peak host
# memory and the GPU allocator's peak come from benchmarks/throughput.py (one process per line,
# each algorithm at its reference settings). The steps:
#   throughput_3s5z_vs_3s6z_large  CMAT, MAT and MAPPO on SMAX 3s5z_vs_3s6z at 8,192
#       environments; CMAT and MAT pass the 819,200-sample minibatch in 8 chunks
#       (`ppo.minibatch_chunks`: the same gradient in less memory), MAPPO whole;
#   throughput_27m_vs_30m          the same three on 27m_vs_30m at 1,024 environments;
#   scaling                        CMAT and MAT agent-scaling points, 3m, 27m_vs_30m, 100m, at 256
#       environments (benchmarks/agent_scaling.py; in OUT/scaling/ its JSON after each point,
#       its table and PNG if the step ends in time);
#   throughput_3s5z_vs_3s6z_small  3s5z_vs_3s6z at 1,024 environments;
#   tests                          the core properties on the GPU (each test compiles its own
#       programs, 15-20 s apiece there): agent permutation, action masks, chunked gradients,
#       the paper's loss with the joint ratio.
# A full pass takes about 20 minutes on one H200 (2026-12-04: each throughput process spent
# 20-85 s compiling; the scaling step finished one point in 120 s), more than one call:
# GPU_STEPS="NAME ..." runs the named steps alone, in the order above, e.g.
# GPU_STEPS="scaling tests" after a call that ran the two throughput steps.
# GPU_QUICK=1 runs the same steps at CPU sizes: a check of the script, not a figure.
set -uo pipefail
out=${1:?usage: gpu.sh OUT}
steps=(throughput_3s5z_vs_3s6z_large throughput_27m_vs_30m scaling throughput_3s5z_vs_3s6z_small
  tests)
read -ra chosen <<< "${GPU_STEPS:-${steps[*]}}"
for name in "${chosen[@]}"; do
  [[ " ${steps[*]} " == *" $name "* ]] || {
    echo "GPU_STEPS: unknown step $name (steps: ${steps[*]})" >&2; exit 2; }
done
selected() { [[ " ${chosen[*]} " == *" $1 "* ]]; }

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

step() {  # step NAME LIMIT COMMAND...: within LIMIT and the time left
  local name=$1 limit=$2
  shift 2
  local left=$(( budget - ($(date +%s) - start) ))
  (( left < limit )) && limit=$left
  if (( limit <= 5 )); then echo "== $name: skipped (time budget spent)"; return; fi
  echo "== $name (at most $limit s): $*"
  timeout "$limit" bash -c '"$@"' "$name" "$@"
  echo "== $name: exit code $? after $(( $(date +%s) - start )) s (124: time limit)"
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

selected throughput_3s5z_vs_3s6z_large && step throughput_3s5z_vs_3s6z_large 240 \
  compare 3s5z_vs_3s6z "$large" cmat:ppo.minibatch_chunks=8 mat:ppo.minibatch_chunks=8 mappo
selected throughput_27m_vs_30m && step throughput_27m_vs_30m 300 \
  compare 27m_vs_30m "$small" cmat mat mappo
selected scaling && step scaling 360 "$PY" benchmarks/agent_scaling.py --out "$out/scaling" \
  --teams "${teams[@]}" --envs "$scaling_envs" --updates 1 --lines cmat mat
selected throughput_3s5z_vs_3s6z_small && step throughput_3s5z_vs_3s6z_small 150 \
  compare 3s5z_vs_3s6z "$small" cmat mat mappo
selected tests && step tests 150 "$PY" -m pytest -q -o addopts= -p no:cacheprovider \
  tests/test_network.py::test_permuting_agents_permutes_policies_and_keeps_value_and_consensus \
  tests/test_network.py::test_masked_actions_have_zero_probability_and_are_never_sampled \
  tests/test_minibatch_chunks.py::test_chunked_minibatch_gives_the_same_loss_and_gradient \
  tests/test_cmat_options.py::test_paper_options_give_the_papers_loss
echo "== done after $(( $(date +%s) - start )) s"
ls -la "$out"
