#!/usr/bin/env bash
# The GPU figures on one GPU machine in one 10-minute call, all outputs in one folder.
#
# Prepare here: `bash scripts/gpu_wheels.sh` (cmat's dependencies the GPU image lacks, and
# pytest, into .whl/). There, in the repository root, with .whl carried:
#   bash benchmarks/gpu.sh OUT
# Everything goes to OUT/gpu.log within GPU_SECONDS (default 570). Compilation, 20-85 s per
# process on an H200 (2026-12-04), made one step after another a 20-minute pass, so the script
# works in two phases:
#   1. every selected step's programs are compiled at once, one background process per step
#      (`--compile-only`), into JAX's persistent compilation cache (JAX_COMPILATION_CACHE_DIR,
#      default /tmp/cmat-jax-cache); the tests run beside them;
#   2. the steps are timed one after another, each as soon as its own programs are compiled,
#      loading them from the cache (the log gives the cache's entries before and after each).
#      A step may still run beside the compilation of a later one: that is host work, apart
#      from XLA's autotuning of the later step's kernels; the log names the background jobs
#      still running when each step starts. Kernels autotuned while several processes share
#      the GPU may be slower choices than one process alone would make.
# JAX's preallocation is off in both phases (the processes share the GPU's memory); the GPU
# allocator's peak that throughput.py reports does not depend on it.
# Training steps/s, peak host memory and the GPU allocator's peak come from
# benchmarks/throughput.py (one process per line, each algorithm at its reference settings).
# The steps, most wanted first:
#   throughput_3s5z_vs_3s6z_large  CMAT, MAT and MAPPO on SMAX 3s5z_vs_3s6z at 8,192
#       environments; CMAT and MAT pass the 819,200-sample minibatch in 8 chunks
#       (`ppo.minibatch_chunks`: the same gradient in less memory), MAPPO whole;
#   throughput_27m_vs_30m          the same three on 27m_vs_30m at 1,024 environments;
#   scaling                        CMAT and MAT agent-scaling points, 3m, 27m_vs_30m, 100m, at 256
#       environments (benchmarks/agent_scaling.py; in OUT/scaling/ its JSON after each point,
#       its table and PNG if the step ends in time);
#   throughput_3s5z_vs_3s6z_small  3s5z_vs_3s6z at 1,024 environments;
#   fleet                          decision latency of dispatch fleets of 100 and 1,000 vehicles:
#       CMAT at m = 2 (cmat's large-team rule; also with 16 inducing points, `k=16`) and m = 5
#       (the dispatch suite's), MAT, Sable and MAPPO, batches of 1 and 64 teams (benchmarks/decision_latency.py, into OUT/fleet/;
#       timed only, in phase 2);
#   fleet_scaling                  training on dispatch fleets of 100, 250, 500 and 1,000
#       vehicles: CMAT at m = 2 (full attention and k = 16), MAT, Sable, MAPPO and the
#       environment alone, at 256 environments (benchmarks/agent_scaling.py, into
#       OUT/fleet_scaling/; points past their time limit are reported as such);
#   tests                          the core properties on the GPU: agent permutation, action
#       masks, chunked gradients, the paper's loss with the joint ratio (phase 1 only).
# GPU_STEPS="NAME ..." runs the named steps alone. GPU_QUICK=1 runs the same steps at CPU sizes:
# a check of the script, not a figure.
set -uo pipefail
out=${1:?usage: gpu.sh OUT}
steps=(throughput_3s5z_vs_3s6z_large throughput_27m_vs_30m scaling throughput_3s5z_vs_3s6z_small
  fleet fleet_scaling tests)
read -ra asked <<< "${GPU_STEPS:-${steps[*]}}"
for name in "${asked[@]}"; do
  [[ " ${steps[*]} " == *" $name "* ]] || {
    echo "GPU_STEPS: unknown step $name (steps: ${steps[*]})" >&2; exit 2; }
done
selected() { [[ " ${asked[*]} " == *" $1 "* ]]; }
chosen=()
for name in "${steps[@]}"; do selected "$name" && chosen+=("$name"); done

start=$(date +%s)
budget=${GPU_SECONDS:-570}
mkdir -p "$out/compile"
exec > >(tee "$out/gpu.log") 2>&1
# shellcheck source=benchmarks/gpu_env.sh
source benchmarks/gpu_env.sh || exit 1
export JAX_COMPILATION_CACHE_DIR=${JAX_COMPILATION_CACHE_DIR:-/tmp/cmat-jax-cache}
export JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0
export XLA_PYTHON_CLIENT_PREALLOCATE=false
trap 'kill $(jobs -p) 2>/dev/null' EXIT

if [ "${GPU_QUICK:-0}" = 1 ]; then
  small=8 large=16 scaling_envs=8 teams="3m 8m" fleets="10" fleet_teams="10 20"
else
  small=1024 large=8192 scaling_envs=256 teams="3m 27m_vs_30m 100m" fleets="100 1000"
  fleet_teams="100 250 500 1000"
fi
export small large scaling_envs teams fleets fleet_teams out PY

compare() {  # compare ENV ENVS ALGO...: throughput.py's algorithm comparison
  local env=$1 envs=$2
  shift 2
  local lines=()
  for algo in "$@"; do lines+=(--algo "$algo"); done
  "$PY" benchmarks/throughput.py --compare-algorithms --env "smax:$env" "${lines[@]}" \
    --set "num_envs=$envs" ${COMPILE_ONLY:+--compile-only}
}
throughput_3s5z_vs_3s6z_large() {
  compare 3s5z_vs_3s6z "$large" cmat:ppo.minibatch_chunks=8 mat:ppo.minibatch_chunks=8 mappo
}
throughput_27m_vs_30m() { compare 27m_vs_30m "$small" cmat mat mappo; }
scaling() {
  local team_list
  read -ra team_list <<< "$teams"
  "$PY" benchmarks/agent_scaling.py --out "$out/scaling" --teams "${team_list[@]}" \
    --envs "$scaling_envs" --updates 1 --lines cmat mat ${COMPILE_ONLY:+--compile-only}
}
throughput_3s5z_vs_3s6z_small() { compare 3s5z_vs_3s6z "$small" cmat mat mappo; }
fleet() {
  [ -n "${COMPILE_ONLY:-}" ] && return 0
  local fleet_list
  read -ra fleet_list <<< "$fleets"
  "$PY" benchmarks/decision_latency.py --out "$out/fleet" --teams "${fleet_list[@]}" \
    --lines "cmat m=2" "cmat m=2 k=16" "cmat m=5" mat sable mappo --batches 1 64 --calls 20 \
    --timeout 60
}
fleet_scaling() {
  local size team_list=()
  for size in $fleet_teams; do team_list+=("dispatch:grid-$size-mid"); done
  "$PY" benchmarks/agent_scaling.py --out "$out/fleet_scaling" --teams "${team_list[@]}" \
    --envs "$scaling_envs" --updates 1 \
    --lines "cmat m=2" "cmat m=2 k=16" mat sable mappo "env only" \
    --point-timeout 120 ${COMPILE_ONLY:+--compile-only}
}
tests() {
  "$PY" -m pytest -q -o addopts= -p no:cacheprovider \
    tests/test_network.py::test_permuting_agents_permutes_policies_and_keeps_value_and_consensus \
    tests/test_network.py::test_masked_actions_have_zero_probability_and_are_never_sampled \
    tests/test_minibatch_chunks.py::test_chunked_minibatch_gives_the_same_loss_and_gradient \
    tests/test_minibatch_chunks.py::test_accumulated_slices_give_the_minibatchs_loss_and_gradient \
    tests/test_cmat_options.py::test_paper_options_give_the_papers_loss
}
export -f compare "${steps[@]}"

elapsed() { echo $(( $(date +%s) - start )); }

declare -A background
echo "== phase 1 at $(elapsed) s: compiling ${chosen[*]} side by side"
for name in "${chosen[@]}"; do
  if [ "$name" = tests ]; then
    timeout "$budget" bash -c tests > "$out/compile/tests.log" 2>&1 &
  else
    COMPILE_ONLY=1 timeout "$budget" bash -c "$name" > "$out/compile/$name.log" 2>&1 &
  fi
  background[$name]=$!
done

running() {  # the background jobs still running
  local name names=()
  for name in "${!background[@]}"; do
    kill -0 "${background[$name]}" 2>/dev/null && names+=("$name")
  done
  echo "${names[*]:-none}"
}

settle() {  # settle NAME: wait for NAME's background job, then print its log
  wait "${background[$1]}"
  echo "== $1, phase 1: exit code $? after $(elapsed) s (124: time limit)"
  cat "$out/compile/$1.log"
}

cached() { find "$JAX_COMPILATION_CACHE_DIR" -type f 2>/dev/null | wc -l; }

step() {  # step NAME LIMIT: NAME timed, within LIMIT and the time left
  local name=$1 limit=$2 left before code
  settle "$name"
  left=$(( budget - $(elapsed) ))
  (( left < limit )) && limit=$left
  if (( limit <= 5 )); then echo "== $name: skipped (time budget spent)"; return; fi
  before=$(cached)
  echo "== $name (at most $limit s; background jobs still running: $(running))"
  timeout "$limit" bash -c "$name"
  code=$?
  echo "== $name: exit code $code after $(elapsed) s (124: time limit); compilation cache" \
    "entries $before before, $(cached) after (equal: nothing compiled afresh, unless a" \
    "background job added some meanwhile)"
}

selected throughput_3s5z_vs_3s6z_large && step throughput_3s5z_vs_3s6z_large 150
selected throughput_27m_vs_30m && step throughput_27m_vs_30m 150
selected scaling && step scaling 200
selected throughput_3s5z_vs_3s6z_small && step throughput_3s5z_vs_3s6z_small 90
selected fleet && step fleet 150
selected fleet_scaling && step fleet_scaling 150
selected tests && settle tests
echo "== done after $(elapsed) s"
ls -la "$out"
