"""``nerfmeta demo``: the README's main job on a scene the project makes itself."""

from __future__ import annotations

import argparse

from nerfmeta.commands.fit import ProgressBar
from nerfmeta.demo import DemoConfig, run_demo
from nerfmeta.fit.loop import FitConfig


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    d = DemoConfig()
    p = subparsers.add_parser(
        "demo",
        help="generate an object scene, inspect it and fit it (the README's main job)",
        description="Generate one procedural object scene, plot its cameras, fit the grid backbone from scratch "
        "with a time budget, and print where the reports are.",
    )
    p.add_argument("--out", default="runs/demo", metavar="DIR", help="output folder (default runs/demo)")
    p.add_argument("--time-budget", type=float, default=d.time_budget_s, metavar="S", help=f"fit time in seconds (default {d.time_budget_s:g})")
    p.add_argument("--category", default=d.category, help=f"object category (default {d.category})")
    p.add_argument("--seed", type=int, default=d.seed, help=f"seed (default {d.seed})")
    p.add_argument("--overwrite", action="store_true", help="replace DIR if it exists")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    config = DemoConfig(category=args.category, time_budget_s=args.time_budget, seed=args.seed)
    bar = ProgressBar(FitConfig(time_budget_s=config.time_budget_s))
    try:
        result = run_demo(config, args.out, overwrite=args.overwrite, callbacks=[bar])
    finally:
        bar.close()
    s = result.summary
    i = result.inspect
    splits = ", ".join(f"{k} {v}" for k, v in i.views_per_split.items())
    print(f"scene: {result.scene} ({i.format}, {splits}, {i.width}x{i.height})")
    print(f"fit: test PSNR {s['test_psnr']} dB, SSIM {s['test_ssim']} after {s['iters']} iterations / {s['time_s']:.1f} s "
          f"({s['samples_per_ray']} samples per ray)")
    print(f"reports: {result.out}/inspect/cameras.png, {result.out}/fit/psnr_vs_iter.png, {result.out}/fit/psnr_vs_time.png, "
          f"{result.out}/fit/renders/, {result.out}/fit/summary.json")
    return 0
