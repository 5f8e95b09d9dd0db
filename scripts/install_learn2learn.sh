#!/usr/bin/env bash
# Build (once, cached) and install learn2learn 0.2.0 into the given virtual environment.
# Its sdist ships Cython output that does not compile on Python 3.11; regenerating the C files
# from the .pyx sources fixes that. learn2learn's own requirement list pulls gsutil and qpth,
# which nothing we use imports, so the wheel is installed with --no-deps plus the three
# modules its package __init__ really imports (requests, scipy, gym).
# Usage: scripts/install_learn2learn.sh PYTHON
set -euo pipefail
quiet_pip() { "$py" -m pip "$@" 2>&1 | { grep -v "^WARNING: Location" || true; }; }
py=${1:?usage: install_learn2learn.sh PYTHON}
py="$(cd "$(dirname "$py")" && pwd)/$(basename "$py")"  # absolute, but not resolved out of the venv
version=0.2.0
cache=${NERFMETA_WHEEL_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/nerfmeta/wheels}
tag=$("$py" -c 'import sys; print(f"cp{sys.version_info[0]}{sys.version_info[1]}")')
mkdir -p "$cache"
wheel=$(ls "$cache"/learn2learn-$version-$tag-*.whl 2>/dev/null | head -n 1 || true)
if [ -z "$wheel" ]; then
    work=$(mktemp -d)
    trap 'rm -rf "$work"' EXIT
    quiet_pip install -q "cython>=3" wheel setuptools
    quiet_pip download -q --no-deps --no-binary :all: "learn2learn==$version" -d "$work"
    tar -xzf "$work/learn2learn-$version.tar.gz" -C "$work"
    rm -f "$work/learn2learn-$version"/learn2learn/data/*.c
    (cd "$work/learn2learn-$version" && "$py" setup.py -q build_ext bdist_wheel >"$work/build.log" 2>&1) \
        || { tail -n 20 "$work/build.log" >&2; exit 1; }
    cp "$work/learn2learn-$version"/dist/*.whl "$cache/"
    wheel=$(ls "$cache"/learn2learn-$version-$tag-*.whl | head -n 1)
fi
quiet_pip install -q requests scipy gym
quiet_pip install -q --no-deps "$wheel"
echo "learn2learn $version installed from $wheel"
