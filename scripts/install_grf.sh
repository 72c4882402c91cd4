#!/usr/bin/env bash
# Builds Google Research Football (gfootball 2.10.2) into .venv, for the `grf:SCENARIO` host envs.
#
# gfootball ships no wheel: pip compiles its C++ engine (about 10 minutes on 2 cores). It needs
# Debian packages (installed here with apt-get when run as root, else printed), and its build
# calls plain `python3`, so it runs inside the activated venv. gym 0.25.2 is pinned: gym 0.26
# changed `reset` and breaks gfootball's wrappers.
#
#   bash scripts/install_grf.sh            # after scripts/setup.sh
#   .venv/bin/python -m pytest -m slow tests/test_host_envs.py -k grf
set -euo pipefail
cd "$(dirname "$0")/.."

packages=(git cmake build-essential libgl1-mesa-dev libsdl2-dev libsdl2-image-dev libsdl2-ttf-dev
          libsdl2-gfx-dev libboost-all-dev libdirectfb-dev libst-dev mesa-utils xvfb python3-dev)
if [ "$(id -u)" = 0 ]; then
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${packages[@]}"
elif ! dpkg -s "${packages[@]}" > /dev/null 2>&1; then
    echo "install_grf.sh: run as root, or install first: sudo apt-get install ${packages[*]}" >&2
    exit 1
fi

[ -x .venv/bin/python ] || bash scripts/setup.sh
# shellcheck disable=SC1091
source .venv/bin/activate
pip install --quiet "setuptools<70" wheel psutil six "gym==0.25.2"
pip install --no-build-isolation "gfootball==2.10.2"
python -c "import gfootball.env; print('gfootball', 'ok')"
