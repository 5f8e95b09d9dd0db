"""Where a fitted cup's floor is: the heights at which the fitted and the exact SDF change sign along vertical lines.

On a generated scene with an exact SDF (``make-collection``, z up), three vertical lines through the middle of the
box (x offsets 0, 0.15 and 0.3 of its half-width) are sampled at 4001 heights; each sign change is printed as a height
in % of the bounding-box diagonal above the box's bottom, for the truth and for each RUN (an SDF fit of that scene).
A cup's floor is the pair of crossings near the bottom; a fit whose first crossing is far above the truth's stopped
its carve at a false floor (BENCHMARKS.md, *Surfaces: carving concavities*, section 25).

Usage::

    .venv/bin/python scripts/probe_floor.py SCENE [RUN ...]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import nerfmeta  # noqa: E402,F401 - before torch, which then spins its OpenMP workers briefly (nerfmeta/__init__.py)
import torch  # noqa: E402

from nerfmeta.geometry.extract import surface_function  # noqa: E402
from nerfmeta.geometry.load import load_run_model  # noqa: E402
from nerfmeta.geometry.truth import scene_sdf_of  # noqa: E402

OFFSETS = (0.0, 0.15, 0.3)
"""x offsets of the vertical lines, in fractions of the box's half-width."""


def sign_changes(values: np.ndarray, heights: np.ndarray) -> list[float]:
    """Heights where ``values`` (N,) along ``heights`` (N,) go from >= 0 to < 0 or back: at each, the first sample on the new side."""
    inside = values < 0
    return [float(h) for h in heights[1:][inside[1:] != inside[:-1]]]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path, help="a generated scene folder (its collection holds the exact SDF)")
    parser.add_argument("runs", nargs="*", type=Path, help="SDF fit runs of that scene")
    args = parser.parse_args(argv)
    found = scene_sdf_of(args.scene)
    if found is None:
        raise SystemExit(f"{args.scene}: not a scene of a generated collection (no exact SDF)")
    sdf, box = found
    diag = float(np.linalg.norm(box[1] - box[0]))
    z = np.linspace(box[0][2], box[1][2], 4001)
    pct = 100 * (z - box[0][2]) / diag
    centre, half = (box[0] + box[1]) / 2, (box[1][0] - box[0][0]) / 2
    lines = [np.stack([np.full_like(z, centre[0] + dx * half), np.full_like(z, centre[1]), z], 1) for dx in OFFSETS]

    def report(name: str, f) -> None:
        parts = [f"x {dx}: " + ", ".join(f"{h:.2f}" for h in sign_changes(f(p), pct)) for dx, p in zip(OFFSETS, lines)]
        print(f"{name}: " + "; ".join(parts))

    report("truth", lambda p: sdf(torch.tensor(p)).numpy())
    for run in args.runs:
        model, scene = load_run_model(run)
        fitted = surface_function(model, scene.bounds).values  # the SDF in the loaded frame
        with torch.no_grad():
            report(str(run), lambda p: fitted(scene.normalization.apply_points(torch.as_tensor(p, dtype=torch.float32))).double().numpy())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
