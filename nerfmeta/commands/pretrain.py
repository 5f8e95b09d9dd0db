"""``nerfmeta pretrain category``: train a category model on the training scenes of one category."""

from __future__ import annotations

import argparse
from pathlib import Path

from nerfmeta import config as options
from nerfmeta.commands.fit import ProgressBar, parse_overrides
from nerfmeta.data.registry import parse_background
from nerfmeta.fields.registry import BACKBONES
from nerfmeta.fit.loop import FitConfig

PRETRAIN_OPTIONS = ("category", "backbone", "max_scenes", "downscale", "background", "device")
"""The ``CategoryPretrainConfig`` fields that are options (the collection is positional; ``model`` is ``--set``)."""
FIT_OPTIONS = ("iters", "batch_rays", "seed", "eval_every", "checkpoint_every")
"""The :class:`FitConfig` fields that are options of a category pretraining."""
FIT_DEFAULTS = {"eval_every": 0, "holdout_tile": 0.0}
"""Where a category pretraining's optimisation settings differ from a fit's defaults (no held-out tiles: a category
model is a start for other scenes, fitted to its scenes' every pixel for its whole length, as the shipped zoo was)."""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    from pretrain.category import CategoryPretrainConfig

    p = subparsers.add_parser(
        "pretrain",
        help="pretrain a starting point for fits: 'pretrain category' trains a category model",
        description="Pretrain models that 'nerfmeta fit --init' starts from.",
    )
    sub = p.add_subparsers(dest="what", metavar="WHAT")
    sub.required = True
    c = sub.add_parser(
        "category",
        help="train one field on all training scenes of a category (its mean shape and appearance)",
        description="Train one radiance field on the rays of all training scenes of category C of COLLECTION together, "
        "in the collection's canonical box, and save it to DIR (model.safetensors, init.json with the manifest entry: "
        "category, scenes used, seed, steps, final PSNR on their test views; config.json, metrics.jsonl, "
        "psnr_vs_iter.png). Start a fit from it with 'nerfmeta fit SCENE --init category:DIR [--freeze K]'.",
    )
    c.add_argument("collection", metavar="COLLECTION", help="collection folder from 'nerfmeta make-collection'")
    c.add_argument("--out", required=True, metavar="DIR", help="folder to write (must be new or empty)")
    options.add_config_options(
        c, CategoryPretrainConfig, only=PRETRAIN_OPTIONS, choices={"backbone": sorted(BACKBONES)},
        parsers={"background": parse_background},
        metavars={"category": "C", "max_scenes": "N", "downscale": "F", "background": "COLOUR", "device": "DEV"},
        notes={"backbone": "the grid trains its fine stage only", "background": "white, black or R,G,B",
               "device": "cpu, cuda or cuda:N"},
        defaults={"max_scenes": "all", "background": "white"},
    )
    options.add_config_options(c, FitConfig, only=FIT_OPTIONS, notes={"batch_rays": "drawn from all scenes"},
                               defaults={"eval_every": "0: only at the end, on all test views"})
    c.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a backbone config field (repeatable; typed and checked like the options; the fields are listed in "
                   "'nerfmeta fit --help')")
    c.add_argument("--resume", action="store_true", help="continue the category run in DIR from its checkpoint")
    c.add_argument("--overwrite", action="store_true", help="replace an existing DIR (only a category run of ours)")
    c.set_defaults(func=run_category)


class _LazyBar:
    """A :class:`ProgressBar` opened at the first iteration, so bad input prints only its error line."""

    def __init__(self, fit_config: FitConfig):
        self.fit_config = fit_config
        self.bar: ProgressBar | None = None

    def __call__(self, record, model, state) -> None:
        if self.bar is None:
            self.bar = ProgressBar(self.fit_config)
        self.bar(record, model, state)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def run_category(args: argparse.Namespace) -> int:
    from pretrain.category import CategoryPretrainConfig, pretrain_category

    fit_config = options.build_config(FitConfig, {**FIT_DEFAULTS, **options.given_values(args, FitConfig)})
    values = options.given_values(args, CategoryPretrainConfig)
    backbone = values.get("backbone", "grid")
    config = options.build_config(CategoryPretrainConfig, {
        **values, "collection": str(Path(args.collection)), "model": parse_overrides(args.set, backbone), "fit": fit_config})
    bar = _LazyBar(fit_config)
    try:
        manifest = pretrain_category(config, args.out, overwrite=args.overwrite, resume=args.resume, callbacks=[bar])
    finally:
        bar.close()
    print(f"category model '{manifest['category']}' ({manifest['backbone']}): {len(manifest['scenes'])} scenes, "
          f"{manifest['steps']} iterations in {manifest['time_s']:.1f} s, test PSNR {manifest['final_psnr']} dB")
    print(f"saved to {args.out}/ (model.safetensors, init.json); fit with: nerfmeta fit SCENE --init category:{args.out}")
    return 0
