#!/usr/bin/env bash
# Creates .venv with Python 3.11 and installs cmat with its test extra. The core needs no system
# packages beyond a C compiler-free CPython 3.11 with venv (JAX, JaxMARL and the rest are wheels).
set -euo pipefail
cd "$(dirname "$0")/.."
python=$(command -v python3.11 || command -v python3)
[ -x .venv/bin/python ] || "$python" -m venv .venv
.venv/bin/python -m pip install --quiet --upgrade pip
# --no-compile: Python byte-compiles the modules it imports on first import; pip would compile
# all 16k files of the dependencies up front (35 s on one core here, most never imported).
.venv/bin/python -m pip install --quiet --no-compile -e ".[test]"
# marl-eval (reads the experiments' marl_eval.json in a test) pins pandas==1.4.4, which does not
# build on Python 3.11 with NumPy 2; its code runs on the pandas the marl-eval extra installs.
.venv/bin/python -m pip install --quiet --no-deps "id-marl-eval==0.0.4"
