"""The scene-format registry: one parser per format, picked by ``detect``.

Each parser module has ``NAME``, ``EXPECTS`` (the files it reads, for error messages),
``detect(path) -> bool`` and ``load(path, options) -> Scene``. :func:`load_scene` tries them in
:data:`FORMATS` order and uses the first that recognises the path.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from nerfmeta.data import blender, colmap, llff, nerfstudio, npz
from nerfmeta.data.common import LoadOptions
from nerfmeta.data.images import DEFAULT_MAX_PIXELS, list_photos, unread_images
from nerfmeta.data.scene import Scene
from nerfmeta.data.video import VIDEO_SUFFIXES
from nerfmeta.errors import ConfigError, SceneError

__all__ = ["FORMATS", "LoadOptions", "SceneFormat", "detect_format", "is_photo_folder", "load_scene",
           "parse_background"]

POSE_TOOLS_HINT = (
    "'nerfmeta poses PHOTOS --out SCENE' computes them from the images (and 'nerfmeta fit PHOTOS' runs it for you), "
    "as do COLMAP (its sparse/0/ beside images/ is read as it is), LLFF's imgs2poses.py (poses_bounds.npy) and "
    "nerfstudio's ns-process-data (transforms.json)"
)


@dataclass(frozen=True)
class SceneFormat:
    """One supported scene format."""

    name: str
    """Recorded in ``Scene.format``."""
    expects: str
    """The files it reads, for error messages."""
    detect: Callable[[Path], bool]
    """True when the path looks like this format."""
    load: Callable[[Path, LoadOptions], Scene]
    """Read the scene; raises SceneError on bad input."""


FORMATS: tuple[SceneFormat, ...] = tuple(
    SceneFormat(m.NAME, m.EXPECTS, m.detect, m.load) for m in (blender, nerfstudio, llff, colmap, npz)
)


def _supported() -> str:
    return "; ".join(f"{f.name}: {f.expects}" for f in FORMATS)


def is_photo_folder(path: str | os.PathLike) -> bool:
    """True for a folder of photos (directly in it or in its ``images/``) without any pose file a parser reads: what
    ``nerfmeta poses`` (and ``nerfmeta fit`` on the way) turns into a scene."""
    path = Path(path)
    return path.is_dir() and not any(fmt.detect(path) for fmt in FORMATS) and bool(list_photos(path))


def detect_format(path: str | os.PathLike) -> SceneFormat:
    """The format of a scene folder or file.

    Raises:
        SceneError: the path is missing, an empty folder, a folder of images without poses, or
            in no supported format (the message lists what each format expects).
    """
    path = Path(path)
    if not path.exists():
        raise SceneError(f"{path}: scene not found")
    for fmt in FORMATS:
        if fmt.detect(path):
            return fmt
    if path.is_dir():
        if not any(path.iterdir()):
            raise SceneError(f"{path}: folder is empty (supported formats: {_supported()})")
        if list_photos(path):
            raise SceneError(
                f"{path}: has images but no camera poses: add transforms_train.json (Blender), "
                f"transforms.json (nerfstudio) or poses_bounds.npy (LLFF); {POSE_TOOLS_HINT}"
            )
        if other := unread_images(path) or unread_images(path / "images"):
            found = ", ".join(f"{n} {suffix}" for suffix, n in other.items())
            raise SceneError(f"{path}: holds images nerfmeta does not read ({found} files); it reads PNG, JPEG and "
                             "HEIC/HEIF photos: convert them to one of those (e.g. JPEG)")
    if path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES:
        raise SceneError(f"{path}: a video, not a scene: 'nerfmeta poses {path} --out SCENE' makes a scene of its "
                         "frames ('nerfmeta fit' and 'nerfmeta classify' take the video as it is)")
    raise SceneError(f"{path}: unknown scene format (supported formats: {_supported()})")


def load_scene(
    path: str | os.PathLike,
    *,
    downscale: float = 1.0,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    max_pixels: int = DEFAULT_MAX_PIXELS,
    normalize: bool = True,
    scene_type: str = "auto",
    max_side: int = 0,
) -> Scene:
    """Read a scene in any supported format.

    Args:
        path: a scene folder (Blender, nerfstudio, LLFF) or a ``.npz`` file.
        downscale: reduce images by this factor (>= 1, area filtering); intrinsics follow.
        background: RGB in [0, 1] that RGBA images are composited on.
        max_pixels: refuse images with more pixels than this.
        normalize: move a scene of extreme scale or far from the origin into range (the identity
            for scenes already in range; see :mod:`nerfmeta.data.normalize`).
        scene_type: ``auto`` or the kind of capture (see :mod:`nerfmeta.data.scene_type`).
        max_side: reduce images further while their longest side exceeds it (0: no limit; see
            :attr:`LoadOptions.max_side`).

    Raises:
        ConfigError: a bad option. SceneError: a bad or unsupported scene (one line, naming the
            file and what is wrong).
    """
    options = LoadOptions(downscale=downscale, background=background, max_pixels=max_pixels, normalize=normalize,
                          scene_type=scene_type, max_side=max_side)
    return load_scene_with(path, options)


def load_scene_with(path: str | os.PathLike, options: LoadOptions) -> Scene:
    """:func:`load_scene` taking a :class:`LoadOptions`."""
    path = Path(path)
    return detect_format(path).load(path, options)


def parse_background(text: str) -> tuple[float, float, float]:
    """``white``, ``black`` or ``R,G,B`` (three numbers in [0, 1]) as an RGB tuple.

    Raises:
        ConfigError: anything else.
    """
    named = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}
    key = text.strip().lower()
    if key in named:
        return named[key]
    parts = key.split(",")
    try:
        rgb = tuple(float(p) for p in parts)
    except ValueError:
        rgb = ()
    if len(rgb) != 3 or not all(math.isfinite(v) and 0.0 <= v <= 1.0 for v in rgb):
        raise ConfigError(f"background {text!r} must be white, black or R,G,B with values in [0, 1]")
    return rgb  # type: ignore[return-value]
