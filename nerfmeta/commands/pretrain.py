"""``nerfmeta pretrain category``: train a category model on the training scenes of one category."""

from __future__ import annotations

import argparse
from pathlib import Path

from nerfmeta.commands.fit import ProgressBar, _check_positive, parse_overrides
from nerfmeta.data.registry import parse_background
from nerfmeta.fields.registry import BACKBONES
from nerfmeta.fit.loop import FitConfig

_FIT = FitConfig()


def add_parser(subparsers: argparse._SubParsersAction) -> None:
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
    c.add_argument("--category", required=True, metavar="C", help="category whose training scenes are used")
    c.add_argument("--out", required=True, metavar="DIR", help="folder to write (must be new or empty)")
    c.add_argument("--backbone", choices=sorted(BACKBONES), default="grid", help="grid (fine stage only) or nerf; default grid")
    c.add_argument("--iters", type=int, default=_FIT.iters, metavar="N", help=f"iterations (default {_FIT.iters})")
    c.add_argument("--batch-rays", type=int, default=_FIT.batch_rays, metavar="N", help=f"rays per iteration, drawn from all scenes (default {_FIT.batch_rays})")
    c.add_argument("--seed", type=int, default=_FIT.seed, help=f"seed of weights, rays and jitter (default {_FIT.seed})")
    c.add_argument("--eval-every", type=int, default=0, metavar="N", help="test PSNR on a few test views every N iterations (default 0: only at the end, on all)")
    c.add_argument("--max-scenes", type=int, default=None, metavar="N", help="use only the first N training scenes (default all)")
    c.add_argument("--downscale", type=float, default=1.0, metavar="F", help="reduce images by F >= 1 (default 1)")
    c.add_argument("--background", default="white", metavar="COLOUR", help="white, black or R,G,B (default white); fit with the same one")
    c.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default cpu)")
    c.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a backbone config field (repeatable)")
    c.add_argument("--checkpoint-every", type=int, default=_FIT.checkpoint_every, metavar="N",
                   help=f"checkpoint every N iterations, for --resume (default {_FIT.checkpoint_every}; 0: only at the end)")
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

    for name, value, zero_ok in (("--iters", args.iters, False), ("--batch-rays", args.batch_rays, False),
                                 ("--eval-every", args.eval_every, True), ("--checkpoint-every", args.checkpoint_every, True)):
        _check_positive(name, value, zero_ok)
    fit_config = FitConfig(iters=args.iters, batch_rays=args.batch_rays, seed=args.seed, eval_every=args.eval_every,
                           checkpoint_every=args.checkpoint_every)
    config = CategoryPretrainConfig(
        collection=str(Path(args.collection)), category=args.category, backbone=args.backbone,
        model=parse_overrides(args.set, args.backbone), fit=fit_config, max_scenes=args.max_scenes,
        downscale=args.downscale, background=parse_background(args.background), device=args.device,
    )
    bar = _LazyBar(fit_config)
    try:
        manifest = pretrain_category(config, args.out, overwrite=args.overwrite, resume=args.resume, callbacks=[bar])
    finally:
        bar.close()
    print(f"category model '{manifest['category']}' ({manifest['backbone']}): {len(manifest['scenes'])} scenes, "
          f"{manifest['steps']} iterations in {manifest['time_s']:.1f} s, test PSNR {manifest['final_psnr']} dB")
    print(f"saved to {args.out}/ (model.safetensors, init.json); fit with: nerfmeta fit SCENE --init category:{args.out}")
    return 0
