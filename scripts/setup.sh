#!/usr/bin/env bash
# Creates .venv with Python 3.11 and installs cmat with its test extra. The core needs no system
# packages beyond a C compiler-free CPython 3.11 with venv (JAX, JaxMARL and the rest are wheels).
set -euo pipefail
cd "$(dirname "$0")/.."
python=$(command -v python3.11 || command -v python3)
[ -x .venv/bin/python ] || "$python" -m venv .venv
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet --no-compile -e ".[test]"
# Bytecode for every installed module and cmat's own, on all cores (33 s on 2 cores when fresh,
# a few seconds when up to date): where PYTHONDONTWRITEBYTECODE is set, as on the project's CI
# machine, Python never writes it, and every process compiled the ~2,400 modules a training run
# imports from source again (6.7 s against 2.7 s with bytecode, 2026-12-07).
.venv/bin/python -m compileall -q -j 0 .venv/lib/python*/site-packages cmat > /dev/null
# marl-eval (reads the experiments' marl_eval.json in a test) pins pandas==1.4.4, which does not
# build on Python 3.11 with NumPy 2; its code runs on the pandas the marl-eval extra installs.
.venv/bin/python -m pip install --quiet --no-deps "id-marl-eval==0.0.4"
