#!/usr/bin/env bash
# Everything CI checks, in order: lint, types, no tracked file over 5 MB, the documentation site
# (warnings are errors), the fast test suite, then the built wheel in a fresh virtual
# environment outside the checkout (scripts/check_wheel.sh). Needs .venv (scripts/setup.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
# Python writes the bytecode of what it imports, so the test suite's processes (a hundred
# `cmat` processes and more) read it rather than compile ~2,400 modules each from source, as
# they do where PYTHONDONTWRITEBYTECODE is set (the project's CI machine sets it): 6.7 s
# against 2.7 s for a training run's imports (2026-12-07).
unset PYTHONDONTWRITEBYTECODE
.venv/bin/ruff check .
.venv/bin/mypy
large=$(git ls-files -z | xargs -0 stat -c '%s %n' 2>/dev/null | awk '$1 > 5 * 1024 * 1024')
if [ -n "$large" ]; then
    echo "tracked files over 5 MB (checkpoints and archives travel outside git):" >&2
    echo "$large" >&2
    exit 1
fi
NO_MKDOCS_2_WARNING=1 DISABLE_MKDOCS_2_WARNING=true .venv/bin/mkdocs build --strict --quiet --site-dir "$(mktemp -d)/site"
.venv/bin/python -m pytest -q
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
bash scripts/check_wheel.sh "$work"
