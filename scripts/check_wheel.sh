#!/usr/bin/env bash
# Builds cmat's wheel and installs it into a fresh virtual environment outside the checkout,
# where the command line and the Python API train, evaluate and load a policy from the
# installed package alone (its package data: suite settings, reference results, experiment
# specs, the Manhattan table). Usage: bash scripts/check_wheel.sh [WORK_DIR]
set -euo pipefail
repo=$(cd "$(dirname "$0")/.." && pwd)
work=${1:-$(mktemp -d)}
mkdir -p "$work"
"$repo/.venv/bin/python" -m build --wheel --outdir "$work/dist" "$repo" > "$work/build.log" 2>&1 \
    || { cat "$work/build.log"; exit 1; }
wheel=$(ls "$work"/dist/cmat_marl-*.whl)
python=$(command -v python3.11 || command -v python3)
"$python" -m venv "$work/venv"
"$work/venv/bin/python" -m pip install --quiet --no-compile "$wheel"
cd "$work"  # nothing of the checkout is importable from here
# The processes below import the same modules: the first writes their bytecode for the others.
unset PYTHONDONTWRITEBYTECODE
# What is checked here is the package, not XLA's optimiser: its programs compile unoptimised
# (as the test suite's quick modules do) and into one cache the processes share: the API's run
# below trains the command line's program.
export JAX_DISABLE_MOST_OPTIMIZATIONS=1 XLA_FLAGS="${XLA_FLAGS:-} --xla_cpu_use_fusion_emitters=false"
export JAX_COMPILATION_CACHE_DIR="$work/jax-cache"
export TF_CPP_MIN_LOG_LEVEL=2
"$work/venv/bin/cmat" --version
"$work/venv/bin/cmat" train --env matrix:fig1 --steps 800 --seeds 2 --set ppo.lr=1e-3 \
    --out cli-run > cli.log
"$work/venv/bin/cmat" eval --run cli-run --episodes 2 --seed 1
"$work/venv/bin/cmat" train --env dispatch:manhattan-100-mid --dry-run | tail -1
"$work/venv/bin/cmat" experiment dispatch --dry-run --out grid | tail -1
"$work/venv/bin/python" - <<'PY'
import cmat

assert "/site-packages/" in cmat.__file__, cmat.__file__
run = cmat.train(env="matrix:fig1", steps=800, seeds=2, out="api-run", ppo={"lr": 1e-3})
print(run.metrics.groupby("kind")["episode_return"].last().to_dict())
print(run.evaluate(episodes=2).to_dict("records"))
policy = run.policy()
print("policy", policy.seed, policy.spec.num_agents, "agents;", cmat.__version__, "from",
      cmat.__file__)
PY
echo "wheel check passed: $wheel"
