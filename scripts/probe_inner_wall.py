"""Where a fitted cup's inner wall goes wrong: how many training views see it, how thick the true wall is, and how
far the fitted SDF puts it from the truth, by height.

On a generated scene with an exact SDF (``make-collection``), with the body's axis vertical (z up):

- **views**: for oriented points on the true surface, the training cameras that see each one (its normal faces
  the camera, it projects inside the image, and a sphere trace of the exact SDF from it to the camera meets
  nothing), summed up for the inner wall (normals pointing towards the axis, above the lowest 15 % of the
  height) by height band;
- **wall**: the true wall's thickness at mid-height (outer minus inner radius), in % of the bounding-box
  diagonal, and the inner depth over the inner diameter;
- for each RUN (an SDF fit of that scene): the fitted SDF's mean value on the true inner wall and on the true
  outer surface, in % of the diagonal (negative: the true surface lies inside the fitted solid, i.e. the wall
  is too thick there), overall and by height band.

BENCHMARKS.md, *Surfaces: carving concavities*, section 13, has what it measured.

Usage::

    .venv/bin/python scripts/probe_inner_wall.py SCENE [RUN ...] [--points 4000]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import nerfmeta  # noqa: E402,F401 - before torch, which then spins its OpenMP workers briefly (nerfmeta/__init__.py)
import torch  # noqa: E402

from nerfmeta.geometry.extract import surface_function  # noqa: E402
from nerfmeta.geometry.load import load_run_model  # noqa: E402
from nerfmeta.geometry.truth import sample_sdf_surface, scene_sdf_of  # noqa: E402

BANDS = np.arange(0.1, 1.0, 0.2)
"""Lower edges of the height bands (fractions of the object's height) the inner wall is summarised over."""


def views_seeing(sdf, points: torch.Tensor, normals: torch.Tensor, poses: torch.Tensor, focal: float, size: int,
                 diag: float, steps: int = 160) -> torch.Tensor:
    """(N,) number of cameras (poses (V, 4, 4), OpenGL camera-to-world, square ``size`` images) that see each
    surface point (N, 3) with unit normal (N, 3): front-facing, inside the image, no surface between (sphere trace)."""
    count = torch.zeros(len(points), dtype=torch.long)
    for pose in poses:
        centre = pose[:3, 3]
        to_cam = centre - points
        dist = to_cam.norm(dim=-1)
        d = to_cam / dist[:, None]
        local = (points - centre) @ pose[:3, :3]
        z = -local[:, 2]
        in_frame = (z > 0) & ((focal * local[:, :2] / z[:, None]).abs() < size / 2).all(-1)
        s = torch.full_like(dist, 2e-3 * diag)
        free = torch.ones_like(in_frame)
        for _ in range(steps):
            f = sdf(points + d * s[:, None])
            free &= ~((f < 1e-4 * diag) & (s < dist))
            s = s + f.clamp(min=1e-4 * diag)
        count += ((normals * d).sum(-1) > 0.05) & in_frame & free
    return count


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path, help="a generated scene folder (its collection holds the exact SDF)")
    parser.add_argument("runs", nargs="*", type=Path, help="SDF fit runs of that scene")
    parser.add_argument("--points", type=int, default=4000, help="points on the true surface (default 4000)")
    args = parser.parse_args(argv)
    found = scene_sdf_of(args.scene)
    if found is None:
        raise SystemExit(f"{args.scene}: not a scene of a generated collection (no exact SDF)")
    sdf, box = found
    diag = float(np.linalg.norm(box[1] - box[0]))
    surface = sample_sdf_surface(sdf, box, args.points, seed=0)
    meta = json.loads((args.scene / "transforms_train.json").read_text())
    poses = torch.tensor([f["transform_matrix"] for f in meta["frames"]], dtype=torch.float64)
    size = int(json.loads((args.scene.parents[1] / "collection.json").read_text())["camera"]["resolution"])
    focal = 0.5 * size / math.tan(0.5 * meta["camera_angle_x"])
    p, n = torch.tensor(surface.points), torch.tensor(surface.normals)
    views = views_seeing(sdf, p, n, poses, focal, size, diag).numpy()

    pts, nrm = surface.points, surface.normals
    rel = pts[:, :2] - np.median(pts[:, :2], 0)
    radius = np.linalg.norm(rel, axis=1)
    height = (pts[:, 2] - pts[:, 2].min()) / np.ptp(pts[:, 2])
    facing = (nrm[:, :2] * rel).sum(-1) / np.maximum(radius, 1e-12)
    inner, outer = (facing < -0.3) & (height > 0.15), (facing > 0.3) & (height > 0.15)
    mid = (height > 0.4) & (height < 0.6)
    r_in, r_out = np.median(radius[inner & mid]), np.percentile(radius[outer & mid], 30)
    depth = pts[:, 2].max() - pts[inner, 2].min()
    print(f"{args.scene}: wall {100 * (r_out - r_in) / diag:.2f} % of the diagonal at mid-height, inner depth / inner "
          f"diameter {depth / (2 * r_in):.2f}; views seeing a point: inner wall median {np.median(views[inner]):.0f} "
          f"(10th percentile {np.percentile(views[inner], 10):.0f}), outer median {np.median(views[outer]):.0f}, "
          f"unseen {100 * np.mean(views == 0):.1f} % of the surface")
    print("  inner wall by height: " + ", ".join(
        f"{lo:.1f}-{min(lo + 0.2, 1.0):.1f}: median {np.median(views[inner & (height >= lo) & (height < lo + 0.2)]):.0f}" for lo in BANDS))
    for run in args.runs:
        model, scene = load_run_model(run)
        fitted = surface_function(model, scene.bounds).values  # the SDF in the loaded frame, on the run's device
        with torch.no_grad():
            loaded = scene.normalization.apply_points(torch.as_tensor(pts, dtype=torch.float32))
            f = torch.cat([fitted(c) for c in loaded.split(8192)]).double().numpy() / float(scene.normalization.scale)
        pct = 100 * f / diag
        bands = ", ".join(f"{lo:.1f}-{min(lo + 0.2, 1.0):.1f}: {pct[inner & (height >= lo) & (height < lo + 0.2)].mean():+.2f}" for lo in BANDS)
        print(f"  {run}: fitted SDF on the true inner wall {pct[inner].mean():+.2f} %, outer {pct[outer].mean():+.2f} % "
              f"({bands})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
