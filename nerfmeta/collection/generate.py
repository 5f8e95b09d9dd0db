"""Generate a collection: many scenes per category, each rendered and written in the Blender format.

Layout written under ``out``::

    out/collection.json                 every scene: name, path, category, split, aabb, shape
    out/<category>/<category>_<k>/      one Blender-format scene (transforms_{train,test}.json, PNGs)

Everything is a function of :class:`CollectionConfig`: each scene's shape and camera azimuth come
from its own ``numpy.random.SeedSequence`` keyed by (seed, category name, index), so a scene does
not change when other categories are added, and two runs give byte-identical files. The folder
is built under a hidden sibling name and renamed into place at the end, so an error or an
interruption never leaves a partial collection at ``out``.
"""

from __future__ import annotations

import json
import logging
import math
import multiprocessing
import os
import zlib
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import torch

from nerfmeta.collection.categories import CATEGORIES, sample_shape
from nerfmeta.collection.render import RenderConfig, render_views
from nerfmeta.collection.shapes import Shape, shape_bounds, shape_from_json, shape_sdf, shape_to_json
from nerfmeta.data.write import write_blender_scene
from nerfmeta.errors import ConfigError
from nerfmeta.io import to_jsonable, write_json
from nerfmeta.runfolder import check_target, run_folder
from nerfmeta.render.cameras import fibonacci_directions, look_at

log = logging.getLogger(__name__)

FORMAT = "nerfmeta-collection"
VERSION = 1
MIN_RESOLUTION = 8
MAX_RESOLUTION = 2048
MAX_VIEWS = 10_000
AABB_PAD = 0.02
RAYS_PER_CHUNK = 1 << 18
GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


@dataclass(frozen=True)
class CollectionConfig:
    """What to generate: categories, counts, cameras and rendering."""

    categories: tuple[str, ...] = tuple(CATEGORIES)
    """Category names, in order (see ``make-collection --list-categories``)."""
    scenes_per_category: int = 10
    """Scenes generated for each category."""
    views: int = 40
    """Training views per scene."""
    test_views: int = 10
    """Test views per scene, on a different set of directions than the training views."""
    resolution: int = 64
    """Image width and height in pixels."""
    seed: int = 0
    """Global seed; each scene derives its own from (seed, category, index)."""
    fov_degrees: float = 30.0
    """Horizontal (= vertical) field of view of the cameras."""
    radius: float = 4.0
    """Distance of the cameras from the object's centre (the object fits in the unit sphere)."""
    full_sphere: bool = False
    """Place cameras on the whole sphere instead of the upper hemisphere."""
    val_fraction: float = 0.1
    """Fraction of each category's scenes assigned to the ``val`` split."""
    test_fraction: float = 0.1
    """Fraction of each category's scenes assigned to the ``test`` split."""
    render: RenderConfig = field(default_factory=RenderConfig)
    """How the views are rendered."""

    def validate(self) -> None:
        """Raise :class:`ConfigError` (one line) for any value that cannot be generated."""
        if not self.categories:
            raise ConfigError("no categories given; see --list-categories")
        unknown = [c for c in self.categories if c not in CATEGORIES]
        if unknown:
            raise ConfigError(f"unknown categor{'y' if len(unknown) == 1 else 'ies'} {', '.join(map(repr, unknown))}; known: {', '.join(CATEGORIES)}")
        if len(set(self.categories)) != len(self.categories):
            raise ConfigError(f"categories repeated in {','.join(self.categories)}")
        for name in ("scenes_per_category", "views", "test_views"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ConfigError(f"--{name.replace('_', '-')} must be a positive integer, got {value}")
            if value > MAX_VIEWS:
                raise ConfigError(f"--{name.replace('_', '-')} {value} is too large (at most {MAX_VIEWS})")
        if not MIN_RESOLUTION <= self.resolution <= MAX_RESOLUTION:
            raise ConfigError(f"--resolution must be between {MIN_RESOLUTION} and {MAX_RESOLUTION}, got {self.resolution}")
        if self.seed < 0:
            raise ConfigError(f"--seed must be >= 0, got {self.seed}")
        if not 1.0 <= self.fov_degrees <= 150.0:
            raise ConfigError(f"--fov must be between 1 and 150 degrees, got {self.fov_degrees}")
        if not self.radius > 1.5:
            raise ConfigError(f"--radius must be above 1.5 (the object fills the unit sphere), got {self.radius}")
        for name in ("val_fraction", "test_fraction"):
            value = getattr(self, name)
            if not 0.0 <= value < 1.0:
                raise ConfigError(f"--{name.replace('_', '-')} must be in [0, 1), got {value}")
        if self.val_fraction + self.test_fraction >= 1.0:
            raise ConfigError(f"--val-fraction + --test-fraction must be below 1, got {self.val_fraction + self.test_fraction}")
        try:
            self.render.validate()
        except ValueError as err:
            raise ConfigError(str(err)) from None

    @property
    def camera_angle_x(self) -> float:
        return self.fov_degrees * math.pi / 180.0

    @property
    def focal(self) -> float:
        """Focal length in pixels."""
        return 0.5 * self.resolution / math.tan(0.5 * self.camera_angle_x)

    @property
    def near(self) -> float:
        return max(self.radius - 2.0, 0.05)

    @property
    def far(self) -> float:
        return self.radius + 2.0


@dataclass(frozen=True)
class SceneRecord:
    """One scene of a collection (what ``collection.json`` lists).

    Attributes:
        name: ``<category>_<index>``, unique in the collection.
        path: the scene folder relative to the collection root.
        category: the category name.
        index: the scene's number within its category.
        split: ``train``, ``val`` or ``test`` (which scenes a method may learn from).
        azimuth: rotation (radians) of this scene's camera spiral around z.
        shape: the exact geometry and appearance.
    """

    name: str
    path: str
    category: str
    index: int
    split: str
    azimuth: float
    shape: Shape

    @property
    def aabb(self) -> np.ndarray:
        """(2, 3) world box holding the surface, padded, inside ``[-1, 1]^3``."""
        return np.clip(shape_bounds(self.shape) + np.array([[-AABB_PAD], [AABB_PAD]]), -1.0, 1.0)

    def sdf(self, points: torch.Tensor) -> torch.Tensor:
        """(N, 3) world points -> (N,) signed distances to this scene's object."""
        return shape_sdf(self.shape, points)


def _category_key(category: str) -> int:
    return zlib.crc32(category.encode())


def scene_rng(seed: int, category: str, index: int, stream: int) -> np.random.Generator:
    """The generator of one scene; ``stream`` 0 draws the shape, 1 the cameras."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(_category_key(category), index, stream)))


def split_assignment(config: CollectionConfig, category: str) -> list[str]:
    """Split of each scene index of ``category``: a seeded shuffle cut by the fractions."""
    n = config.scenes_per_category
    n_test = min(int(round(n * config.test_fraction)), n - 1)  # always keep a training scene
    n_val = min(int(round(n * config.val_fraction)), n - 1 - n_test)
    rng = np.random.default_rng(np.random.SeedSequence(config.seed, spawn_key=(_category_key(category), 2**32 - 1)))
    order = rng.permutation(n).tolist()
    splits = ["train"] * n
    for k, idx in enumerate(order):
        if k < n_test:
            splits[idx] = "test"
        elif k < n_test + n_val:
            splits[idx] = "val"
    return splits


def plan_collection(config: CollectionConfig) -> list[SceneRecord]:
    """Sample every scene's shape, split and camera azimuth (no rendering), sorted by name."""
    config.validate()
    records = []
    for category in config.categories:
        splits = split_assignment(config, category)
        for index in range(config.scenes_per_category):
            shape = sample_shape(category, scene_rng(config.seed, category, index, 0))
            azimuth = float(scene_rng(config.seed, category, index, 1).uniform(0.0, 2.0 * math.pi))
            name = f"{category}_{index:03d}"
            records.append(SceneRecord(name, f"{category}/{name}", category, index, splits[index], azimuth, shape))
    return sorted(records, key=lambda r: r.name)


def camera_poses(config: CollectionConfig, azimuth: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(V, 4, 4) train and (T, 4, 4) test camera-to-world poses (float64) looking at the origin.

    Train and test directions are two Fibonacci spirals turned by ``azimuth`` and by ``azimuth``
    plus half a golden angle, so they never coincide.
    """

    def ring(n: int, turn: float) -> torch.Tensor:
        d = fibonacci_directions(n, upper_only=not config.full_sphere, offset=0.5)
        c, s = math.cos(turn), math.sin(turn)
        d = torch.stack([d[:, 0] * c - d[:, 1] * s, d[:, 0] * s + d[:, 1] * c, d[:, 2]], dim=-1)
        eye = config.radius * d
        return look_at(eye, torch.zeros_like(eye), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(eye))

    return ring(config.views, azimuth), ring(config.test_views, azimuth + 0.5 * GOLDEN_ANGLE)


def to_uint8(images: torch.Tensor) -> np.ndarray:
    """(..., C) floats in [0, 1] -> uint8, rounding half up."""
    return torch.floor(images.clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8).numpy()


def render_scene(record: SceneRecord, config: CollectionConfig) -> tuple[np.ndarray, torch.Tensor, np.ndarray, torch.Tensor]:
    """Render one scene: train images (V, H, W, 4) uint8 and poses, test images and poses."""
    train, test = camera_poses(config, record.azimuth)
    poses = torch.cat([train, test], dim=0)
    aabb = torch.as_tensor(record.aabb, dtype=torch.float32)
    r = config.resolution
    per_chunk = max(1, RAYS_PER_CHUNK // (r * r))
    chunks = []
    for start in range(0, poses.shape[0], per_chunk):
        chunks.append(render_views(record.sdf, record.shape.albedo, poses[start : start + per_chunk], config.focal, r, r, aabb, config.render))
    images = to_uint8(torch.cat(chunks, dim=0))
    return images[: len(train)], train, images[len(train) :], test


def scene_entry(record: SceneRecord) -> dict[str, Any]:
    """The ``collection.json`` entry of a scene."""
    return {
        "name": record.name,
        "path": record.path,
        "category": record.category,
        "index": record.index,
        "split": record.split,
        "azimuth": record.azimuth,
        "aabb": record.aabb.tolist(),
        "shape": shape_to_json(record.shape),
    }


def collection_document(config: CollectionConfig, records: list[SceneRecord]) -> dict[str, Any]:
    return {
        "format": FORMAT,
        "version": VERSION,
        "config": to_jsonable(config),
        "camera": {
            "camera_angle_x": config.camera_angle_x,
            "resolution": config.resolution,
            "radius": config.radius,
            "near": config.near,
            "far": config.far,
            "up": [0.0, 0.0, 1.0],
        },
        "frame": "z up, front +x, bounding box centred at the origin with half-diagonal 1",
        "scenes": [scene_entry(r) for r in records],
    }


def check_output(out: Path, overwrite: bool) -> None:
    """Raise a one-line error if ``out`` cannot become a collection folder (:mod:`nerfmeta.runfolder`'s rules)."""
    check_target(out, "collection", overwrite=overwrite)


def write_scene(record: SceneRecord, config: CollectionConfig, root: str | os.PathLike) -> int:
    """Render one scene and write it in the Blender format under ``root / record.path``.

    Returns:
        the number of views written.
    """
    train_img, train_pose, test_img, test_pose = render_scene(record, config)
    extra = {"near": config.near, "far": config.far, "category": record.category, "aabb": record.aabb.tolist()}
    splits = {"train": (train_img, train_pose), "test": (test_img, test_pose)}
    write_blender_scene(Path(root) / record.path, splits, config.camera_angle_x, extra)
    return len(train_img) + len(test_img)


def _worker_init() -> None:
    # Runs in worker processes this module started: one intra-op thread each, since the
    # tensors here are small and the workers already share the cores.
    torch.set_num_threads(1)


def generate_collection(
    config: CollectionConfig,
    out: str | os.PathLike,
    *,
    overwrite: bool = False,
    progress: Callable[[SceneRecord, int], None] | None = None,
    workers: int = 1,
) -> Path:
    """Render and write a whole collection; returns the path of ``collection.json``.

    Args:
        config: what to generate (validated first; nothing is written if it is invalid).
        out: the collection folder; must be absent or empty, or an earlier collection when
            ``overwrite`` is set.
        progress: called after each scene with its record and the number of views written
            (in completion order, which varies with ``workers``; the files do not).
        workers: scenes rendered in parallel; above 1, by that many spawned processes with one
            torch thread each. The output is identical for any value.
    """
    config.validate()
    if workers < 1:
        raise ConfigError(f"--workers must be a positive integer, got {workers}")
    out = Path(os.path.abspath(out))
    check_output(out, overwrite)
    records = plan_collection(config)
    with run_folder(out, "collection", overwrite=overwrite, aside=True) as run:  # built aside, swapped in when complete
        tmp = run.dir
        if workers == 1 or len(records) == 1:
            for record in records:
                n = write_scene(record, config, tmp)
                log.debug("rendered %s (%d views)", record.name, n)
                if progress is not None:
                    progress(record, n)
        else:
            ctx = multiprocessing.get_context("spawn")
            with ProcessPoolExecutor(min(workers, len(records)), mp_context=ctx, initializer=_worker_init) as pool:
                futures = {pool.submit(write_scene, r, config, tmp): r for r in records}
                try:
                    for fut in as_completed(futures):
                        n = fut.result()
                        if progress is not None:
                            progress(futures[fut], n)
                except BaseException:
                    pool.shutdown(wait=True, cancel_futures=True)
                    raise
        write_json(tmp / "collection.json", collection_document(config, records))
    log.info("wrote %d scenes to %s", len(records), out)
    return out / "collection.json"


# ---------------------------------------------------------------------------------------------
# Reading a collection back


@dataclass(frozen=True)
class Collection:
    """A collection read from ``collection.json``.

    Attributes:
        root: the collection folder.
        config: the configuration document it was generated with (plain JSON).
        scenes: one record per scene, sorted by name.
    """

    root: Path
    config: Mapping[str, Any]
    scenes: tuple[SceneRecord, ...]

    def by_category(self, category: str) -> tuple[SceneRecord, ...]:
        return tuple(s for s in self.scenes if s.category == category)

    def by_split(self, split: str) -> tuple[SceneRecord, ...]:
        return tuple(s for s in self.scenes if s.split == split)

    def scene_path(self, record: SceneRecord) -> Path:
        return self.root / record.path


def record_from_entry(entry: Mapping[str, Any]) -> SceneRecord:
    """A :class:`SceneRecord` from one ``collection.json`` scene entry."""
    return SceneRecord(
        name=entry["name"],
        path=entry["path"],
        category=entry["category"],
        index=int(entry["index"]),
        split=entry["split"],
        azimuth=float(entry["azimuth"]),
        shape=shape_from_json(entry["shape"]),
    )


def load_collection(path: str | os.PathLike) -> Collection:
    """Read a collection from its folder or its ``collection.json``."""
    path = Path(path)
    doc_path = path / "collection.json" if path.is_dir() else path
    try:
        doc = json.loads(doc_path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{doc_path} not found; make one with 'nerfmeta make-collection'") from None
    except json.JSONDecodeError as err:
        raise ConfigError(f"{doc_path} is not valid JSON ({err})") from None
    if doc.get("format") != FORMAT:
        raise ConfigError(f"{doc_path} is not a nerfmeta collection (format {doc.get('format')!r})")
    return Collection(doc_path.parent, doc.get("config", {}), tuple(record_from_entry(e) for e in doc["scenes"]))


def scene_sdf(entry: Mapping[str, Any] | SceneRecord) -> Callable[[torch.Tensor], torch.Tensor]:
    """The exact signed-distance function of a scene from its ``collection.json`` entry.

    Returns:
        ``sdf(points (N, 3)) -> (N,)``, world units, negative inside; dtype/device follow the points.
    """
    record = entry if isinstance(entry, SceneRecord) else record_from_entry(entry)
    return record.sdf
