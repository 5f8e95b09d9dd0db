"""``nerfmeta inspect``: summarise a scene and optionally plot its cameras."""

from __future__ import annotations

import argparse
import json

from nerfmeta.data.common import LoadOptions
from nerfmeta.data.registry import parse_background
from nerfmeta.data.scene_type import SCENE_TYPES
from nerfmeta.inspect import format_summary, inspect_scene
from nerfmeta.io import to_jsonable


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "inspect",
        help="summarise a scene (format, splits, intrinsics, near/far, bounds) and plot its cameras",
        description="Load a scene (Blender, nerfstudio, LLFF or tiny-NeRF .npz) and report what was read.",
    )
    parser.add_argument("scene", metavar="SCENE", help="scene folder, or a .npz file")
    parser.add_argument("--out", metavar="DIR", help="write DIR/cameras.png and DIR/inspect.json")
    parser.add_argument("--downscale", type=float, default=1.0, metavar="F", help="reduce images by F >= 1 (default 1)")
    parser.add_argument(
        "--background",
        default="white",
        metavar="COLOUR",
        help="white, black or R,G,B in [0, 1]: what RGBA images are composited on (default white)",
    )
    parser.add_argument("--no-normalize", dest="normalize", action="store_false",
                        help="load the scene exactly as written, without moving a scene of extreme scale or far from "
                        "the origin into range (the report's normalisation line says what was applied)")
    parser.add_argument("--scene-type", default="auto", choices=("auto", *SCENE_TYPES),
                        help="kind of capture: auto (detected from the cameras and image borders; default), object, "
                        "forward or unbounded")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    options = LoadOptions(downscale=args.downscale, background=parse_background(args.background), normalize=args.normalize,
                          scene_type=args.scene_type)
    summary = inspect_scene(args.scene, options, out=args.out)
    if args.json:
        print(json.dumps(to_jsonable(summary), indent=2))
    else:
        print(format_summary(summary))
    return 0
