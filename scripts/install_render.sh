#!/usr/bin/env bash
# Installs what `cmat render` needs beyond the Python packages: OSMesa, so MuJoCo draws
# MaMuJoCo episodes headless (MUJOCO_GL=osmesa), and ffmpeg for .mp4 output (GIFs need nothing).
# SMAX and MPE render without it. Debian packages, installed with apt-get when run as root, else
# printed.
#
#   bash scripts/install_render.sh
#   .venv/bin/cmat render --run runs/mamujoco_HalfCheetah-6x1-... --out cheetah.gif
set -euo pipefail

packages=(libosmesa6 ffmpeg)
if [ "$(id -u)" = 0 ]; then
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${packages[@]}"
elif ! dpkg -s "${packages[@]}" > /dev/null 2>&1; then
    echo "install_render.sh: run as root, or install first: sudo apt-get install ${packages[*]}" >&2
    exit 1
fi
