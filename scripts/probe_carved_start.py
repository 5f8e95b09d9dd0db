"""Does the SDF fit keep a concavity it is given? Start an SDF from a carved shape and fit it.

The start: the SDF network regressed (L1, Adam, ``--reg-steps`` batches of 4096 box points) to the signed
distance of a density run's surface (its level set at ``--resolution``^3, Euclidean distance transforms
inside and out), or with ``--truth`` to the generated scene's exact SDF. Then ``--iters`` steps of the
ordinary fit loop (512 rays). Prints, as JSON lines, the hidden concavity left open
(:mod:`nerfmeta.geometry.concavity`) after the regression and after the fit, and the fit's Chamfer at 100k
points and 128^3. BENCHMARKS.md, *Surfaces: carving concavities*, section 1, has what it measured.

Usage::

    .venv/bin/python scripts/probe_carved_start.py DENSITY_RUN SCENE [--iters 500] [--truth] [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nerfmeta.config import build_config, parse_overrides  # noqa: E402
from nerfmeta.fields.grid_ops import interp_cf  # noqa: E402
from nerfmeta.fields.registry import build_model  # noqa: E402
from nerfmeta.fields.sdf import SdfConfig  # noqa: E402
from nerfmeta.fit.loop import FitConfig, fit  # noqa: E402
from nerfmeta.geometry.concavity import concavity_figures  # noqa: E402
from nerfmeta.geometry.extract import grid_values, surface_function  # noqa: E402
from nerfmeta.geometry.load import load_run_model  # noqa: E402
from nerfmeta.geometry.metrics import GeometryConfig  # noqa: E402
from nerfmeta.geometry.runs import evaluate_mesh, mesh_in_file_frame  # noqa: E402
from nerfmeta.geometry.truth import ground_truth, scene_sdf_of  # noqa: E402

RECIPE = {"view_dependent": False, "init_variance": 0.1, "variance_lr": 1e-2}
"""The SDF settings of BENCHMARKS.md's 10-minute fits, which ``--set`` overrides."""


def level_set_distance(values: np.ndarray, level: float, inside_above: bool, cell: np.ndarray) -> torch.Tensor:
    """(R, R, R) signed distance (negative inside) of a lattice's level set, from two distance transforms."""
    from scipy import ndimage

    inside = values > level if inside_above else values < level
    return torch.as_tensor(np.where(inside, -ndimage.distance_transform_edt(inside, sampling=cell),
                                    ndimage.distance_transform_edt(~inside, sampling=cell)), dtype=torch.float32)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("density_run", help="a fit run of a density backbone (e.g. --backbone grid) on SCENE")
    ap.add_argument("scene", help="the generated scene (its exact SDF scores the result)")
    ap.add_argument("--iters", type=int, default=500)
    ap.add_argument("--reg-steps", type=int, default=500)
    ap.add_argument("--resolution", type=int, default=96)
    ap.add_argument("--truth", action="store_true", help="regress to the exact SDF instead of the density's level set")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="SDF config fields over the recipe")
    args = ap.parse_args()

    density, scene = load_run_model(args.density_run)
    exact, _ = scene_sdf_of(args.scene)
    box = scene.bounds.float()
    surface = surface_function(density, box)
    lattice = level_set_distance(grid_values(surface.values, box, args.resolution), surface.level, surface.inside_above,
                                 (box[1] - box[0]).numpy() / (args.resolution - 1))
    norm = scene.normalization
    model = build_model("sdf", build_config(SdfConfig, {**RECIPE, **parse_overrides(args.set, SdfConfig)}), box, seed=0)
    opt = torch.optim.Adam([p for n, p in model.named_parameters() if n != "variance"], lr=1e-3)
    gen = torch.Generator().manual_seed(0)
    for _ in range(args.reg_steps):
        u = torch.rand(4096, 3, generator=gen)
        points = box[0] + (box[1] - box[0]) * u
        target = (exact(norm.invert_points(points.double())) * norm.scale).float() if args.truth else \
            interp_cf(lattice[None], points, box)[:, 0]
        loss = (model.sdf_world(points) - target).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    start = concavity_figures(model, scene, exact)
    print(json.dumps({"stage": "regressed", "l1": round(loss.item(), 4), **dataclasses.asdict(start)}))
    result = fit(model, scene, FitConfig(iters=args.iters, batch_rays=512, eval_every=0, eval_views=2, checkpoint_every=0,
                                         final_lpips=False), background=torch.ones(3))
    mesh = mesh_in_file_frame(model, scene, 128, colors=False)
    metrics = evaluate_mesh(mesh, ground_truth(args.scene, 100_000, resolution=128, seed=1),
                            GeometryConfig(n_points=100_000, resolution=128, floor=False))
    print(json.dumps({"stage": "fitted", "iters": args.iters, "test_psnr": result.final.psnr if result.final else None,
                      "chamfer_pct_diagonal": round(metrics.chamfer_pct_diagonal, 3),
                      **dataclasses.asdict(concavity_figures(model, scene, exact))}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
