# Sourced by the GPU scripts (benchmarks/gpu.sh, benchmarks/gpu_grid_slice.sh) in the
# repository root of a GPU machine: installs the wheels carried in .whl/ (prepared here by
# scripts/gpu_wheels.sh) next to the image's JAX, puts cmat on PYTHONPATH, and prints the
# devices. Sets PY; returns non-zero when the wheels do not install or JAX does not start.
PY=${PYTHON:-python3}
if [ -d .whl ]; then
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl || return 1
  export PYTHONPATH=/tmp/site:$PWD
else
  export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
fi
export PYTHONUNBUFFERED=1
command -v nvidia-smi >/dev/null && nvidia-smi -L
"$PY" -c "import jax; print('jax', jax.__version__, jax.devices())" || return 1
