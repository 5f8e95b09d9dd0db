"""``nerfmeta render``: a video of a fitted run along a camera path.

The run folder's ``config.json`` and checkpoint give the model; its scene gives the cameras the
path is made from (:mod:`nerfmeta.render.paths`); frames are rendered a few at a time by the same
code that renders test views (:func:`nerfmeta.fit.evaluate.render_view`) and streamed into the
video (:mod:`nerfmeta.render.video`).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import re
import sys
from pathlib import Path

import torch

from nerfmeta.errors import ConfigError

PATHS = ("auto", "orbit", "spiral", "walk", "test")
FRAME_CHUNK = 8
"""Frames rendered per step (each a small scene of their poses; the video takes them as they come)."""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "render",
        help="render a video of a fitted run along an orbit, a spiral, the capture's walk or its test views",
        description="Render RUN (a 'nerfmeta fit' run folder) along a camera path into FILE (.mp4 or .gif). "
                    "orbit: a circle around the point the cameras look at (cameras around an object); spiral: "
                    "LLFF's spiral around the mean camera (forward-facing captures); walk: along the training "
                    "cameras in their order, smoothed (a video's own path; where an unbounded scene's background "
                    "was seen); test: the test views; auto: spiral for a forward-facing capture, walk for an "
                    "unbounded one whose cameras form a walk, else orbit.",
    )
    p.add_argument("run", metavar="RUN", help="run folder written by 'nerfmeta fit'")
    p.add_argument("--out", required=True, metavar="FILE", help="video to write: FILE.mp4 or FILE.gif")
    p.add_argument("--path", choices=PATHS, default="auto", help="camera path (default auto)")
    p.add_argument("--frames", type=int, default=None, metavar="N",
                   help="frames along an orbit, spiral or walk (default 120); --path test renders each test view once")
    p.add_argument("--fps", type=float, default=30.0, metavar="F", help="frames per second (default 30)")
    p.add_argument("--resolution", default="1", metavar="WxH|SCALE",
                   help="frame size: WxH in pixels, or a scale of the run's image size (default 1)")
    p.add_argument("--device", default=None, metavar="DEV", help="torch device (default: the run's)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace FILE if 'nerfmeta render' wrote it (a file it did not write is never replaced)")
    p.set_defaults(func=run)


def parse_resolution(text: str, height: int, width: int) -> tuple[int, int]:
    """``(height, width)`` of the frames: ``WxH`` in pixels, or a positive scale of ``height`` x ``width``."""
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if match:
        w, h = int(match[1]), int(match[2])
        if w < 2 or h < 2 or w * h > 16_000_000:
            raise ConfigError(f"--resolution {text}: width and height must be at least 2 and at most 16 megapixels in all")
        return h, w
    try:
        scale = float(text)
    except ValueError:
        raise ConfigError(f"--resolution {text!r}: expected WxH (e.g. 640x360) or a scale (e.g. 0.5)") from None
    if not (0 < scale <= 16):
        raise ConfigError(f"--resolution {text}: a scale must be in (0, 16]")
    return max(2, round(height * scale)), max(2, round(width * scale))


def check_video_target(out: str, overwrite: bool) -> Path:
    """The video path to write, or a one-line error: not .mp4/.gif, not a writable file path
    (:func:`~nerfmeta.paths.check_output_file`), an existing file without ``overwrite``, or one nerfmeta did not write."""
    from nerfmeta.paths import check_output_file
    from nerfmeta.render.video import made_by_nerfmeta, video_format

    try:
        video_format(out)
    except ValueError as err:
        raise ConfigError(f"--out {err}") from None
    path = check_output_file(out, option="--out")
    if path.exists():
        if not overwrite:
            raise ConfigError(f"--out {path}: exists; pass --overwrite to replace a video 'nerfmeta render' wrote")
        if not made_by_nerfmeta(path):
            raise ConfigError(f"--out {path}: exists and was not written by 'nerfmeta render'; it is never replaced, "
                              "choose another file")
    return path


def load_run(run: Path, device: str | None):
    """``(model, scene, config)`` of a fit run folder: its config, scene (as it was fitted) and checkpoint."""
    from nerfmeta.fit.restore import load_fitted_run

    fitted = load_fitted_run(run, device)
    return fitted.model, fitted.scene, fitted.config


def path_poses(scene, path: str, frames: int) -> tuple[str, torch.Tensor]:
    """``(path name, (n, 4, 4) poses)`` of ``path`` for ``scene`` (``auto`` resolved from its training cameras)."""
    from nerfmeta.render import paths

    train = scene.poses[scene.split_indices("train")].double()
    if path == "auto":  # the kind of capture decides (nerfmeta.data.scene_type)
        if scene.scene_type.kind == "forward":
            path = "spiral"
        else:
            path = "walk" if scene.scene_type.kind == "unbounded" and paths.is_walk(train) else "orbit"
    if path == "walk":
        try:
            return path, paths.walk_path(train, frames)
        except ValueError as err:
            raise ConfigError(f"--path walk: {err}") from None
    if path == "test":
        return path, scene.poses[scene.split_indices("test")].double()
    if path == "orbit":
        try:
            return path, paths.orbit_path(train, frames)
        except ValueError as err:
            raise ConfigError(f"--path orbit: {err}; use --path spiral") from None
    if scene.ndc is not None:  # fitted in NDC: near/far are NDC distances; the world's near bound is kept in the space
        depth = paths.focus_depth(scene.ndc.scene_near, math.inf)
    else:
        depth = paths.focus_depth(scene.near, scene.far)
    return path, paths.spiral_path(train, frames, depth)


def frame_scene(scene, poses: torch.Tensor, height: int, width: int):
    """A scene of ``poses`` (n, 4, 4) with the first view's intrinsics scaled to ``height`` x ``width`` and
    blank targets: what :func:`~nerfmeta.fit.evaluate.render_view` renders."""
    from nerfmeta.data.common import scale_intrinsics

    n = len(poses)
    intrinsics = scale_intrinsics(scene.intrinsics[:1].double(), width / scene.width, height / scene.height)
    return dataclasses.replace(scene, images=torch.zeros(n, height, width, 3), poses=poses.to(scene.poses.dtype),
                               intrinsics=intrinsics.expand(n, 4).to(scene.intrinsics.dtype), alphas=None,
                               splits={"train": tuple(range(n)), "test": ()}, image_names=())


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from nerfmeta.fit.evaluate import render_view
    from nerfmeta.render.video import VideoWriter, even_size

    if args.frames is not None and args.frames < 1:
        raise ConfigError(f"--frames {args.frames}: must be >= 1")
    if not (0 < args.fps <= 240):
        raise ConfigError(f"--fps {args.fps:g}: must be in (0, 240]")
    run_dir = Path(args.run)
    out = check_video_target(args.out, args.overwrite)
    model, scene, config = load_run(run_dir, args.device)
    height, width = parse_resolution(args.resolution, scene.height, scene.width)
    if out.suffix.lower() == ".mp4":
        height, width = even_size(height, width)  # H.264 in yuv420p
    path, poses = path_poses(scene, args.path, args.frames or 120)
    if args.path == "test" and args.frames is not None:
        poses = poses[: args.frames]
    if len(poses) == 0:
        raise ConfigError(f"{run_dir}: the scene has no test views; use --path orbit or spiral")
    background = torch.tensor(config.background, dtype=torch.float32, device=torch.device(config.device))
    with VideoWriter(out, args.fps) as writer, \
            tqdm(total=len(poses), unit="frame", desc=f"render {path}", file=sys.stderr, dynamic_ncols=True) as bar:
        for start in range(0, len(poses), FRAME_CHUNK):
            chunk = frame_scene(scene, poses[start:start + FRAME_CHUNK], height, width)
            frames = [render_view(model, chunk, k, background, chunk=config.fit.chunk_rays).rgb
                      for k in range(chunk.n_views)]
            writer.append(torch.stack(frames).numpy())
            bar.update(len(frames))
        writer.close()
    print(f"wrote {out} ({len(poses)} frames, {path} path, {width}x{height}, {args.fps:g} fps)")
    return 0
