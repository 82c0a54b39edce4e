#!/usr/bin/env bash
# Sets up a fresh Linux x86_64 machine for mmf-rl, idempotently:
#   1. system libraries: FFmpeg (torchcodec video decoding), EGL + OSMesa (offscreen MuJoCo);
#   2. uv, then a .venv built exactly from uv.lock, with mmf-rl installed editable.
# A second run does no network work and takes a few seconds.
set -euo pipefail
cd "$(dirname "$0")/.."

APT_PACKAGES=(ffmpeg libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6)
missing=()
for pkg in "${APT_PACKAGES[@]}"; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if ((${#missing[@]})); then
    echo "setup: installing system packages: ${missing[*]}"
    SUDO=""
    [ "$(id -u)" -eq 0 ] || SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

PYTHON="${PYTHON:-python3.11}"
command -v "$PYTHON" >/dev/null || { echo "setup: $PYTHON not found; mmf-rl needs CPython 3.11" >&2; exit 1; }
if ! command -v uv >/dev/null; then
    echo "setup: installing uv"
    "$PYTHON" -m pip install --quiet --disable-pip-version-check uv
fi

# --frozen: install exactly what uv.lock says, never re-resolve on a user's machine.
# --compile-bytecode: uv leaves compiling to the first import, which cannot write the .pyc where the
# environment sets PYTHONDONTWRITEBYTECODE (CI machines do): every process, spawned data and recorder
# workers included, then recompiled torch/tensordict/lerobot from source (7.0 s to import the trainer,
# 3.3 s compiled). The compilation runs once, about 30 s; later syncs skip it.
uv sync --frozen --extra test --python "$PYTHON" --quiet --compile-bytecode
# Versions from package metadata: importing torch/lerobot here would add ~10 s to every `make`.
echo "setup: ready (.venv: $(.venv/bin/python -c 'from importlib.metadata import version as v; print(", ".join(f"{p} {v(p)}" for p in ("torch", "torchrl", "lerobot", "mujoco")))'))"
