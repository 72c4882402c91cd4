#!/usr/bin/env bash
# Creates .venv with Python 3.11 and installs cmat with its test extra. The core needs no system
# packages beyond a C compiler-free CPython 3.11 with venv (JAX, JaxMARL and the rest are wheels).
set -euo pipefail
cd "$(dirname "$0")/.."
python=$(command -v python3.11 || command -v python3)
[ -x .venv/bin/python ] || "$python" -m venv .venv
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet -e ".[test]"
