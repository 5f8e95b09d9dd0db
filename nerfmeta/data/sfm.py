"""Camera poses from a folder of photos: structure from motion with pycolmap.

``PHOTOS/`` (PNG, JPEG or HEIC/HEIF; no pose file) -> ``SCENE/``, a nerfstudio scene that
:mod:`nerfmeta.data.nerfstudio` reads::

    SCENE/transforms.json        fl_x, fl_y, cx, cy, w, h (PINHOLE), near, far, frames[file_path, transform_matrix]
    SCENE/images/NAME            the photos as fitted: EXIF orientation applied, longest side at most
                                 ``max_side``, undistorted when the camera model has distortion (a HEIC/HEIF
                                 photo becomes ``STEM.jpg``: COLMAP does not read HEIF)
    SCENE/colmap/                the sparse model those poses come from (cameras/images/points3D.bin)
    SCENE/sfm.json               what happened: photos, registered, unregistered, reprojection error, seconds per phase,
                                 the matcher kept and any jumps of a walk left

The phases (:func:`compute_poses`): read every photo (one line naming a file Pillow cannot read,
or photos of different sizes) and write the prepared copies; SIFT features; matching (every pair, or
neighbours in file-name order for a video's frames); incremental mapping (the largest model is kept);
undistortion; conversion. No vocabulary tree is used (nothing is downloaded). The default matcher,
``auto``, matches every pair and, when the model folds a walk (:func:`walk_jumps`: neighbours more than
90 degrees apart, as look-alike sides of a symmetric scene make it), matches neighbours only, reusing
the features, and keeps the model that folds less. COLMAP's mapping is not repeatable on several
threads, and a draw of it can bend a walk at one photo (on beer from 1 draw in 4 to every draw, with the
matches of different runs, turned part of the walk 10-15 degrees, with a normal reprojection error); so the neighbours'
matches are mapped ``map_draws`` times, and once more by GLOMAP's global mapper (``global_draw``: some
runs' matches bend the incremental mapper on most seeds), and the draw kept whose poses explain the most
of every pair's verified matches (:func:`match_agreement`: the far pairs, which the neighbours' model
never saw, tell a whole walk from a bent one).

Conventions (:func:`opengl_camera_to_world`): COLMAP stores world-to-camera ``(q, t)`` with the
OpenCV camera (x right, y down, looking along +z); nerfmeta, like nerfstudio, uses OpenGL
camera-to-world matrices (x right, y up, looking along -z). The world is turned as nerfstudio's
``colmap_to_json`` turns it (:data:`WORLD_FROM_COLMAP`: COLMAP's y, z become -z, y).

The SfM scene is written through :mod:`nerfmeta.runfolder` (kind ``poses``), built aside and
swapped in complete, so a failure leaves nothing half-written; the photo folder is only read.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import numbers
import os
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterator, Literal, Sequence

import numpy as np
from PIL import Image

from nerfmeta.config import bounded
from nerfmeta.data.images import (EXIF_ORIENTATION, HEIF_SUFFIXES, MAX_SIDE, decode_array, image_shape, list_photos,
                                  read_exif)
from nerfmeta.errors import SceneError
from nerfmeta.io import write_json
from nerfmeta.runfolder import run_folder

log = logging.getLogger(__name__)

TRANSFORMS = "transforms.json"
REPORT = "sfm.json"
IMAGES = "images"
COLMAP = "colmap"
MIN_PHOTOS = 3
"""Fewest photos structure from motion is attempted on (two give a pair, not a scene to fit)."""
WALK_STEP_DEG = 30.0
"""Photos whose median turn between file-name neighbours is at most this are a walk (a video's frames)."""
JUMP_DEG = 90.0
"""A turn of the viewing direction above this between neighbours of a walk is a jump (:func:`walk_jumps`)."""
WORLD_FROM_COLMAP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""The rotation applied to COLMAP's world, as nerfstudio's ``colmap_to_json`` applies it (rows 0, 2, 1; the last negated)."""
OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0])
"""Camera axes: OpenCV (x right, y down, z forward) to OpenGL (x right, y up, z backward)."""
DISTORTION_MODELS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
}
"""The COLMAP camera models read here and the order of their parameters."""

Progress = Callable[[str, int, int], None]
"""``progress(phase, done, total)``: called as each phase advances (the CLI draws a bar per phase)."""


@dataclass(frozen=True)
class SfmConfig:
    """How camera poses are computed from photos."""

    max_side: int = bounded(MAX_SIDE, low=16)
    """Longest image side used (larger photos are downscaled on load, area filter); the written images have it."""
    matcher: Literal["auto", "exhaustive", "sequential"] = "auto"
    """Which pairs are matched: every pair, or neighbours in file-name order (for a video's frames; faster); ``auto``:
    every pair, then neighbours when that folds a walk (the camera turning over 90 degrees between neighbours)."""
    overlap: int = bounded(10, low=1)
    """Sequential matcher: each photo is matched with the next ``overlap`` photos in file-name order."""
    far_pairs: bool = False
    """Sequential matcher: match each photo with the ones 1, 2, 4, ... 2^(overlap - 1) photos later instead of the next
    ``overlap`` (COLMAP's quadratic overlap, its default). Off by default: on a walk round a symmetric scene (a can on
    square tiles) those far pairs match look-alike views from other sides and fold the reconstruction; the neighbours
    alone keep a video's walk whole."""
    camera_model: Literal["SIMPLE_RADIAL", "RADIAL", "OPENCV", "PINHOLE", "SIMPLE_PINHOLE"] = "SIMPLE_RADIAL"
    """COLMAP camera model of the photos (one camera for all, or one per lens when every photo's EXIF gives its focal
    length: :func:`has_exif_focal`); a model with distortion is undistorted to PINHOLE images."""
    max_features: int = bounded(8192, low=64)
    """Most SIFT features per image."""
    min_registered: float = bounded(0.8, low=0, high=1, low_open=True)
    """Fraction of the photos that must register: a lower fraction is an error naming the ones that did not; at or
    above it those are left out of the scene, named in a warning and in ``sfm.json``. A capture often has a few
    photos SfM cannot place (blurred, or of a featureless side), and the rest still make a scene; before, one such
    photo stopped ``nerfmeta fit PHOTOS``, whose error pointed to an option only ``nerfmeta poses`` has."""
    threads: int = bounded(-1, low=-1)
    """Threads COLMAP uses (-1: all cores)."""
    seed: int = bounded(0, low=0)
    """Seed of COLMAP's random sampling (RANSAC, mapping)."""
    map_draws: int = bounded(6, low=1)
    """``auto``, when it falls back to neighbours: how many times the incremental mapper maps their matches (seeds
    ``seed``, ``seed + 1``, ...); the draw whose poses explain the most of every pair's verified matches is kept
    (:func:`match_agreement`). On beer a draw bent the walk (0.50 of the matches explained against 0.56-0.64) in 5 of
    20, 8 of 12, 3 of 4 and 3 of 3 draws on four runs' matches; each draw costs one mapping (about 5 s on beer's 71 photos
    at 720 x 1280)."""
    global_draw: bool = True
    """``auto``, when it falls back to neighbours: one more draw by GLOMAP's global mapper (``pycolmap.global_mapping``),
    scored with the incremental draws; its failures are not the incremental mapper's (on the run whose draws bent
    3 times in 4 it explained 0.64 of the matches; 5-8 s on beer)."""


# --------------------------------------------------------------------------------------------
# Pure conversions


def quaternion_to_matrix(q_wxyz: Sequence[float]) -> np.ndarray:
    """(3, 3) rotation of a quaternion in COLMAP's text order ``(w, x, y, z)`` (normalised first)."""
    w, x, y, z = np.asarray(q_wxyz, dtype=np.float64) / np.linalg.norm(q_wxyz)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """``(w, x, y, z)`` with ``w >= 0`` of a (3, 3) rotation (the inverse of :func:`quaternion_to_matrix`)."""
    r = np.asarray(rotation, dtype=np.float64)
    # the largest of the four squared components is computed directly, the others from it (stable for every rotation)
    squares = np.array([1 + r[0, 0] + r[1, 1] + r[2, 2], 1 + r[0, 0] - r[1, 1] - r[2, 2],
                        1 - r[0, 0] + r[1, 1] - r[2, 2], 1 - r[0, 0] - r[1, 1] + r[2, 2]])
    k = int(np.argmax(squares))
    s = 2.0 * math.sqrt(max(squares[k], 1e-300))
    if k == 0:
        q = [s / 4, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif k == 1:
        q = [(r[2, 1] - r[1, 2]) / s, s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif k == 2:
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s]
    else:
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4]
    q = np.array(q)
    return q if q[0] >= 0 else -q


def opengl_camera_to_world(q_wxyz: Sequence[float], t: Sequence[float], *, world: np.ndarray = WORLD_FROM_COLMAP) -> np.ndarray:
    """(4, 4) OpenGL camera-to-world matrix of a COLMAP world-to-camera pose ``x_cam = R(q) x_world + t``.

    The camera centre is ``-R^T t``; the camera axes are flipped from OpenCV to OpenGL
    (:data:`OPENGL_FROM_OPENCV`) and the world is turned by ``world`` (default
    :data:`WORLD_FROM_COLMAP`; the identity keeps COLMAP's world).
    """
    rotation = quaternion_to_matrix(q_wxyz)
    c2w = np.eye(4)
    c2w[:3, :3] = world @ rotation.T @ OPENGL_FROM_OPENCV
    c2w[:3, 3] = world @ (-rotation.T @ np.asarray(t, dtype=np.float64))
    return c2w


def colmap_world_to_camera(c2w: np.ndarray, *, world: np.ndarray = WORLD_FROM_COLMAP) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of :func:`opengl_camera_to_world`: ``(q_wxyz, t)`` of a (4, 4) OpenGL camera-to-world matrix."""
    rotation_c2w = world.T @ c2w[:3, :3] @ OPENGL_FROM_OPENCV  # COLMAP world, OpenCV camera
    centre = world.T @ c2w[:3, 3]
    rotation = rotation_c2w.T
    return matrix_to_quaternion(rotation), -rotation @ centre


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics in pixels (pixel centres at ``i + 0.5``, as COLMAP and nerfmeta use) and distortion."""

    width: int
    """Image width."""
    height: int
    """Image height."""
    fx: float
    """Focal length along x."""
    fy: float
    """Focal length along y."""
    cx: float
    """Principal point x."""
    cy: float
    """Principal point y."""
    distortion: dict[str, float] = field(default_factory=dict)
    """Non-zero distortion coefficients by name (``k1``, ``k2``, ``p1``, ``p2``); empty for a pinhole."""


def camera_from_colmap(model: str, params: Sequence[float], width: int, height: int) -> PinholeCamera:
    """The :class:`PinholeCamera` of a COLMAP camera (``model`` in :data:`DISTORTION_MODELS`, its ``params``).

    Raises:
        SceneError: another camera model (fisheye, ...), or the wrong number of parameters.
    """
    names = DISTORTION_MODELS.get(model)
    if names is None:
        raise SceneError(f"COLMAP camera model {model} is not supported (supported: {', '.join(DISTORTION_MODELS)})")
    if len(params) != len(names):
        raise SceneError(f"COLMAP camera model {model} needs {len(names)} parameters, got {len(params)}")
    values = dict(zip(names, (float(p) for p in params)))
    fx = values.get("fx", values.get("f"))
    fy = values.get("fy", values.get("f"))
    distortion = {k: v for k, v in values.items() if k in ("k1", "k2", "p1", "p2") and v != 0.0}
    return PinholeCamera(int(width), int(height), fx, fy, values["cx"], values["cy"], distortion)


def near_far_from_depths(depths: Sequence[np.ndarray], *, margin: float = 0.1) -> tuple[float, float]:
    """``(near, far)`` ray distances that hold the sparse points every camera sees.

    Args:
        depths: per camera, (k,) depths along its optical axis of the points it observes.
        margin: the 0.1 % and 99.9 % depth percentiles (over all cameras) are widened by this fraction.
    """
    every = np.concatenate([np.asarray(d, dtype=np.float64).reshape(-1) for d in depths] or [np.zeros(0)])
    every = every[np.isfinite(every) & (every > 0)]
    if every.size == 0:
        raise SceneError("the reconstruction has no 3-D points in front of the cameras")
    near = float(np.percentile(every, 0.1)) * (1 - margin)
    far = float(np.percentile(every, 99.9)) * (1 + margin)
    return near, max(far, near * 1.01)


def rotation_steps_deg(rotations: np.ndarray) -> np.ndarray:
    """Angles (degrees) of the rotations between consecutive ``(N, 3, 3)`` camera rotations (``N - 1`` of them)."""
    relative = np.einsum("nij,nkj->nik", rotations[1:], rotations[:-1])
    cos = (np.trace(relative, axis1=1, axis2=2) - 1) / 2
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def is_walk(rotations: np.ndarray, *, walk_deg: float = WALK_STEP_DEG) -> bool:
    """Whether ``(N, 3, 3)`` camera rotations in their order are a walk: three or more whose median step is at most
    ``walk_deg`` (a video's frames in file-name order; photos in no particular order are not)."""
    steps = rotation_steps_deg(np.asarray(rotations, dtype=np.float64))
    return len(steps) >= 2 and float(np.median(steps)) <= walk_deg


def axis_steps_deg(rotations: np.ndarray, *, world_to_camera: bool = False) -> np.ndarray:
    """Angles (degrees) between the viewing directions of consecutive ``(N, 3, 3)`` camera rotations: camera-to-world
    (the optical axis is a column) or, with ``world_to_camera``, world-to-camera (a row, as COLMAP stores them). A
    camera rolled about its own axis (a photo turned a quarter, or upside down) does not change it."""
    rotations = np.asarray(rotations, dtype=np.float64)
    axes = rotations[:, 2, :] if world_to_camera else rotations[:, :, 2]
    norms = np.linalg.norm(axes, axis=1)
    cos = np.einsum("ni,ni->n", axes[1:], axes[:-1]) / (norms[1:] * norms[:-1])
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def walk_jumps(rotations: np.ndarray, *, world_to_camera: bool = False, jump_deg: float = JUMP_DEG) -> list[int]:
    """Indices ``i`` where the viewing direction of cameras ``i - 1 -> i`` of a walk (:func:`is_walk`) turns by more
    than ``jump_deg`` (:func:`axis_steps_deg`; camera-to-world rotations unless ``world_to_camera``); none for cameras
    that are no walk. A jump in a walk is almost always a reconstruction that folded look-alike views from different
    sides; a camera that only rolls (a photo taken with the phone turned) is none."""
    if not is_walk(rotations):
        return []
    steps = axis_steps_deg(rotations, world_to_camera=world_to_camera)
    return [int(i) + 1 for i in np.flatnonzero(steps > jump_deg)]


def essential_matrix(rotation1: np.ndarray, t1: np.ndarray, rotation2: np.ndarray, t2: np.ndarray) -> np.ndarray:
    """(3, 3) essential matrix ``E`` of two world-to-camera poses ``x_cam = R x_world + t`` (COLMAP's): ``x2^T E x1 = 0``
    for the normalised image points ``x1``, ``x2`` (homogeneous) of one world point."""
    rotation = np.asarray(rotation2, dtype=np.float64) @ np.asarray(rotation1, dtype=np.float64).T
    t = np.asarray(t2, dtype=np.float64) - rotation @ np.asarray(t1, dtype=np.float64)
    cross = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    return cross @ rotation


def sampson_distances(essential: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """(N,) Sampson distances (first-order geometric error, in normalised image units) of correspondences
    ``x1 -> x2`` ((N, 2) normalised points each) from the epipolar geometry ``essential`` (3, 3)."""
    h1 = np.concatenate([np.asarray(x1, dtype=np.float64), np.ones((len(x1), 1))], 1)
    h2 = np.concatenate([np.asarray(x2, dtype=np.float64), np.ones((len(x2), 1))], 1)
    lines2, lines1 = h1 @ essential.T, h2 @ essential  # epipolar lines E x1 (in image 2) and E^T x2 (in image 1)
    residual = np.abs((h2 * lines2).sum(1))
    norm = np.sqrt(lines2[:, 0] ** 2 + lines2[:, 1] ** 2 + lines1[:, 0] ** 2 + lines1[:, 1] ** 2)
    return residual / np.maximum(norm, np.finfo(np.float64).tiny)


def photo_hash(paths: Sequence[Path], config: SfmConfig) -> str:
    """A hex key of the photos' names and contents and of ``config`` (what a cached SfM scene was made from)."""
    digest = hashlib.sha256(json.dumps(asdict(config), sort_keys=True).encode())
    for path in paths:
        digest.update(path.name.encode() + b"\0")
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                digest.update(block)
        digest.update(b"\0")
    return digest.hexdigest()[:32]


# --------------------------------------------------------------------------------------------
# Photos


def check_photos(paths: Sequence[Path], folder: Path) -> tuple[tuple[int, int], frozenset[str]]:
    """``((height, width), turned)``: the size the photos share as shown (EXIF orientation applied; read from the
    headers) and the names of those shown the other way round (portrait among landscape, or the reverse).

    A phone held upright for some shots and sideways for others takes both from one camera: SfM gets those photos
    turned a quarter to the orientation most of them have (:func:`prepare_photo`), a pinhole camera rolled by 90
    degrees with the same focal length, and poses them so. Ties keep the first photo's orientation.

    Raises:
        SceneError: fewer than :data:`MIN_PHOTOS`, an unreadable file, or photos of different sizes.
    """
    if len(paths) < MIN_PHOTOS:
        found = ", ".join(p.name for p in paths) or "none"
        raise SceneError(f"{folder}: {len(paths)} photo(s) ({found}); structure from motion needs at least {MIN_PHOTOS} "
                         "overlapping photos of the scene from different places")
    sizes = {p: image_shape(p) for p in paths}
    first = paths[0]
    for path, size in sizes.items():
        if sorted(size) != sorted(sizes[first]):
            raise SceneError(f"{path}: is {size[1]}x{size[0]} but {first.name} is {sizes[first][1]}x{sizes[first][0]}; "
                             "all photos must come from one camera at one size")
    other = [p for p in paths if sizes[p] != sizes[first]]
    if 2 * len(other) > len(paths):
        shared = sizes[other[0]]
        return shared, frozenset(p.name for p in paths if sizes[p] != shared)
    return sizes[first], frozenset(p.name for p in other)


def prepared_names(paths: Sequence[Path]) -> dict[str, str]:
    """The name each photo has in the SfM scene, by its own name: the same for PNG and JPEG, ``STEM.jpg`` for a
    HEIC/HEIF photo (COLMAP reads no HEIF).

    Raises:
        SceneError: two photos would get one name (``IMG_1.HEIC`` beside ``IMG_1.jpg``: the same shot twice, at a
            guess).
    """
    names: dict[str, str] = {}
    taken: dict[str, str] = {}
    for path in paths:
        name = path.stem + ".jpg" if path.suffix.lower() in HEIF_SUFFIXES else path.name
        if name.lower() in taken:
            raise SceneError(f"{path.parent}: {taken[name.lower()]} and {path.name} would both be {name} in the scene "
                             "(the same photo in two formats?); keep one of them")
        names[path.name], taken[name.lower()] = name, path.name
    return names


def prepared_size(height: int, width: int, max_side: int) -> tuple[int, int]:
    """``(height, width)`` scaled so that the longest side is at most ``max_side`` (unchanged when it is)."""
    scale = min(1.0, max_side / max(height, width))
    return max(1, round(height * scale)), max(1, round(width * scale))


def prepare_photo(source: Path, dest: Path, size: tuple[int, int], *, turn: bool = False) -> None:
    """Write ``source`` to ``dest`` as RGB of ``size`` = (height, width): EXIF orientation applied, turned a quarter
    clockwise with ``turn`` (a portrait photo among landscape ones), alpha composited on white, area-downscaled; a file
    that needs none of this is copied as it is."""
    array = decode_array(source)
    exif = read_exif(source)
    if turn:
        array = np.ascontiguousarray(np.rot90(array, k=-1))
    stored_as_shown = exif is None or exif.get(EXIF_ORIENTATION, 1) in (1, None)
    if array.shape[:2] == size and array.ndim == 3 and array.shape[2] == 3 and array.dtype == np.uint8 \
            and not turn and source.suffix.lower() == dest.suffix.lower() and stored_as_shown:
        shutil.copyfile(source, dest)
        return
    if array.dtype != np.uint8:
        array = (array.astype(np.float64) / 65535.0 * 255.0 + 0.5).astype(np.uint8)
    if array.ndim == 2:
        array = array[..., None]
    if array.shape[2] in (2, 4):
        rgb, alpha = array[..., :-1].astype(np.float64), array[..., -1:].astype(np.float64) / 255.0
        array = (rgb * alpha + 255.0 * (1 - alpha) + 0.5).astype(np.uint8)
    if array.shape[2] == 1:
        array = np.repeat(array, 3, axis=2)
    image = Image.fromarray(array)
    if image.size != (size[1], size[0]):
        image = image.resize((size[1], size[0]), Image.Resampling.BOX)
    # The copy keeps the EXIF (COLMAP's focal-length prior: focal length, 35 mm equivalent, make and model), said
    # to be upright: its pixels are turned already.
    extra = {}
    if exif is not None:
        exif[EXIF_ORIENTATION] = 1
        extra["exif"] = exif.tobytes()
    if dest.suffix.lower() in (".jpg", ".jpeg"):
        image.save(dest, quality=95, **extra)
    else:
        image.save(dest, **extra)


def has_exif_focal(path: Path) -> bool:
    """True when the photo's EXIF gives a focal length (in mm, or its 35 mm equivalent).

    Photos that all have one are given to COLMAP with one camera per distinct size and EXIF focal length (its AUTO
    mode: a phone that switched lenses for some shots has two cameras); otherwise they share one camera, as COLMAP's
    AUTO mode would give every photo without EXIF a camera of its own."""
    exif = read_exif(path)
    try:
        sub = {} if exif is None else exif.get_ifd(0x8769)
    except Exception:  # a damaged Exif sub-block: no focal length worth reading
        return False
    return any(isinstance(sub.get(tag), numbers.Real) and float(sub.get(tag)) > 0 for tag in (0x920A, 0xA405))


# --------------------------------------------------------------------------------------------
# COLMAP


@contextlib.contextmanager
def _colmap_quiet(verbose: bool) -> Iterator[None]:
    """COLMAP's log lines below FATAL held back (unless ``verbose``) and its setting restored after."""
    import pycolmap

    old = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = old if verbose else max(old, 3)  # nerfmeta says what failed, in one line
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


@dataclass(frozen=True)
class SfmResult:
    """What :func:`compute_poses` made."""

    scene: Path
    """The scene folder (``transforms.json`` and ``images/``)."""
    photos: int
    """Photos given."""
    registered: tuple[str, ...]
    """Names of the photos that have a pose, as in the scene (a HEIC/HEIF photo's as ``STEM.jpg``)."""
    unregistered: tuple[str, ...]
    """Names of the photos (as in the photo folder) that did not register."""
    reprojection_error: float
    """Mean reprojection error of the sparse points, pixels."""
    points: int
    """Sparse 3-D points."""
    seconds: dict[str, float]
    """Wall-clock time per phase."""
    matcher: str = "exhaustive"
    """The matcher whose model was kept (``auto`` resolves to ``exhaustive`` or ``sequential``)."""
    jumps: tuple[str, ...] = ()
    """Photos of a walk whose camera turns by more than :data:`JUMP_DEG` from the previous one (:func:`walk_jumps`)."""
    draws: tuple[dict, ...] = ()
    """The neighbours' mapping draws, when there were several: mapper, seed, registered, jumps, agreement, and which was kept."""
    turned: tuple[str, ...] = ()
    """Photos (as in the photo folder) turned a quarter to the others' orientation (:func:`check_photos`)."""

    def as_json(self) -> dict:
        return {**asdict(self), "scene": str(self.scene), "registered": list(self.registered),
                "unregistered": list(self.unregistered), "jumps": list(self.jumps), "draws": list(self.draws),
                "turned": list(self.turned)}


def posed_images(model) -> dict:
    """The images of ``model`` that have a pose, by name (none for no model)."""
    return {} if model is None else {image.name: image for image in model.images.values() if image.has_pose}


AGREE_PX = 2.0
"""A verified match is explained by a model when its Sampson distance from the model's epipolar geometry is below this (pixels)."""


@dataclass(frozen=True)
class VerifiedMatches:
    """Every matched pair's verified (inlier) matches in a COLMAP database, read once to score several models."""

    keypoints: dict[str, np.ndarray]
    """(K, 2) pixel positions of each photo's keypoints, by name (photos in a verified pair only)."""
    pairs: tuple[tuple[str, str, np.ndarray], ...]
    """``(photo a, photo b, (M, 2) keypoint indices in a and b)`` of every pair with verified matches."""


def read_verified_matches(database: Path) -> VerifiedMatches:
    """The verified matches of every pair in ``database`` and the keypoints they refer to."""
    import pycolmap

    db = pycolmap.Database.open(database)
    try:
        names = {image.image_id: image.name for image in db.read_all_images()}
        pair_ids, geometries = db.read_two_view_geometries()
        pairs, keypoints = [], {}
        for pair_id, geometry in zip(pair_ids, geometries):
            matches = np.asarray(geometry.inlier_matches).reshape(-1, 2)
            if not len(matches):
                continue
            ids = pycolmap.pair_id_to_image_pair(pair_id)
            for image_id in ids:
                if names[image_id] not in keypoints:
                    keypoints[names[image_id]] = np.asarray(db.read_keypoints(image_id))[:, :2]
            pairs.append((names[ids[0]], names[ids[1]], matches))
    finally:
        db.close()
    return VerifiedMatches(keypoints, tuple(pairs))


def match_agreement(model, matches: VerifiedMatches, *, tol_px: float = AGREE_PX) -> float:
    """The share of the verified ``matches`` (of every pair whose photos ``model`` posed) that ``model``'s poses
    explain: Sampson distance (:func:`sampson_distances`) under ``tol_px`` pixels.

    Look-alike views of a symmetric scene leave some verified matches that no true model explains, so the share
    is never near 1; what it tells is which of several models of the same photos is the most consistent. A model
    mapped from neighbours' matches never saw the far pairs, and only a walk kept whole explains them.
    """
    posed = posed_images(model)
    points: dict[str, np.ndarray] = {}

    def normalised(name: str) -> np.ndarray:
        if name not in points:
            points[name] = np.asarray(model.cameras[posed[name].camera_id].cam_from_img(matches.keypoints[name]))
        return points[name]

    explained = total = 0
    for name_a, name_b, pair in matches.pairs:
        if name_a not in posed or name_b not in posed:
            continue
        a, b = posed[name_a], posed[name_b]
        pose_a, pose_b = a.cam_from_world(), b.cam_from_world()
        essential = essential_matrix(pose_a.rotation.matrix(), pose_a.translation, pose_b.rotation.matrix(),
                                     pose_b.translation)
        focal = math.sqrt(model.cameras[a.camera_id].mean_focal_length() * model.cameras[b.camera_id].mean_focal_length())
        error = sampson_distances(essential, normalised(name_a)[pair[:, 0]], normalised(name_b)[pair[:, 1]]) * focal
        explained += int((error < tol_px).sum())
        total += len(pair)
    return explained / total if total else 0.0


def _largest_model(models: dict) -> "object | None":
    return max(models.values(), key=lambda m: m.num_reg_images(), default=None)


def reconstruct(images: Path, names: Sequence[str], work: Path, config: SfmConfig, progress: Progress,
                seconds: dict[str, float], *, features: Path | None = None):
    """Features, matches and incremental mapping of ``names`` in ``images``; the largest model (or None).

    ``work`` receives COLMAP's database and models; ``seconds`` adds up the time of each phase.
    ``features``: an earlier run's database whose features are reused (its matches are dropped).
    ``config.matcher`` is ``exhaustive`` or ``sequential`` here (:func:`compute_poses` resolves ``auto``).
    """
    import pycolmap

    database = work / "database.db"
    t0 = time.perf_counter()
    progress("features", 0, 1)
    if features is not None:
        shutil.copyfile(features, database)
        db = pycolmap.Database.open(database)
        try:
            db.clear_matches()
            db.clear_two_view_geometries()
        finally:
            db.close()
    else:
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = config.camera_model
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = config.threads
        extraction.sift.max_num_features = config.max_features
        per_lens = all(has_exif_focal(images / n) for n in names)  # one camera per lens, else one for all
        mode = pycolmap.CameraMode.AUTO if per_lens else pycolmap.CameraMode.SINGLE
        pycolmap.extract_features(database, images, image_names=list(names), camera_mode=mode,
                                  reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
    progress("features", 1, 1)
    seconds["features"] = seconds.get("features", 0.0) + time.perf_counter() - t0
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = config.threads
    t0 = time.perf_counter()
    progress("matching", 0, 1)
    if config.matcher == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = config.overlap
        pairing.quadratic_overlap = config.far_pairs
        pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)
    else:
        pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
    progress("matching", 1, 1)
    seconds["matching"] = seconds.get("matching", 0.0) + time.perf_counter() - t0
    return map_matches(database, images, len(names), work / "sparse", config, progress, seconds)


def map_matches(database: Path, images: Path, photos: int, sparse: Path, config: SfmConfig, progress: Progress,
                seconds: dict[str, float], *, seed: int | None = None, phase: str = "mapping",
                mapper: Literal["incremental", "global"] = "incremental"):
    """Mapping of the matches in ``database`` into the new folder ``sparse``; the largest model (or None).

    ``mapper``: COLMAP's incremental mapper (photo by photo, with bundle adjustment as it goes) or GLOMAP's global one
    (:func:`pycolmap.global_mapping`: every rotation at once, then every position, then bundle adjustment), whose
    failures are not the incremental mapper's. ``seed`` (default ``config.seed``) seeds the sampling; on several
    threads the result still varies from run to run. ``phase`` names the progress bar (over the ``photos`` photos).
    """
    import pycolmap

    registered = [0]

    def next_image() -> None:
        registered[0] += 1
        progress(phase, min(registered[0], photos), photos)

    t0 = time.perf_counter()
    progress(phase, 0, photos)
    sparse.mkdir()
    options = pycolmap.GlobalPipelineOptions() if mapper == "global" else pycolmap.IncrementalPipelineOptions()
    options.num_threads = config.threads
    options.random_seed = config.seed if seed is None else seed
    options.min_model_size = MIN_PHOTOS
    if mapper == "global":
        models = pycolmap.global_mapping(database, images, sparse, options=options)
    else:
        models = pycolmap.incremental_mapping(database, images, sparse, options=options, next_image_callback=next_image)
    seconds["mapping"] = seconds.get("mapping", 0.0) + time.perf_counter() - t0
    model = _largest_model(models)
    progress(phase, 0 if model is None else model.num_reg_images(), photos)
    return model


def best_draw(first, work: Path, images: Path, names: Sequence[str], every_pair: Path, config: SfmConfig,
              progress: Progress, seconds: dict[str, float]):
    """``(model, draws)``: of ``first`` (mapped in ``work``), ``config.map_draws - 1`` more incremental mappings of the
    same matches (seeds ``config.seed + k``) and, with ``config.global_draw``, one global mapping of them, the one that
    registers the most photos, then folds the least, then agrees best with the verified matches of every pair in
    ``every_pair`` (:func:`match_agreement`); ``draws`` describes each (none for a single draw)."""
    plan = [("incremental", config.seed + k) for k in range(1, config.map_draws)]
    plan += [("global", config.seed)] if config.global_draw else []
    if not plan:
        return first, ()
    models, rows = [first], [("incremental", config.seed)]
    for k, (mapper, seed) in enumerate(plan, start=2):
        models.append(map_matches(work / "database.db", images, len(names), work / f"sparse-{k}", config, progress,
                                  seconds, seed=seed, mapper=mapper,  # type: ignore[arg-type]
                                  phase=f"mapping, draw {k} of {len(plan) + 1}" + (" (global)" if mapper == "global" else "")))
        rows.append((mapper, seed))
    t0 = time.perf_counter()
    matches = read_verified_matches(every_pair)
    draws = []
    for model, (mapper, seed) in zip(models, rows):
        posed = sorted(posed_images(model))
        draws.append({"mapper": mapper, "seed": seed, "registered": len(posed),
                      "jumps": len(model_jumps(model, posed)) if posed else 0,
                      "agreement": round(match_agreement(model, matches), 4) if posed else 0.0})
    seconds["agreement"] = seconds.get("agreement", 0.0) + time.perf_counter() - t0
    best = max(range(len(models)), key=lambda k: (draws[k]["registered"], -draws[k]["jumps"], draws[k]["agreement"]))
    return models[best], tuple({**row, "kept": k == best} for k, row in enumerate(draws))


def _undistorted(model, images: Path, work: Path):
    """``(model, image folder)`` with the distortion removed (COLMAP's undistorter; PINHOLE cameras)."""
    import pycolmap

    model_dir = work / "distorted"
    model_dir.mkdir()
    model.write(model_dir)
    out = work / "undistorted"
    pycolmap.undistort_images(out, model_dir, images)
    return pycolmap.Reconstruction(out / "sparse"), out / "images"


def point_depths(model, image) -> np.ndarray:
    """(k,) depths along ``image``'s optical axis of the sparse points of ``model`` it observes."""
    pose = image.cam_from_world()
    points = np.array([model.points3D[p.point3D_id].xyz for p in image.points2D if p.has_point3D()]).reshape(-1, 3)
    return (points @ np.asarray(pose.rotation.matrix()).T + np.asarray(pose.translation))[:, 2]


def _camera_keys(camera: PinholeCamera) -> dict:
    """A camera's ``transforms.json`` keys (nerfstudio layout)."""
    return {"camera_model": "OPENCV" if camera.distortion else "PINHOLE", "w": camera.width, "h": camera.height,
            "fl_x": camera.fx, "fl_y": camera.fy, "cx": camera.cx, "cy": camera.cy, **camera.distortion}


def scene_document(model, names: Sequence[str]) -> tuple[dict, PinholeCamera]:
    """The ``transforms.json`` document (nerfstudio layout) of ``model``'s images ``names`` and the first one's camera
    (at the top level; a frame whose camera is another one carries its own keys)."""
    by_name = posed_images(model)
    cameras = {cam_id: camera_from_colmap(cam.model.name, list(cam.params), cam.width, cam.height)
               for cam_id, cam in model.cameras.items()}
    first = by_name[names[0]].camera_id
    frames, depths = [], []
    for name in names:
        image = by_name[name]
        pose = image.cam_from_world()
        x, y, z, w = pose.rotation.quat  # pycolmap keeps Eigen's (x, y, z, w) order
        frames.append({"file_path": f"{IMAGES}/{name}",
                       "transform_matrix": opengl_camera_to_world((w, x, y, z), pose.translation).tolist(),
                       **(_camera_keys(cameras[image.camera_id]) if image.camera_id != first else {})})
        depths.append(point_depths(model, image))
    near, far = near_far_from_depths(depths)
    applied = np.eye(4)[:3]
    applied[:, :3] = WORLD_FROM_COLMAP
    doc = {**_camera_keys(cameras[first]), "near": near, "far": far, "applied_transform": applied.tolist(),
           "frames": frames}
    return doc, cameras[first]


def folded_walk_note(views: Sequence[int]) -> str:
    """One line on the jumps (:func:`walk_jumps`) of a scene's poses, and what recomputes them."""
    return (f"views {', '.join(map(str, views))} turn over {JUMP_DEG:g} degrees from the previous view: if the views are a walk's "
            "frames, the poses folded it (look-alike sides of the scene) and a fit will blur; 'nerfmeta poses' on the "
            "images recomputes them")


def model_jumps(model, names: Sequence[str]) -> list[str]:
    """The photos of ``names`` (registered in ``model``, in file-name order) where a walk jumps (:func:`walk_jumps`)."""
    by_name = posed_images(model)
    rotations = np.array([np.asarray(by_name[name].cam_from_world().rotation.matrix()) for name in names])
    return [names[i] for i in walk_jumps(rotations, world_to_camera=True)]


def jump_advice(jumps: Sequence[str], config: SfmConfig) -> str:
    """One line on the jumps of a walk (:func:`walk_jumps`) and which options keep the walk whole."""
    shown = ", ".join(jumps[:6]) + (f" and {len(jumps) - 6} more" if len(jumps) > 6 else "")
    if config.matcher == "exhaustive":
        fix = "--matcher sequential (neighbours only)"
    elif config.matcher == "auto":  # neighbours only folded it too (or registered fewer photos)
        fix = f"--matcher sequential with a smaller --overlap than {config.overlap}"
    elif config.far_pairs:
        fix = "--no-far-pairs"
    else:
        fix = f"a smaller --overlap than {config.overlap}"
    return (f"the camera turns by more than {JUMP_DEG:g} degrees from the previous photo at {shown}: if the photos are "
            f"a walk's frames in name order, the reconstruction folded look-alike views from different sides; try {fix}")


def _unregistered_error(folder: Path, missing: Sequence[str], total: int, config: SfmConfig) -> SceneError:
    shown = ", ".join(missing[:8]) + (f" and {len(missing) - 8} more" if len(missing) > 8 else "")
    if len(missing) == total:
        return SceneError(f"{folder}: structure from motion found no two photos that overlap enough to start a model "
                          f"({total} photos); take overlapping photos of one textured scene from nearby viewpoints")
    share = max(0.01, math.floor((total - len(missing)) / total * 100) / 100)
    return SceneError(f"{folder}: {len(missing)} of {total} photos did not register (at least {config.min_registered:g} "
                      f"must): {shown}; they share too few features with the others (retake or remove them, or keep "
                      f"the rest with: nerfmeta poses {folder} --out SCENE --min-registered {share:g})")


def compute_poses(photos: str | os.PathLike, out: str | os.PathLike, config: SfmConfig = SfmConfig(), *,
                  overwrite: bool = False, progress: Progress | None = None, verbose: bool = False) -> SfmResult:
    """Structure from motion on the photos of ``photos``, written as a nerfstudio scene to ``out`` (see the module doc).

    ``out`` is a run folder of kind ``poses``: new or empty (or, with ``overwrite``, a poses scene
    of ours), built aside and swapped in complete; ``photos`` is only read.

    Raises:
        SceneError: too few photos, an unreadable one, mixed sizes, no overlap, or too few registered
            (naming the photos that did not). RunFolderError: ``out`` cannot take the scene.
    """
    import pycolmap  # noqa: F401  (a missing extra fails here, before anything is written)

    progress = progress or (lambda phase, done, total: None)
    folder = Path(photos)
    paths = list_photos(folder)
    if not folder.is_dir():
        raise SceneError(f"{folder}: not a folder of photos")
    (height, width), turned = check_photos(paths, folder)
    size = prepared_size(height, width, config.max_side)
    scene_names = prepared_names(paths)
    own = {scene: name for name, scene in scene_names.items()}  # the photos' own names, for messages
    seconds: dict[str, float] = {}
    with run_folder(out, "poses", overwrite=overwrite, aside=True, protect=(folder,)) as run, \
            tempfile.TemporaryDirectory(prefix="nerfmeta-sfm-") as tmp, _colmap_quiet(verbose):
        work = Path(tmp)
        prepared = work / "photos"
        prepared.mkdir()
        t0 = time.perf_counter()
        names = [scene_names[p.name] for p in paths]
        for k, path in enumerate(paths):
            progress("photos", k, len(paths))
            prepare_photo(path, prepared / scene_names[path.name], size, turn=path.name in turned)
        progress("photos", len(paths), len(paths))
        seconds["photos"] = time.perf_counter() - t0
        if turned:
            shown = sorted(turned)
            log.warning("%s: %d of %d photos are %s, the rest %s: turned a quarter clockwise to match (so in the "
                        "scene's images/): %s", folder, len(turned), len(paths),
                        "landscape" if height > width else "portrait", "portrait" if height > width else "landscape",
                        ", ".join(shown[:8]) + (f" and {len(shown) - 8} more" if len(shown) > 8 else ""))
        matcher = "exhaustive" if config.matcher == "auto" else config.matcher
        draws: tuple[dict, ...] = ()
        attempt = work / matcher
        attempt.mkdir()
        model = reconstruct(prepared, names, attempt, replace(config, matcher=matcher), progress, seconds)
        registered = sorted(posed_images(model))
        if len(registered) < MIN_PHOTOS or len(registered) < config.min_registered * len(names) - 1e-9:
            raise _unregistered_error(folder, [own[n] for n in names if n not in set(registered)], len(names), config)
        jumps = model_jumps(model, registered)
        if jumps and config.matcher == "auto":  # a folded walk: match neighbours only, keep it if it folds less
            log.warning("%s: matching every pair folded the walk at %s (look-alike views from different sides); "
                        "matching each photo with its next %d only", folder, ", ".join(jumps[:6]), config.overlap)
            retry = work / "sequential"
            retry.mkdir()
            again = reconstruct(prepared, names, retry, replace(config, matcher="sequential"), progress, seconds,
                                features=attempt / "database.db")
            again, draws = best_draw(again, retry, prepared, names, attempt / "database.db", config, progress, seconds)
            kept = sorted(posed_images(again))
            if len(kept) >= len(registered) and len(kept_jumps := model_jumps(again, kept)) < len(jumps):
                model, registered, matcher, jumps = again, kept, "sequential", kept_jumps
            else:
                draws = ()
        missing = [own[n] for n in names if n not in set(registered)]
        if missing:
            log.warning("%s: %d photo(s) did not register and are left out: %s", folder, len(missing), ", ".join(missing))
        t0 = time.perf_counter()
        image_dir = prepared
        if any(camera_from_colmap(cam.model.name, list(cam.params), cam.width, cam.height).distortion
               for cam in model.cameras.values()):
            model, image_dir = _undistorted(model, prepared, work)
        doc, _ = scene_document(model, registered)
        seconds["undistort"] = time.perf_counter() - t0
        (run.dir / IMAGES).mkdir()
        for name in registered:
            shutil.copyfile(image_dir / name, run.dir / IMAGES / name)
        (run.dir / COLMAP).mkdir()
        model.write_binary(str(run.dir / COLMAP))
        if jumps:
            log.warning("%s: %s", folder, jump_advice(jumps, config))
        result = SfmResult(run.path, len(names), tuple(registered), tuple(missing),
                           float(model.compute_mean_reprojection_error()), int(model.num_points3D()),
                           {k: round(v, 3) for k, v in seconds.items()}, matcher, tuple(jumps), draws,
                           tuple(sorted(turned)))
        write_json(run.dir / REPORT, {**result.as_json(), "config": asdict(config)})
        write_json(run.dir / TRANSFORMS, doc)
    return result


# --------------------------------------------------------------------------------------------
# The cache ``nerfmeta fit PHOTOS`` uses


def cache_root() -> Path:
    """Where SfM scenes are cached: ``$NERFMETA_CACHE/poses``, else ``$XDG_CACHE_HOME/nerfmeta/poses`` (``~/.cache``)."""
    base = os.environ.get("NERFMETA_CACHE")
    if base:
        return Path(base) / "poses"
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "nerfmeta" / "poses"


def cached_poses(photos: str | os.PathLike, config: SfmConfig = SfmConfig(), *, progress: Progress | None = None,
                 verbose: bool = False) -> tuple[Path, bool]:
    """``(scene folder, was cached)``: the SfM scene of ``photos`` from the cache, computed there when missing.

    The key is the photos' names and contents and ``config`` (:func:`photo_hash`), so changing a
    photo or an option computes a new scene. A cached scene that lost its ``transforms.json`` is
    recomputed.
    """
    folder = Path(photos)
    paths = list_photos(folder)
    check_photos(paths, folder)
    scene = cache_root() / photo_hash(paths, config)
    if (scene / TRANSFORMS).is_file():
        return scene, True
    compute_poses(folder, scene, config, overwrite=True, progress=progress, verbose=verbose)
    return scene, False
