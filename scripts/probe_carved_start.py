"""Does the SDF fit keep a concavity it is given? Start an SDF from a carved shape and fit it.

The start: the SDF network regressed (L1, Adam, ``--reg-steps`` batches of 4096 points, half uniform in the box
and half within about 0.03 world units of the target's zero set) to the signed distance of a density run's surface
(its level set at ``--resolution``^3, Euclidean distance transforms inside and out), or with ``--truth`` to the
generated scene's exact SDF. Optionally ``--colour-first`` steps with the SDF network and ``s`` frozen, so the
colour learns the start's geometry. Then ``--iters`` steps of the ordinary fit loop (512 rays). Prints, as JSON
lines after each stage: the hidden concavity left open (:mod:`nerfmeta.geometry.concavity`), ``solid_held`` (the
fraction of points at least 0.004 world units inside the true solid that the network puts inside: a thin wall
the regression has not converged on shows as holes here, not in the concavity), test PSNR, Chamfer at 100k
points and 128^3, and the mean signed distance of the network on the true surface, on the visual hull and on
hidden surface (``offset_*_pct``, % of the diagonal, negative: too fat; :func:`~nerfmeta.geometry.concavity.surface_offsets`). BENCHMARKS.md, *Surfaces: carving concavities*, section 1, and *Surfaces: the open cup* have
what it measured.

Usage::

    .venv/bin/python scripts/probe_carved_start.py DENSITY_RUN SCENE [--iters 500] [--truth] [--colour-first N] [--set KEY=VALUE ...] [--colour-normal grad|detached|zero]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import nerfmeta  # noqa: E402,F401 - before torch, which then spins its OpenMP workers briefly (nerfmeta/__init__.py)
import torch  # noqa: E402

from nerfmeta.config import build_config, parse_overrides  # noqa: E402
from nerfmeta.fields.grid_ops import interp_cf  # noqa: E402
from nerfmeta.fields.registry import build_model  # noqa: E402
from nerfmeta.fields.sdf import SdfConfig  # noqa: E402
from nerfmeta.fit.loop import FitConfig, fit  # noqa: E402
from nerfmeta.geometry.concavity import concavity_figures, surface_offsets  # noqa: E402
from nerfmeta.geometry.extract import grid_values, surface_function  # noqa: E402
from nerfmeta.geometry.load import load_run_model  # noqa: E402
from nerfmeta.geometry.metrics import GeometryConfig  # noqa: E402
from nerfmeta.geometry.runs import evaluate_mesh, mesh_in_file_frame  # noqa: E402
from nerfmeta.geometry.truth import ground_truth, in_loaded_frame, scene_sdf_of  # noqa: E402

RECIPE = {"view_dependent": False, "init_variance": 0.1, "variance_lr": 1e-2}
"""The SDF settings of BENCHMARKS.md's 10-minute fits, which ``--set`` overrides."""


def level_set_distance(values: np.ndarray, level: float, inside_above: bool, cell: np.ndarray) -> torch.Tensor:
    """(R, R, R) signed distance (negative inside) of a lattice's level set, from two distance transforms."""
    from scipy import ndimage

    inside = values > level if inside_above else values < level
    return torch.as_tensor(np.where(inside, -ndimage.distance_transform_edt(inside, sampling=cell),
                                    ndimage.distance_transform_edt(~inside, sampling=cell)), dtype=torch.float32)


def level_set_target(density, box: torch.Tensor, resolution: int):
    """The signed distance (world units) of a density run's surface, as a function of (N, 3) box points."""
    surface = surface_function(density, box)
    lattice = level_set_distance(grid_values(surface.values, box, resolution), surface.level, surface.inside_above,
                                 (box[1] - box[0]).numpy() / (resolution - 1))
    return lambda points: interp_cf(lattice[None], points, box)[:, 0]


def cut_colour_normal(model, mode: str) -> None:
    """Make ``model``'s colour network see the SDF gradient ``detached`` (no photometric gradient reaches the geometry
    through the normal) or as ``zero`` (no normal at all); the eikonal term keeps the true gradient."""
    original = model.get_outputs

    def get_outputs(embedding, sel, directions, ray_idx):
        grad = embedding.grad.detach() if mode == "detached" else torch.zeros_like(embedding.grad)
        return original(dataclasses.replace(embedding, grad=grad), sel, directions, ray_idx)

    model.get_outputs = get_outputs


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("density_run", help="a fit run of a density backbone (e.g. --backbone grid) on SCENE")
    ap.add_argument("scene", help="the generated scene (its exact SDF scores the result)")
    ap.add_argument("--iters", type=int, default=500)
    ap.add_argument("--reg-steps", type=int, default=2400, help="regression steps (800 leave the mug's 1.3-pixel wall "
                    "with holes, solid_held 0.64; 2400 hold it, 0.99)")
    ap.add_argument("--colour-first", type=int, default=0, metavar="N", help="steps fitting only the colour before the joint fit")
    ap.add_argument("--resolution", type=int, default=96)
    ap.add_argument("--truth", action="store_true", help="regress to the exact SDF instead of the density's level set")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="SDF config fields over the recipe")
    ap.add_argument("--colour-normal", choices=("grad", "detached", "zero"), default="grad",
                    help="the normal the colour network sees: the SDF's gradient (the field's own), the same with no "
                         "gradient back into the geometry, or none (zeros): does shading move the surface?")
    args = ap.parse_args()

    density, scene = load_run_model(args.density_run)
    exact, _ = scene_sdf_of(args.scene)
    box = scene.bounds.float()
    exact_loaded = in_loaded_frame(exact, scene.normalization)

    def truth(points: torch.Tensor) -> torch.Tensor:
        return exact_loaded(points).float()

    target_sdf = truth if args.truth else level_set_target(density, box, args.resolution)

    def in_box(n: int, gen: torch.Generator) -> torch.Tensor:
        return box[0] + (box[1] - box[0]) * torch.rand(n, 3, generator=gen)

    model = build_model("sdf", build_config(SdfConfig, {**RECIPE, **parse_overrides(args.set, SdfConfig)}), box, seed=0)
    if args.colour_normal != "grad":
        cut_colour_normal(model, args.colour_normal)
    geometry = [p for n, p in model.named_parameters() if n.startswith(("sdf.", "encoder."))]
    opt = torch.optim.Adam(geometry, lr=1e-3)
    gen = torch.Generator().manual_seed(0)
    pool = in_box(400_000, gen)
    near = pool[target_sdf(pool).abs() < 0.03]
    probe = in_box(400_000, torch.Generator().manual_seed(5))
    solid = probe[truth(probe) < -0.004]
    for _ in range(args.reg_steps):
        points = torch.cat([in_box(2048, gen),
                            near[torch.randint(len(near), (2048,), generator=gen)] + 0.01 * torch.randn(2048, 3, generator=gen)])
        loss = (model.sdf_world(points) - target_sdf(points)).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    reference = ground_truth(args.scene, 100_000, resolution=128, seed=1)

    def report(stage: str, psnr: float | None = None, **extra) -> None:
        with torch.no_grad():
            held = float((model.sdf_world(solid) < 0).float().mean())
        mesh = mesh_in_file_frame(model, scene, 128, colors=False)
        metrics = evaluate_mesh(mesh, reference, GeometryConfig(n_points=100_000, resolution=128, floor=False))
        offsets = {f"offset_{part}_pct": round(f["mean_pct_diagonal"], 3) for part, f in surface_offsets(model, scene, reference).items()}
        print(json.dumps({"stage": stage, **extra, "test_psnr": psnr, "solid_held": round(held, 3),
                          "chamfer_pct_diagonal": round(metrics.chamfer_pct_diagonal, 3), "s": round(float(model.inv_s().detach()), 1),
                          **dataclasses.asdict(concavity_figures(model, scene, exact)), **offsets}), flush=True)

    def run_fit(iters: int) -> float | None:
        result = fit(model, scene, FitConfig(iters=iters, batch_rays=512, eval_every=0, eval_views=2, checkpoint_every=0,
                                             final_lpips=False), background=torch.ones(3))
        return result.final.psnr if result.final else None

    report("regressed", l1=round(loss.item(), 4))
    frozen = geometry + [model.variance]
    if args.colour_first:
        for p in frozen:
            p.requires_grad_(False)
        report("colour-first", run_fit(args.colour_first), iters=args.colour_first)
        for p in frozen:
            p.requires_grad_(True)
    report("fitted", run_fit(args.iters), iters=args.iters)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
