"""How much is a better *shape* worth as the voxel grid's start? The true occupancy, the visual hull, a learned guess.

Issue #17's carved start (:mod:`nerfmeta.priors`) starts the coarse grid from the visual hull of the training views,
and it ends level with the scratch grid or below it on concave objects. This probe measures what a start of the
*right* shape would give, and how much of that a small network over the views recovers. Each arm starts the coarse
grid as the carved start does (alpha :data:`~nerfmeta.priors.start.HULL_ALPHA` a step on the occupied points,
:data:`~nerfmeta.priors.start.EMPTY_ALPHA` elsewhere, the mean colour the points project to, the carve's 100 coarse
steps); only *which* points are occupied differs:

- ``scratch``: no start (the tuned defaults); ``carve``: the shipped carved start (`--init carve`);
- ``truth:D``: a generated scene's exact SDF below ``D`` coarse voxels (the oracle: what no view-based start can beat);
- ``hull:M:K``: the visual hull with masks dilated by ``M`` pixels, then grown by ``K`` voxels in 3-D;
- ``net:WEIGHTS[:TAU]``: :mod:`nerfmeta.priors.occupancy`'s learned start, a small 3-D CNN over per-voxel multi-view features
  (how many views see the point and show foreground there, the mean and spread of the
  colours it projects to), trained by ``train`` on a generated collection to predict the ``truth:1`` occupancy;
  the points it gives above ``TAU``, within the visual hull (2-pixel masks, grown a voxel).

``fit`` prints one JSON line: test PSNR on all test views at fixed iterations (the fit is as long as the last mark,
its learning rate decaying over it; one torch thread, seed 0: the
figures do not depend on the machine's load). BENCHMARKS.md, *Grid priors: what a right shape is worth*, has what
it measured.

Usage::

    .venv/bin/python scripts/probe_occupancy_start.py train COLLECTION [COLLECTION ...] --out NET.safetensors [--width 16] [--steps 2000]
    .venv/bin/python scripts/probe_occupancy_start.py fit SCENE ARM [--marks 50 100 200 400 700 1000] [--coarse-iters N] [--set KEY=VALUE]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import nerfmeta  # noqa: E402,F401 - before torch, which then spins its OpenMP workers briefly (nerfmeta/__init__.py)
import torch  # noqa: E402

from nerfmeta.data import load_scene  # noqa: E402
from nerfmeta.fields.grid_ops import dilate  # noqa: E402
from nerfmeta.fields.registry import build_model  # noqa: E402
from nerfmeta.fields.voxel_grid import VoxelGridConfig  # noqa: E402
from nerfmeta.fit.evaluate import evaluate_views  # noqa: E402
from nerfmeta.fit.loop import FitConfig, fit  # noqa: E402
from nerfmeta.priors.carve import SEEN_FRACTION, dilate_masks, start_colours, visual_hull  # noqa: E402
from nerfmeta.config import parse_overrides  # noqa: E402
from nerfmeta.errors import ConfigError  # noqa: E402
from nerfmeta.io import save_tensors  # noqa: E402
from nerfmeta.priors.occupancy import grid_views, learned_grid_start, load_occupancy_net  # noqa: E402
from nerfmeta.priors.start import CARVE_COARSE_ITERS, carve_grid_start, load_occupied_start  # noqa: E402
from pretrain.occupancy import (OccupancyTrainConfig, occupancy_volume, print_log,  # noqa: E402
                                train_occupancy_net, true_distance)

def train(args: argparse.Namespace) -> int:
    """Fit :class:`OccupancyNet` to every scene of the collections (:func:`pretrain.occupancy.train_occupancy_net`)."""
    from nerfmeta.collection.generate import load_collection

    if args.out.exists():  # never over a file this command did not write now
        raise SystemExit(f"{args.out}: already exists; name a new file for the network")
    config = OccupancyTrainConfig(width=args.width, steps=args.steps, pos_weight=args.pos_weight, seed=args.seed)
    volumes = [occupancy_volume(c.root / r.path) for c in map(load_collection, args.collections) for r in c.scenes]
    print(f"{len(volumes)} scenes", flush=True)
    net, _ = train_occupancy_net(volumes, config, on_log=print_log)
    save_tensors(args.out, net.state_dict())  # atomically
    return 0


def occupied_points(arm: str, scene_path: Path, scene, model) -> torch.Tensor:
    """(N,) bool: the coarse points the arm ``truth:D`` or ``hull:M:K`` starts occupied."""
    kind, *params = arm.split(":")
    if kind == "truth":
        return (true_distance(scene_path, scene, model) < float(params[0])).reshape(-1)
    if kind == "hull":
        views = grid_views(model, scene)
        inside, seen = visual_hull(views.points, dilate_masks(views.masks, int(params[0])), views.poses, views.intrinsics)
        return dilate((inside & (seen >= SEEN_FRACTION)).view(model.size), int(params[1])).reshape(-1)
    raise SystemExit(f"unknown arm {arm!r}: scratch, carve, truth:D, hull:M:K or net:WEIGHTS[:TAU]")


def start(arm: str, scene_path: Path, scene, background: torch.Tensor, coarse_iters: int | None = None,
          overrides: dict | None = None):
    """The arm's model, started, and a note (what it occupied, how long building it took); ``coarse_iters`` None: the
    carve's coarse stage for the starts (:data:`~nerfmeta.priors.start.CARVE_COARSE_ITERS`), the defaults for scratch;
    ``overrides``: other grid settings (``--set``), applied last, so they win as ``nerfmeta fit --set`` does."""
    config = VoxelGridConfig().for_scene(scene)
    if arm != "scratch" or coarse_iters is not None:
        config = dataclasses.replace(config, coarse_iters=CARVE_COARSE_ITERS if coarse_iters is None else coarse_iters)
    config = dataclasses.replace(config, **(overrides or {}))
    model = build_model("grid", config, scene.bounds, seed=0)
    if arm == "scratch":
        return model, "no start" if coarse_iters is None and not overrides else f"no start, {config.coarse_iters} coarse steps"
    if arm == "carve":
        return model, carve_grid_start(model, scene, background).reason
    if arm.startswith("net:"):
        weights, _, tau = arm[4:].partition(":")
        report = learned_grid_start(model, scene, background, load_occupancy_net(weights),
                                    **({"threshold": float(tau)} if tau else {}))
        return model, f"{report.reason}, built in {report.build_s:.2f} s"
    t0 = time.perf_counter()
    occ = occupied_points(arm, scene_path, scene, model)
    views = grid_views(model, scene)
    load_occupied_start(model, occ, start_colours(occ, views.points, views.masks, views.images, views.poses,
                                                  views.intrinsics, background))
    return model, f"{100 * float(occ.float().mean()):.1f}% of the coarse grid occupied, built in {time.perf_counter() - t0:.2f} s"


def fit_arm(args: argparse.Namespace) -> int:
    """One arm on one scene: test PSNR at the marked iterations, one JSON line."""
    overrides = parse_overrides(args.set, VoxelGridConfig)  # a bad setting named before the scene is read
    scene = load_scene(args.scene)
    background = torch.tensor(scene.background, dtype=torch.float32)
    model, note = start(args.arm, Path(args.scene), scene, background, args.coarse_iters, overrides)
    views = list(scene.splits["test"])
    psnr: dict[int, float] = {}

    def evaluate(step: int) -> None:
        psnr[step] = round(evaluate_views(model, scene, views, background, with_ssim=False).psnr, 3)
        model.train()

    def callback(record, model_, state) -> None:
        if record.iter in args.marks and record.iter not in psnr:
            evaluate(record.iter)

    evaluate(0)
    result = fit(model, scene, FitConfig(iters=max(args.marks), eval_every=0, checkpoint_every=0, final_ssim=False),
                 background=background, callbacks=[callback])
    psnr[max(args.marks)] = round(result.final.psnr, 3)
    print(json.dumps({"scene": str(args.scene), "arm": args.arm, "note": note, "psnr": psnr}))
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    t = sub.add_parser("train", help="train the occupancy network on generated collections")
    t.add_argument("collections", nargs="+", help="folders made by `nerfmeta make-collection`")
    t.add_argument("--out", required=True, type=Path)
    t.add_argument("--width", type=int, default=16)
    t.add_argument("--steps", type=int, default=2000)
    t.add_argument("--pos-weight", type=float, default=3.0, help="weight of the occupied points' loss (recall first)")
    t.add_argument("--seed", type=int, default=0)
    f = sub.add_parser("fit", help="fit one scene from one arm's start")
    f.add_argument("scene", help="a generated scene (truth arms need its collection.json)")
    f.add_argument("arm", help="scratch, carve, truth:D, hull:M:K or net:WEIGHTS:TAU")
    f.add_argument("--marks", type=int, nargs="+", default=[50, 100, 200, 400, 700, 1000])
    f.add_argument("--coarse-iters", type=int, default=None, metavar="N",
                   help="coarse steps of the arm's grid (default: the carve's 100 for the starts, the defaults for "
                   "scratch; --init occupancy keeps 200)")
    f.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a grid setting, as `nerfmeta fit --set` takes it (e.g. growth_density=project)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    try:
        return train(args) if args.command == "train" else fit_arm(args)
    except ConfigError as err:
        raise SystemExit(str(err)) from None


if __name__ == "__main__":
    sys.exit(main())
