#!/usr/bin/env bash
# The upper end of cmat's JAX range: a Python 3.12 environment (.venv-latest) with the newest
# JAX that pyproject.toml admits, and the test suite on it. JAX 0.11 and later need Python 3.12;
# .ci/run tests the lower end (Python 3.11, JAX 0.10.2). Arguments go to pytest.
#   bash scripts/test_latest_jax.sh            # the suite CI runs
#   PYTHON=/path/to/python3.12 bash scripts/test_latest_jax.sh tests/test_training.py
set -euo pipefail
cd "$(dirname "$0")/.."
if [ -n "${PYTHON:-}" ]; then
  candidates=("$PYTHON")
else
  candidates=(python3.12 $(ls -d "$(pyenv root 2>/dev/null || echo /nonexistent)"/versions/3.12*/bin/python3.12 2>/dev/null || true))
fi
python=""
for candidate in "${candidates[@]}"; do
  if "$candidate" -c 'import sys; assert sys.version_info[:2] == (3, 12)' 2>/dev/null; then
    python=$candidate
    break
  fi
done
if [ -z "$python" ]; then
  echo "test_latest_jax.sh: no Python 3.12 found (tried ${candidates[*]}); set PYTHON=/path/to/python3.12" >&2
  exit 2
fi
[ -x .venv-latest/bin/python ] || "$python" -m venv .venv-latest
.venv-latest/bin/python -m pip install --quiet --upgrade pip
.venv-latest/bin/python -m pip install --quiet --upgrade --upgrade-strategy eager -e ".[test]"
.venv-latest/bin/python -m pip install --quiet --no-deps "id-marl-eval==0.0.4"
.venv-latest/bin/python -c 'import sys, jax, flax, optax; print(f"Python {sys.version.split()[0]}, jax {jax.__version__}, flax {flax.__version__}, optax {optax.__version__}")'
.venv-latest/bin/python -m pytest -q -p no:cacheprovider "$@"
