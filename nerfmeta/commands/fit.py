"""``nerfmeta fit``: fit a radiance field to a scene and report PSNR against iterations and time."""

from __future__ import annotations

import argparse
import json
from dataclasses import fields
from pathlib import Path

from tqdm import tqdm

from nerfmeta.data.registry import parse_background
from nerfmeta.errors import ConfigError
from nerfmeta.fields.registry import BACKBONES
from nerfmeta.fit.loop import FitConfig, StepRecord
from nerfmeta.fit.run import RENDERED_VIEWS, RunConfig, default_backbone, run_fit

FREEZE_HELP = (
    "keep the first K layers of the initial model fixed (needs --init category:DIR or meta:DIR; default 0: "
    "fine-tune everything). Layers are ordered input to output. nerf: trunk.0..trunk.{depth-1}, density, "
    "feature, view.0, rgb, so K <= depth freezes the first K trunk layers, K = depth + 1 all of the geometry "
    "(only colour adapts); the small preset has 8 layers. grid: density, features, mlp.0..mlp.{mlp_depth-1}, "
    "so K = 1 freezes the density grid (geometry), K = 2 also the feature grid (only the colour MLP adapts)"
)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    defaults = FitConfig()
    p = subparsers.add_parser(
        "fit",
        help="fit a radiance field to a scene; writes metrics, plots, renders and checkpoints",
        description="Fit a radiance field to SCENE's training views, evaluate on its test views, and write "
        "config.json, metrics.jsonl, summary.json, psnr_vs_iter.png, psnr_vs_time.png and renders/ into RUN.",
    )
    p.add_argument("scene", metavar="SCENE", help="scene folder (or .npz file)")
    p.add_argument("--out", required=True, metavar="RUN", help="run folder to write (must be new or empty)")
    p.add_argument("--backbone", choices=sorted(BACKBONES), default=None,
                   help="grid (DirectVoxGO-style) or nerf (MLP); default: the --init model's backbone, else grid")
    p.add_argument("--init", default="auto", metavar="SPEC",
                   help="starting point: auto (default: classify the scene with the model zoo's classifier and start from "
                   "its category model, or from the meta-learned initialisation for an unknown category; from scratch when "
                   "there is no zoo), scratch, category:DIR (a 'nerfmeta pretrain category' model) or meta:DIR (a "
                   "'nerfmeta meta-train' initialisation); a saved init keeps its backbone config")
    p.add_argument("--zoo", default=None, metavar="DIR",
                   help="model zoo for --init auto (default: $NERFMETA_ZOO, else the model_zoo/ shipped with nerfmeta; "
                   "'none' for no zoo); its manifest's hashes are checked")
    p.add_argument("--compare", default="", metavar="BASELINES",
                   help="also fit these baselines with the identical budget and settings beside an --init auto fit, into "
                   "RUN/compare/NAME, and report PSNR against iterations and time for all (supported: scratch)")
    p.add_argument("--freeze", type=int, default=None, metavar="K", help=FREEZE_HELP + "; with --init auto: the zoo's recommended K "
                   "on the category route")
    p.add_argument("--iters", type=int, default=None, metavar="N",
                   help=f"maximum iterations (default {defaults.iters}; with a zoo, the zoo's)")
    p.add_argument("--time-budget", type=float, default=None, metavar="S", help="stop after S seconds of optimisation")
    p.add_argument("--target-psnr", type=float, default=None, metavar="DB",
                   help="stop once test PSNR reaches DB (checked at every --eval-every evaluation and, unless "
                   "--no-stage-end-eval, when the model ends a stage: a grid whose coarse stage meets DB skips its fine stage)")
    p.add_argument("--stage-end-eval", action=argparse.BooleanOptionalAction, default=defaults.stage_end_eval,
                   help="with --target-psnr, evaluate at the end of each model stage (default on)")
    p.add_argument("--eval-ssim", action=argparse.BooleanOptionalAction, default=defaults.final_ssim,
                   help="compute SSIM at the final evaluation (test_ssim in summary.json; default on)")
    p.add_argument("--renders", type=int, default=RENDERED_VIEWS, metavar="N",
                   help=f"write ground truth | prediction images of the first N test views to RUN/renders/ "
                   f"(default {RENDERED_VIEWS}, 0: none)")
    p.add_argument("--downscale", type=float, default=1.0, metavar="F", help="reduce images by F >= 1 (default 1)")
    p.add_argument("--background", default="white", metavar="COLOUR", help="white, black or R,G,B (default white)")
    p.add_argument("--seed", type=int, default=defaults.seed, help=f"seed of weights, rays and jitter (default {defaults.seed})")
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default cpu)")
    p.add_argument("--batch-rays", type=int, default=None, metavar="N",
                   help=f"rays per iteration (default {defaults.batch_rays}; with a zoo, the zoo's)")
    p.add_argument("--eval-every", type=int, default=None, metavar="N",
                   help=f"test PSNR every N iterations, 0 = only at the end (default {defaults.eval_every}; with a zoo, the zoo's)")
    p.add_argument("--checkpoint-every", type=int, default=defaults.checkpoint_every, metavar="N", help=f"checkpoint every N iterations (default {defaults.checkpoint_every})")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a backbone config field, e.g. --set num_voxels=512000 (repeatable)")
    p.add_argument("--resume", action="store_true", help="continue the run in RUN from its checkpoint")
    p.add_argument("--overwrite", action="store_true", help="replace an existing RUN folder")
    p.set_defaults(func=run)


def parse_overrides(items: list[str], backbone: str) -> dict:
    """``KEY=VALUE`` strings -> dict; values parsed as JSON where possible (numbers, lists, booleans)."""
    names = {f.name for f in fields(BACKBONES[backbone][0])}
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or key not in names:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE with KEY one of {', '.join(sorted(names))}")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def _check_positive(name: str, value: float | None, allow_zero: bool = False) -> None:
    if value is not None and (value < 0 or (value == 0 and not allow_zero)):
        raise ConfigError(f"{name} {value}: must be {'>= 0' if allow_zero else '> 0'}")


class ProgressBar:
    """tqdm bar over iterations (or over the time budget when one is given)."""

    def __init__(self, fit_config: FitConfig):
        self.budget = fit_config.time_budget_s
        self.total = round(self.budget, 1) if self.budget else fit_config.iters
        self.bar = None  # created with the first iteration, so an input error stays a single line

    def __call__(self, record: StepRecord, model, state) -> None:
        if self.bar is None:
            self.bar = tqdm(total=self.total, unit="s" if self.budget else "it", dynamic_ncols=True, leave=True)
        if self.budget:
            self.bar.n = round(min(record.time_s, self.budget), 1)
        else:
            self.bar.n = record.iter
        post = {"iter": record.iter, "psnr": f"{record.train_psnr:.2f}", "t": f"{record.time_s:.1f}s",
                "spr": f"{record.samples_per_ray:.0f}"}
        if record.test_psnr is not None:
            post["test"] = f"{record.test_psnr:.2f}"
        self.bar.set_postfix(post, refresh=False)
        self.bar.refresh()
        if record.event:
            self.bar.write(f"iter {record.iter}: {record.event}")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def fit_settings(args: argparse.Namespace, zoo_fit: dict | None) -> dict:
    """Iterations, rays per iteration and evaluation interval: given on the command line, else the zoo's, else FitConfig's."""
    defaults = FitConfig()
    out = {}
    for name in ("iters", "batch_rays", "eval_every"):
        given = getattr(args, name)
        out[name] = given if given is not None else (zoo_fit or {}).get(name, getattr(defaults, name))
    return out


def _made_by_another_init(out: str) -> bool:
    """True for a run folder whose config.json records no routing decision (made with an explicit --init)."""
    try:
        return "route" not in json.loads((Path(out) / "config.json").read_text())
    except (OSError, ValueError):
        return False  # nothing readable to resume: the auto path says so


def run(args: argparse.Namespace) -> int:
    if args.init == "auto" and args.resume and _made_by_another_init(args.out):
        args.init = "scratch"  # a plain resume: run_fit continues with the init saved in config.json
    if args.init == "auto":
        return run_auto(args)
    if args.compare:
        raise ConfigError("--compare needs --init auto (the routed fit is what a baseline is compared with)")
    if args.zoo is not None:
        raise ConfigError("--zoo is used by --init auto only")
    settings = fit_settings(args, None)
    args.iters, args.batch_rays, args.eval_every = settings["iters"], settings["batch_rays"], settings["eval_every"]
    args.freeze = 0 if args.freeze is None else args.freeze
    for name, value, zero_ok in (("--iters", args.iters, False), ("--time-budget", args.time_budget, False),
                                 ("--batch-rays", args.batch_rays, False), ("--eval-every", args.eval_every, True),
                                 ("--checkpoint-every", args.checkpoint_every, True)):
        _check_positive(name, value, zero_ok)
    _check_positive("--renders", args.renders, allow_zero=True)
    fit_config = FitConfig(
        iters=args.iters, time_budget_s=args.time_budget, target_psnr=args.target_psnr, batch_rays=args.batch_rays,
        seed=args.seed, eval_every=args.eval_every, checkpoint_every=args.checkpoint_every,
        stage_end_eval=args.stage_end_eval, final_ssim=args.eval_ssim,
    )
    backbone = args.backbone or default_backbone(args.init)
    config = RunConfig(
        scene=str(Path(args.scene)), backbone=backbone, model=parse_overrides(args.set, backbone),
        fit=fit_config, downscale=args.downscale, background=parse_background(args.background), device=args.device,
        init=args.init, freeze=args.freeze, renders=args.renders,
    )
    bar = ProgressBar(fit_config)
    try:
        summary = run_fit(config, args.out, resume=args.resume, overwrite=args.overwrite, callbacks=[bar])
    finally:
        bar.close()
    if summary["init"] != "scratch":
        frozen = ", ".join(summary["frozen_layers"]) or "none"
        print(f"started from the {summary['init']} model in {summary['init_path']} (frozen layers: {frozen})")
    print(f"test PSNR {summary['test_psnr']} dB, SSIM {summary['test_ssim']}, {summary['iters']} iterations in "
          f"{summary['time_s']:.1f} s ({summary['stop_reason']}), {summary['samples_per_ray']} samples/ray")
    print(f"results in {args.out}/ (summary.json, metrics.jsonl, psnr_vs_iter.png, psnr_vs_time.png, renders/)")
    return 0


def run_auto(args: argparse.Namespace) -> int:
    """``--init auto``: classify, route, fit (and the baselines of ``--compare``)."""
    from nerfmeta.report.snapshots import SNAPSHOT_ITERS
    from nerfmeta.route import classify_and_fit
    from nerfmeta.zoo import open_zoo

    zoo = open_zoo(args.zoo)
    if zoo is None and args.freeze:
        raise ConfigError(f"--freeze {args.freeze}: there is no model zoo, so --init auto fits from scratch and has no learned "
                          "layers to keep; it needs --init category:DIR or meta:DIR (or --zoo DIR)")
    settings = fit_settings(args, zoo.fit if zoo else None)
    for name, value, zero_ok in (("--iters", settings["iters"], False), ("--time-budget", args.time_budget, False),
                                 ("--batch-rays", settings["batch_rays"], False), ("--eval-every", settings["eval_every"], True),
                                 ("--checkpoint-every", args.checkpoint_every, True)):
        _check_positive(name, value, zero_ok)
    if zoo is not None and args.backbone is not None and args.backbone != zoo.backbone:
        raise ConfigError(f"--backbone {args.backbone}: the model zoo in {zoo.root} holds {zoo.backbone} models; drop --backbone, "
                          f"or use --init scratch")
    backbone = zoo.backbone if zoo is not None else (args.backbone or "grid")
    model = parse_overrides(args.set, backbone)
    if zoo is not None:
        model = {**zoo.fit.get("model", {}), **model}
    _check_positive("--renders", args.renders, allow_zero=True)
    fit_config = FitConfig(
        iters=settings["iters"], time_budget_s=args.time_budget, target_psnr=args.target_psnr, batch_rays=settings["batch_rays"],
        seed=args.seed, eval_every=settings["eval_every"], checkpoint_every=args.checkpoint_every,
        stage_end_eval=args.stage_end_eval, final_ssim=args.eval_ssim,
        eval_views=zoo.fit.get("eval_views", FitConfig().eval_views) if zoo is not None else FitConfig().eval_views,
    )
    compare = tuple(name for name in args.compare.split(",") if name)
    snapshots = tuple(i for i in SNAPSHOT_ITERS if i <= fit_config.iters) if compare else ()
    config = RunConfig(scene=str(Path(args.scene)), backbone=backbone, model=model, fit=fit_config, downscale=args.downscale,
                       background=parse_background(args.background), device=args.device, renders=args.renders,
                       snapshot_iters=snapshots)
    bars: list[ProgressBar] = []

    def callbacks_for(name: str):
        print(f"fitting {'the routed model' if name == 'routed' else 'the ' + name + ' baseline'}:", flush=True)
        if bars:
            bars[-1].close()  # one bar at a time
        bars.append(ProgressBar(fit_config))
        return [bars[-1]]

    def on_route(route) -> None:
        print(f"route: {route.route} ({route.reason})", flush=True)

    try:
        summary = classify_and_fit(config, args.out, zoo=zoo, freeze=args.freeze, compare=compare, resume=args.resume,
                                   overwrite=args.overwrite, callbacks_for=callbacks_for, on_route=on_route)
    finally:
        for bar in bars:
            bar.close()
    print(f"routed ({summary['route']['route']}): test PSNR {summary['test_psnr']} dB, {summary['iters']} iterations in "
          f"{summary['time_s']:.1f} s")
    comparison = summary.get("comparison")
    if comparison:
        for line in comparison.get("headline", []):
            print(line)
    print(f"results in {args.out}/ (summary.json with the route, metrics.jsonl, psnr_vs_iter.png, psnr_vs_time.png, renders/"
          + (", report.md, compare/" if comparison else "") + ")")
    return 0
