#!/usr/bin/env bash
# Download, into .whl/, the wheels a GPU machine needs beyond what its image holds (Python 3.12
# with JAX + CUDA, chex, numpy, scipy, matplotlib, pyyaml, tqdm already there): cmat's remaining
# dependencies, flax and optax included (the image's may be older than pyproject.toml allows),
# at the versions this project is tested with. Run it here, where PyPI is reachable;
# benchmarks/gpu_env.sh installs them there (pytest for gpu.sh's tests).
#   bash scripts/gpu_wheels.sh
set -euo pipefail
cd "$(dirname "$0")/.."
grep -qx '/.whl/' .git/info/exclude 2>/dev/null || echo '/.whl/' >> .git/info/exclude
PY=${PYTHON:-.venv/bin/python}
wheels=(
  flax==0.12.8 optax==0.2.8
  distrax==0.1.9 tfp-nightly==0.26.0.dev20261027 dm-tree==0.1.10 gast==0.7.0 decorator==5.3.1
  jaxmarl==0.2.0 gymnax==1.0.1 gymnasium==1.3.0 farama-notifications==0.0.6
  omegaconf==2.4.0 tensorboardX==2.6.5
  pytest==9.2.0 pluggy==1.7.0 iniconfig==2.3.1 pygments==2.21.0 packaging==26.4
)
platforms=()
for n in 17 24 27 28 31 34 35; do platforms+=(--platform "manylinux_2_${n}_x86_64"); done
"$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  "${platforms[@]}" --platform manylinux2014_x86_64 --platform any -d .whl "${wheels[@]}"
ls .whl
du -sh .whl
