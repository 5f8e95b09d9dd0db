"""``nerfmeta make-collection``: generate a procedural ShapeNet-like collection of category scenes."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from nerfmeta.collection.categories import CATEGORIES
from nerfmeta.collection.generate import MAX_RESOLUTION, MIN_RESOLUTION, CollectionConfig, check_output, generate_collection
from nerfmeta.collection.render import RenderConfig
from nerfmeta.errors import ConfigError

_DEFAULT = CollectionConfig()
_DEFAULT_RENDER = RenderConfig()


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "make-collection",
        help="generate a procedural ShapeNet-like collection: many scenes per category, Blender format",
        description=(
            "Sample SDF shapes of each category, render them by sphere tracing and write one "
            "Blender-format scene per shape under OUT, plus OUT/collection.json (every scene's "
            "path, category, split and exact shape parameters). Same arguments, same bytes."
        ),
    )
    parser.add_argument("out", nargs="?", metavar="OUT", help="collection folder to create (absent or empty)")
    parser.add_argument("--list-categories", action="store_true", help="list the categories, one line each, and exit")
    parser.add_argument("--categories", default="all", metavar="A,B,...", help="comma-separated category names, or 'all' (default all)")
    parser.add_argument("--scenes-per-category", type=int, default=_DEFAULT.scenes_per_category, metavar="N", help=f"scenes per category (default {_DEFAULT.scenes_per_category})")
    parser.add_argument("--views", type=int, default=_DEFAULT.views, metavar="V", help=f"training views per scene (default {_DEFAULT.views})")
    parser.add_argument("--test-views", type=int, default=_DEFAULT.test_views, metavar="T", help=f"test views per scene, on other directions (default {_DEFAULT.test_views})")
    parser.add_argument("--resolution", type=int, default=_DEFAULT.resolution, metavar="R", help=f"image size R x R, {MIN_RESOLUTION}..{MAX_RESOLUTION} (default {_DEFAULT.resolution})")
    parser.add_argument("--seed", type=int, default=_DEFAULT.seed, metavar="S", help=f"global seed (default {_DEFAULT.seed})")
    parser.add_argument("--fov", type=float, default=_DEFAULT.fov_degrees, metavar="DEG", help=f"field of view in degrees (default {_DEFAULT.fov_degrees:g})")
    parser.add_argument("--radius", type=float, default=_DEFAULT.radius, metavar="R", help=f"camera distance from the object's centre (default {_DEFAULT.radius:g})")
    parser.add_argument("--full-sphere", action="store_true", help="cameras on the whole sphere instead of the upper hemisphere")
    parser.add_argument("--val-fraction", type=float, default=_DEFAULT.val_fraction, metavar="F", help=f"fraction of each category's scenes in the val split (default {_DEFAULT.val_fraction:g})")
    parser.add_argument("--test-fraction", type=float, default=_DEFAULT.test_fraction, metavar="F", help=f"fraction of each category's scenes in the test split (default {_DEFAULT.test_fraction:g})")
    parser.add_argument("--supersample", type=int, default=_DEFAULT_RENDER.supersample, metavar="K", help=f"K x K rays on edge pixels for anti-aliasing (default {_DEFAULT_RENDER.supersample})")
    parser.add_argument("--specular", type=float, default=_DEFAULT_RENDER.specular, metavar="S", help=f"strength of a soft specular highlight (default {_DEFAULT_RENDER.specular:g}: view-independent)")
    parser.add_argument("--workers", type=int, default=min(os.cpu_count() or 1, 8), metavar="N", help="render N scenes in parallel, one process and one torch thread each (default: CPU count, at most 8)")
    parser.add_argument("--overwrite", action="store_true", help="replace OUT if it already holds a collection")
    parser.add_argument("--preview", action="store_true", help="also write OUT/preview.png, a contact sheet of a few scenes per category")
    parser.set_defaults(func=run)


def parse_categories(text: str) -> tuple[str, ...]:
    """``"all"`` or comma-separated names -> tuple of names (validated later by the config)."""
    if text.strip() == "all":
        return tuple(CATEGORIES)
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    if not names:
        raise ConfigError(f"--categories {text!r} names no category; see --list-categories")
    return names


def run(args: argparse.Namespace) -> int:
    if args.list_categories:
        width = max(len(n) for n in CATEGORIES)
        for name, category in CATEGORIES.items():
            print(f"{name:<{width}}  {category.description}")
        return 0
    if args.out is None:
        raise ConfigError("OUT is required (or pass --list-categories)")
    config = CollectionConfig(
        categories=parse_categories(args.categories),
        scenes_per_category=args.scenes_per_category,
        views=args.views,
        test_views=args.test_views,
        resolution=args.resolution,
        seed=args.seed,
        fov_degrees=args.fov,
        radius=args.radius,
        full_sphere=args.full_sphere,
        val_fraction=args.val_fraction,
        test_fraction=args.test_fraction,
        render=RenderConfig(supersample=args.supersample, specular=args.specular),
    )
    config.validate()
    if args.workers < 1:
        raise ConfigError(f"--workers must be a positive integer, got {args.workers}")
    check_output(Path(args.out), args.overwrite)

    import torch
    from tqdm import tqdm

    n_scenes = len(config.categories) * config.scenes_per_category
    total = n_scenes * (config.views + config.test_views)
    # The tensors are small: intra-op threads cost more than they give (far more on a busy
    # machine), so scenes are parallel across worker processes and each renders on one thread.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with tqdm(total=total, unit="view", desc="make-collection", file=sys.stderr, dynamic_ncols=True) as bar:
            path = generate_collection(
                config, args.out, overwrite=args.overwrite, workers=args.workers, progress=lambda record, n: bar.update(n)
            )
    finally:
        torch.set_num_threads(threads)
    print(f"wrote {n_scenes} scenes ({len(config.categories)} categories) to {path.parent}; index: {path}")
    if args.preview:
        from nerfmeta.collection.preview import write_contact_sheet

        sheet = write_contact_sheet(path.parent, path.parent / "preview.png")
        print(f"contact sheet: {sheet}")
    return 0
