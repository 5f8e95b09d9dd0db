"""``nerfmeta demo``: the README's main job: classify-and-fit two new objects against scratch."""

from __future__ import annotations

import argparse

from nerfmeta.commands.fit import ProgressBar
from nerfmeta.demo import DemoConfig, run_demo
from nerfmeta.fit.loop import FitConfig


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    d = DemoConfig()
    p = subparsers.add_parser(
        "demo",
        help="classify-and-fit two generated objects (a known and an unseen category) against scratch (the README's main job)",
        description="Generate two objects the model zoo has never seen (a known-category one and one of a category the zoo "
        "does not know), run 'nerfmeta fit SCENE --init auto --compare scratch' on each, and gather both into one report.",
    )
    p.add_argument("--out", default="runs/demo", metavar="DIR", help="output folder (default runs/demo)")
    p.add_argument("--zoo", default=None, metavar="DIR", help="model zoo (default: $NERFMETA_ZOO, else the shipped model_zoo/; "
                   "'none' fits from scratch)")
    p.add_argument("--known", default=d.known_category, metavar="CATEGORY", help=f"category of the first object (default {d.known_category})")
    p.add_argument("--unseen", default=d.unseen_category, metavar="CATEGORY", help=f"category of the second object (default {d.unseen_category})")
    p.add_argument("--iters", type=int, default=None, metavar="N", help="iterations per fit (default: the zoo's)")
    p.add_argument("--seed", type=int, default=d.seed, help=f"seed of the objects and fits (default {d.seed}; the zoo is built from 0)")
    p.add_argument("--overwrite", action="store_true", help="replace DIR if it exists")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from nerfmeta.zoo import open_zoo

    zoo = open_zoo(args.zoo)
    if zoo is None:
        print("no model zoo found: fitting both objects from scratch (pass --zoo DIR, or build one with scripts/build_model_zoo)")
    config = DemoConfig(known_category=args.known, unseen_category=args.unseen, iters=args.iters, seed=args.seed)
    bars: list[ProgressBar] = []

    def callbacks_for(scene: str, fit: str):
        print(f"{scene}: fitting {'the routed model' if fit == 'routed' else 'the ' + fit + ' baseline'}", flush=True)
        if bars:
            bars[-1].close()  # one bar at a time
        bars.append(ProgressBar(FitConfig(iters=args.iters or (zoo.fit.get("iters", 300) if zoo else 300))))
        return [bars[-1]]

    def on_route(scene: str, route) -> None:
        print(f"{scene}: route {route.route}: {route.reason}", flush=True)

    try:
        result = run_demo(config, args.out, zoo=zoo, overwrite=args.overwrite, callbacks_for=callbacks_for, on_route=on_route)
    finally:
        for bar in bars:
            bar.close()
    for name, summary in result.summaries.items():
        comparison = summary.get("comparison") or {}
        lines = comparison.get("headline") or [f"test PSNR {summary['test_psnr']} dB after {summary['iters']} iterations"]
        print(f"{name} ({summary['route']['route']} route):")
        for line in lines:
            print(f"  {line}")
        print(f"  report: {result.runs[name]}/report.md" if comparison else f"  results: {result.runs[name]}/")
    if result.report is not None:
        print(f"both scenes: {result.report}")
    return 0
