"""Stiff and extreme cases (issue #8): scene perturbations and a table of real fits on them.

Two layers:

- **Scene writers and perturbations** (files in, files out): variants of the tiny analytic
  spheres scene (:mod:`nerfmeta.data.synthetic`) written in the Blender format, e.g.
  :func:`transform_blender_scene` (every pose, ``near``/``far`` and ``aabb`` of any Blender scene
  moved by a similarity, the images unchanged), :func:`write_uniform_scene`,
  :func:`write_inside_box_scene`, :func:`write_grazing_scene`.
- **Cases** (:data:`CASES`): each writes its scene into a folder, runs the real fit
  (:func:`~nerfmeta.fit.run.run_fit`, or :func:`pretrain.meta_run.meta_train` for the meta-learning
  case) for each backbone it applies to, and checks the outcome: no NaN in the training loss or
  the parameters, a finite test PSNR of at least the case's ``min_psnr``, and, for cases with a
  ``reference``, a test PSNR within :data:`MAX_PSNR_GAP` of the reference case's.

:func:`run_case` never lets one case's failure stop the table: an exception is recorded as that
case's outcome (``error: ...``) and :attr:`CaseResult.ok` is False, so ``scripts/stress.py``
exits non-zero and ``tests/test_stress.py`` fails, naming the case. The exception is a case
whose input cannot be fitted at all (``expect_error``): there the named one-line error is the
right outcome.

Two forms share every function: :data:`QUICK` (16 px scenes, tens of iterations, tiny networks;
the CI form) and :data:`FULL` (32 px, 300 iterations, the grid's defaults, a mid-size MLP).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch

from nerfmeta.data.synthetic import (
    CAMERA_ANGLE_X,
    FAR,
    NEAR,
    render_views,
    tiny_aabb,
    tiny_cameras,
    write_tiny_scene,
)
from nerfmeta.data.write import write_blender_scene
from nerfmeta.fields.registry import default_config
from nerfmeta.fit.checkpoint import CHECKPOINT_NAME
from nerfmeta.fit.loop import FitConfig, StepRecord
from nerfmeta.fit.run import RunConfig, run_fit
from nerfmeta.geometry.metrics import GeometryConfig
from nerfmeta.io import load_tensors, write_bytes_atomic

log = logging.getLogger(__name__)

MAX_PSNR_GAP = 0.5
"""A scaled or translated scene must fit to within this many dB of the original."""
MAX_CHAMFER_GAP = 0.5
"""A scaled surface scene must also be within this many points of Chamfer (% of the bounding-box diagonal) of the original."""
STRESS_GEOMETRY = GeometryConfig(n_points=100000, resolution=128, floor=False)
"""How the surface rows are measured: marching cubes at 128^3, 100k points a surface (sampling floor ~0.2 %)."""
NAN_WORDS = ("nan loss", "inf loss", "non-finite", "not finite", "NaN in", "nan in")
"""Phrases of an error message that report a NaN or inf (the guard's and the checkpoint writer's)."""

# ---------------------------------------------------------------------------------------------
# Scene writers and perturbations


def transform_blender_scene(
    src: str | Path,
    dst: str | Path,
    *,
    scale: float = 1.0,
    offset: Sequence[float] = (0.0, 0.0, 0.0),
    drop: Sequence[str] = (),
) -> Path:
    """Copy a Blender-format scene with its geometry moved by ``x -> scale * x + offset``.

    Camera centres, ``near``/``far`` (2 and 6 when the file has none) and the ``aabb`` follow; the
    rotations and images are unchanged, so the copy shows exactly the same pictures of the same
    scene at another size and place.

    Args:
        src: a Blender-format scene folder (``transforms_{train,val,test}.json`` + images).
        dst: the folder to write (created; must not exist yet).
        scale: positive factor on every length.
        offset: (3,) translation added after scaling.
        drop: top-level keys to leave out of the copy (e.g. ``("aabb",)``: bounds from the frusta).

    Returns:
        ``dst``.
    """
    src, dst = Path(src), Path(dst)
    if not scale > 0 or not math.isfinite(scale):
        raise ValueError(f"scale must be a finite number > 0, got {scale}")
    shift = np.asarray(offset, dtype=np.float64)
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("transforms_*.json"))
    for file in sorted(src.glob("transforms_*.json")):
        doc = {k: v for k, v in json.loads(file.read_text()).items() if k not in drop}
        for frame in doc.get("frames", []):
            matrix = np.asarray(frame["transform_matrix"], dtype=np.float64)
            matrix[:3, 3] = scale * matrix[:3, 3] + shift
            frame["transform_matrix"] = matrix.tolist()
        doc["near"] = scale * float(doc.get("near", NEAR))
        doc["far"] = scale * float(doc.get("far", FAR))
        if "aabb" in doc:
            doc["aabb"] = (scale * np.asarray(doc["aabb"], dtype=np.float64) + shift).tolist()
        write_bytes_atomic(dst / file.name, (json.dumps(doc, indent=1) + "\n").encode())
    return dst


def write_uniform_scene(
    folder: str | Path, rgb: Sequence[float], *, n_train: int = 8, n_test: int = 4, size: int = 32
) -> Path:
    """Opaque images of one colour seen by the tiny scene's cameras; no ``aabb`` (bounds from the frusta).

    The only consistent answers are an empty scene in front of a background of that colour, or
    (for any other background) an opaque shell of that colour filling every ray's reach.

    Args:
        folder: destination (created).
        rgb: the colour, three values in [0, 1].
        n_train, n_test: views per split (cameras of :func:`~nerfmeta.data.synthetic.tiny_cameras`).
        size: image width and height in pixels.
    """
    value = np.round(np.clip(np.asarray(rgb, dtype=np.float64), 0.0, 1.0) * 255).astype(np.uint8)
    splits = {}
    for split, n, spiral in (("train", n_train, 0.5), ("test", n_test, 0.2)):
        if n:
            poses, _ = tiny_cameras(n, spiral, size)
            splits[split] = (np.broadcast_to(value, (n, size, size, 3)).copy(), poses)
    write_blender_scene(folder, splits, CAMERA_ANGLE_X, extra={"near": NEAR, "far": FAR})
    return Path(folder)


INSIDE_RADIUS = 2.5
INSIDE_BOX = 3.0


def write_inside_box_scene(folder: str | Path, *, n_train: int = 8, n_test: int = 4, size: int = 32, seed: int = 0) -> Path:
    """The spheres seen by cameras inside the scene box.

    Cameras at radius 2.5 look at the origin, the ``aabb`` is ``[-3, 3]^3`` (so every camera
    centre is inside it and rays start inside the box), ``near`` is 0.05 and ``far`` 6.
    """
    splits = {}
    for split, n, spiral in (("train", n_train, 0.5), ("test", n_test, 0.2)):
        if n:
            poses, intrinsics = tiny_cameras(n, spiral, size, radius=INSIDE_RADIUS)
            splits[split] = (render_views(poses, intrinsics, size, seed), poses)
    box = [[-INSIDE_BOX] * 3, [INSIDE_BOX] * 3]
    write_blender_scene(folder, splits, CAMERA_ANGLE_X, extra={"near": 0.05, "far": FAR, "aabb": box})
    return Path(folder)


def grazing_poses(aabb: Sequence[Sequence[float]], height: float = 4.0) -> torch.Tensor:
    """(8, 4, 4) cameras whose centres lie on the planes of the box's faces, looking along an axis.

    Four look straight down (-z) from ``z = height`` above the four vertical edges of the box; four
    look along -x from ``x = height`` at the four edges parallel to x. With an odd image width and
    height the centre column and row of pixels then lie exactly in two face planes, and the
    centre pixel's ray runs along an edge of the box: rays that graze the box.
    """
    (x0, y0, z0), (x1, y1, z1) = aabb
    poses = []
    for x, y in ((x0, y0), (x0, y1), (x1, y0), (x1, y1)):
        pose = torch.eye(4, dtype=torch.float64)  # camera axes = world axes: looks along -z
        pose[:3, 3] = torch.tensor([x, y, height], dtype=torch.float64)
        poses.append(pose)
    look_x = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64)  # right=y, up=z, back=+x
    for y, z in ((y0, z0), (y0, z1), (y1, z0), (y1, z1)):
        pose = torch.eye(4, dtype=torch.float64)
        pose[:3, :3] = look_x
        pose[:3, 3] = torch.tensor([height, y, z], dtype=torch.float64)
        poses.append(pose)
    return torch.stack(poses)


def write_grazing_scene(folder: str | Path, *, n_train: int = 8, n_test: int = 4, size: int = 33, seed: int = 0) -> Path:
    """The spheres in a box with no padding, seen partly by cameras whose rays graze the box.

    The ``aabb`` touches the spheres (no padding). Training views: ``n_train`` ordinary views and
    6 of the 8 :func:`grazing_poses`; test views: the other 2 grazing views and ``n_test - 2``
    ordinary ones. ``size`` should be odd (the centre pixels' rays then lie in the face planes).
    """
    aabb = tiny_aabb(seed, pad=0.0)
    graze = grazing_poses(aabb)
    ordinary_train, intrinsics = tiny_cameras(n_train, 0.5, size)
    ordinary_test, _ = tiny_cameras(max(0, n_test - 2), 0.2, size)
    train = torch.cat([ordinary_train, graze[[0, 1, 2, 4, 5, 6]]])
    test = torch.cat([graze[[3, 7]], ordinary_test])
    splits = {name: (render_views(poses, intrinsics, size, seed), poses) for name, poses in (("train", train), ("test", test))}
    write_blender_scene(folder, splits, CAMERA_ANGLE_X, extra={"near": NEAR, "far": FAR, "aabb": aabb})
    return Path(folder)


# ---------------------------------------------------------------------------------------------
# Settings and cases


@dataclass(frozen=True)
class StressSettings:
    """Scene sizes and fit settings of one form of the table."""

    name: str
    """``quick`` or ``full``."""
    size: int
    """Image side of the scenes (odd sizes are rounded up to the next odd number where a case needs one)."""
    n_train: int
    """Training views of the ordinary scenes."""
    n_test: int
    """Test views."""
    fit: FitConfig
    """Iterations, rays per iteration, evaluation."""
    models: Mapping[str, Mapping[str, Any]]
    """Backbone name -> config overrides on top of its defaults."""
    meta: Mapping[str, Any]
    """:class:`pretrain.meta.MetaConfig` fields of the meta-learning cases (per-backbone ``model`` inside)."""
    collection: Mapping[str, Any]
    """:class:`~nerfmeta.collection.generate.CollectionConfig` fields of the meta-learning collection."""


QUICK = StressSettings(
    name="quick",
    size=16,
    n_train=6,
    n_test=2,
    fit=FitConfig(iters=60, batch_rays=256, eval_every=0, checkpoint_every=0),
    models={
        # a short coarse stage with a faster density rate, so the switch to the fine stage, one growth
        # step and occupancy pruning all happen and the fit still learns within 60 iterations
        "grid": {"coarse_iters": 10, "coarse_lr_density": 1.0, "growth_steps": (20,), "occupancy_every": 20},
        "nerf": {"depth": 2, "width": 32, "skips": (), "n_samples": 16, "pos_freqs": 4, "lr": 0.01},
        "sdf": {"depth": 2, "width": 32, "feature_dim": 8, "color_width": 16, "n_samples": 32, "pos_freqs": 4, "lr": 5e-3,
                "occupancy_warmup": 20, "occupancy_every": 20, "hash_levels": 4, "hash_finest_res": 32, "nffb_width": 8},
    },
    meta={"meta_steps": 3, "meta_batch": 2, "support_rays": 64, "query_rays": 64, "inner_steps": 2, "eval_tasks": 1,
          "checkpoint_every": 0,
          "models": {"nerf": {"depth": 2, "width": 16, "skips": (), "n_samples": 8, "pos_freqs": 2},
                     "grid": {"num_voxels": 512, "feature_dim": 2, "mlp_width": 8}}},
    collection={"categories": ("mug", "vase"), "scenes_per_category": 3, "views": 4, "test_views": 1, "resolution": 16,
                "val_fraction": 0.0, "test_fraction": 0.34},
)
"""The CI form: every case in about a second (tiny networks, 60 iterations of 256 rays)."""

FULL = StressSettings(
    name="full",
    size=32,
    n_train=12,
    n_test=4,
    fit=FitConfig(iters=300, batch_rays=512, eval_every=0, checkpoint_every=0),
    # the grid as it ships (auto-sized, 100-step coarse stage, growth at 100/200/300); the MLP at
    # 4 x 64 with 24 samples and a 4x higher rate than the small preset, so a row takes ~20 s on 2 cores
    models={"grid": {}, "nerf": {"depth": 4, "width": 64, "skips": (2,), "n_samples": 24, "lr": 2e-3},
            "sdf": {"lr": 2e-3, "occupancy_warmup": 50, "occupancy_every": 25}},
    meta={"meta_steps": 20, "meta_batch": 4, "support_rays": 256, "query_rays": 256, "inner_steps": 3, "eval_tasks": 2,
          "checkpoint_every": 0, "models": {"nerf": {}, "grid": {}}},
    collection={"categories": ("mug", "vase"), "scenes_per_category": 4, "views": 8, "test_views": 2, "resolution": 32,
                "val_fraction": 0.0, "test_fraction": 0.25},
)
"""The benchmark form: 32 px scenes, 300 iterations of 512 rays, the grid's defaults and a mid-size MLP."""


SceneBuilder = Callable[[Path, StressSettings], Path]
ModelChange = Callable[[str, dict[str, Any]], dict[str, Any]]


@dataclass(frozen=True)
class StressCase:
    """One row group of the table: a scene, a change to the fit, what counts as a sane answer."""

    name: str
    """Row label."""
    build: SceneBuilder | None
    """Writes the scene into the given folder and returns its path (None for the meta-learning cases)."""
    backbones: tuple[str, ...] = ("grid", "nerf")
    """Backbones the case is fitted with."""
    model: ModelChange | None = None
    """Changes the backbone overrides: ``(backbone, overrides) -> overrides``."""
    min_psnr: float = 10.0
    """Lowest final test PSNR (dB) counted as sane."""
    reference: str | None = None
    """Name of a case whose test PSNR this one must match to within :data:`MAX_PSNR_GAP`."""
    normalize: bool = True
    """Load-time normalisation (``RunConfig.normalize``)."""
    meta_algo: str | None = None
    """For a meta-learning case, the algorithm (its scene is a generated collection)."""
    meta_lr_factor: float = 1.0
    """For a meta-learning case, factor on the default inner learning rates."""
    quick: bool = True
    """Part of the quick (CI) form."""
    expect_error: str | None = None
    """For an input that cannot be fitted: the error type name the case must raise (a clear one-line
    error is then the right outcome, ``ok``)."""
    truth: TruthFn | None = None
    """The exact surface of the case's scene (its folder -> SDF and box, file frame): the fit's mesh gets a
    Chamfer distance (:data:`STRESS_GEOMETRY`), compared with the reference's within :data:`MAX_CHAMFER_GAP`."""


TruthFn = Callable[[Path], tuple[Callable[[torch.Tensor], torch.Tensor], np.ndarray]]
"""A case folder -> the exact SDF (points (N, 3) -> (N,)) of its scene and its (2, 3) box, in the file's frame."""


def lr_times(factor: float) -> ModelChange:
    """A :data:`ModelChange` multiplying every learning rate of the backbone config by ``factor``.

    The learning-rate fields are ``lr`` and those named ``lr_*`` or ``*_lr_*`` (grid:
    ``coarse_lr_density``, ``lr_density``, ``lr_features``, ``lr_mlp``; nerf: ``lr``), taken from the
    overrides when given there, else from the backbone's defaults.
    """

    def change(backbone: str, overrides: dict[str, Any]) -> dict[str, Any]:
        defaults = dataclasses.asdict(default_config(backbone))
        out = dict(overrides)
        for name, value in defaults.items():
            if name == "lr" or name.startswith("lr_") or "_lr_" in name:
                out[name] = float(overrides.get(name, value)) * factor
        return out

    return change


def set_fields(**values: Any) -> ModelChange:
    """A :data:`ModelChange` setting fields of the backbone config."""
    return lambda backbone, overrides: {**overrides, **values}


def _odd(n: int) -> int:
    return n if n % 2 else n + 1


def _tiny(**kw: Any) -> SceneBuilder:
    """The tiny spheres scene with ``write_tiny_scene`` keywords (``n_train``, ``angle_x``, ``height`` ...)."""

    def build(folder: Path, s: StressSettings) -> Path:
        args = {"n_train": s.n_train, "n_test": s.n_test, "size": s.size, **kw}
        return write_tiny_scene(folder, **args)

    return build


def _non_square(folder: Path, s: StressSettings) -> Path:
    # 97 x 61 in the full form; the quick form keeps an odd, non-square shape at a third of the size
    # (at 97 x 61 the auto-sized grid has 85^3 voxels, more than 60 iterations can fill)
    width, height = (97, 61) if s.name == "full" else (33, 21)
    return write_tiny_scene(folder, n_train=s.n_train, n_test=s.n_test, size=width, height=height)


def _transformed(scale: float, offset: Sequence[float]) -> SceneBuilder:
    def build(folder: Path, s: StressSettings) -> Path:
        original = write_tiny_scene(folder.with_name(folder.name + "-original"), n_train=s.n_train, n_test=s.n_test, size=s.size)
        return transform_blender_scene(original, folder, scale=scale, offset=offset)

    return build


def _uniform(rgb: Sequence[float]) -> SceneBuilder:
    return lambda folder, s: write_uniform_scene(folder, rgb, n_train=s.n_train, n_test=s.n_test, size=s.size)


def _inside(folder: Path, s: StressSettings) -> Path:
    return write_inside_box_scene(folder, n_train=s.n_train, n_test=s.n_test, size=s.size)


def _no_aabb(n_train: int) -> SceneBuilder:
    def build(folder: Path, s: StressSettings) -> Path:
        original = write_tiny_scene(folder.with_name(folder.name + "-original"), n_train=n_train, n_test=s.n_test, size=s.size)
        return transform_blender_scene(original, folder, drop=("aabb",))

    return build


def _single_view(folder: Path, s: StressSettings) -> Path:
    return write_tiny_scene(folder, n_train=1, n_test=0, size=s.size)


def _grazing(folder: Path, s: StressSettings) -> Path:
    return write_grazing_scene(folder, n_train=s.n_train, n_test=max(s.n_test, 3), size=_odd(s.size))


def _generated(category: str) -> SceneBuilder:
    """One scene of a generated collection of ``category`` (its exact SDF gives the fit a Chamfer distance)."""

    def build(folder: Path, s: StressSettings) -> Path:
        from nerfmeta.collection.generate import CollectionConfig, generate_collection
        from nerfmeta.collection.render import RenderConfig

        config = CollectionConfig(categories=(category,), scenes_per_category=1, views=s.n_train, test_views=s.n_test,
                                  resolution=s.size, val_fraction=0.0, test_fraction=0.0, render=RenderConfig(supersample=1))
        generate_collection(config, folder)
        return folder / category / f"{category}_000"

    return build


def _generated_scaled(category: str, scale: float) -> tuple[SceneBuilder, TruthFn]:
    """A generated scene of ``category`` with every length times ``scale``, and its exact SDF scaled alike.

    The scene is generated beside the case folder (``<folder>-original``) and copied by
    :func:`transform_blender_scene`; the copy is outside any collection, so its truth comes from the
    original's SDF: ``f_s(x) = scale * f(x / scale)``.
    """
    generate = _generated(category)

    def original(folder: Path) -> Path:
        return folder.with_name(folder.name + "-original") / category / f"{category}_000"

    def build(folder: Path, s: StressSettings) -> Path:
        generate(folder.with_name(folder.name + "-original"), s)
        return transform_blender_scene(original(folder), folder, scale=scale)

    def truth(folder: Path) -> tuple[Callable[[torch.Tensor], torch.Tensor], np.ndarray]:
        from nerfmeta.geometry.truth import scene_sdf_of

        sdf, box = scene_sdf_of(original(folder))
        return (lambda x: scale * sdf(x / scale)), np.asarray(box, dtype=np.float64) * scale

    return build, truth


def surface_chamfer(run: Path, truth: tuple[Callable[[torch.Tensor], torch.Tensor], np.ndarray]) -> float:
    """Chamfer distance (% of the bounding-box diagonal) of a fitted run's mesh against an exact SDF (file frame)."""
    from nerfmeta.geometry.load import load_run_model
    from nerfmeta.geometry.runs import evaluate_mesh, mesh_in_file_frame
    from nerfmeta.geometry.truth import sample_sdf_surface

    sdf, box = truth
    gt = sample_sdf_surface(sdf, box, STRESS_GEOMETRY.n_points, resolution=STRESS_GEOMETRY.resolution, seed=STRESS_GEOMETRY.seed)
    model, scene = load_run_model(run)
    mesh = mesh_in_file_frame(model, scene, STRESS_GEOMETRY.resolution, colors=False)
    return float(evaluate_mesh(mesh, gt, STRESS_GEOMETRY).chamfer_pct_diagonal)


_CHAIR = _generated_scaled("chair", 1.0)
_CHAIR_SMALL = _generated_scaled("chair", 1e-3)
_CHAIR_LARGE = _generated_scaled("chair", 1e3)

FAR_OFF = (1000.0, 0.0, 0.0)
FAR_FAR_OFF = (1e6, 0.0, 0.0)

CASES: tuple[StressCase, ...] = (
    StressCase("1 training view", _tiny(n_train=1), min_psnr=8.0),
    StressCase("2 training views", _tiny(n_train=2), min_psnr=8.0),
    StressCase("3 training views", _tiny(n_train=3), min_psnr=8.0),
    StressCase("1 training view, no aabb", _no_aabb(1), min_psnr=8.0),
    StressCase("1 view in all (no test view)", _single_view, backbones=("grid",), expect_error="SceneError"),
    StressCase("uniform white images", _uniform((1.0, 1.0, 1.0)), min_psnr=30.0),
    StressCase("uniform black images", _uniform((0.0, 0.0, 0.0)), min_psnr=15.0),
    StressCase("non-square images", _non_square),
    StressCase("170 degree field of view", _tiny(angle_x=math.radians(170.0))),
    StressCase("1 degree field of view", _tiny(angle_x=math.radians(1.0))),
    StressCase("camera inside the box", _inside),
    StressCase("rays grazing the box", _grazing),
    StressCase("pos_freqs 16", _tiny(), backbones=("nerf",), model=set_fields(pos_freqs=16)),
    StressCase("learning rates x10", _tiny(), model=lr_times(10.0), min_psnr=8.0),
    # Meta rows check that meta-training stays finite (min_psnr 0): at 10x the inner steps may overshoot,
    # which the note shows as a held-out PSNR that drops with adaptation.
    StressCase("MAML inner lr x10", None, backbones=("nerf",), meta_algo="maml", meta_lr_factor=10.0, min_psnr=0.0),
    StressCase("FOMAML inner lr x10", None, backbones=("grid",), meta_algo="fomaml", meta_lr_factor=10.0, min_psnr=0.0),
    StressCase("original (reference)", _tiny()),
    StressCase("poses x 1e-3", _transformed(1e-3, (0.0, 0.0, 0.0)), reference="original (reference)"),
    StressCase("poses x 1e3", _transformed(1e3, (0.0, 0.0, 0.0)), reference="original (reference)"),
    StressCase("translated +1e3 x", _transformed(1.0, FAR_OFF), reference="original (reference)"),
    StressCase("translated +1e6 x", _transformed(1.0, FAR_FAR_OFF), reference="original (reference)", quick=False),
    # Surfaces (issue 19): the SDF backbone, encodings at their limits (full form; tests/test_sdf.py runs them small)
    StressCase("sdf (reference)", _tiny(), backbones=("sdf",), quick=False),
    StressCase("sdf, poses x 1e-3", _transformed(1e-3, (0.0, 0.0, 0.0)), backbones=("sdf",), reference="sdf (reference)", quick=False),
    StressCase("sdf, poses x 1e3", _transformed(1e3, (0.0, 0.0, 0.0)), backbones=("sdf",), reference="sdf (reference)", quick=False),
    StressCase("thin parts (a chair)", _generated("chair"), backbones=("sdf", "nerf"), min_psnr=8.0, quick=False),
    StressCase("sdf, a generated chair (reference)", _CHAIR[0], backbones=("sdf",), min_psnr=8.0, quick=False, truth=_CHAIR[1]),
    StressCase("sdf, chair x 1e-3", _CHAIR_SMALL[0], backbones=("sdf",), min_psnr=8.0, quick=False, truth=_CHAIR_SMALL[1],
               reference="sdf, a generated chair (reference)"),
    StressCase("sdf, chair x 1e3", _CHAIR_LARGE[0], backbones=("sdf",), min_psnr=8.0, quick=False, truth=_CHAIR_LARGE[1],
               reference="sdf, a generated chair (reference)"),
    StressCase("hash table of 4 entries", _tiny(), backbones=("sdf", "nerf"), model=set_fields(encoding="hash", hash_log2_size=2),
               min_psnr=8.0, quick=False),
    StressCase("Fourier sigma 1e3", _tiny(), backbones=("sdf", "nerf"), model=set_fields(encoding="fourier", fourier_sigma=1000.0),
               min_psnr=5.0, quick=False),
    StressCase("poses x 1e-3, no normalisation", _transformed(1e-3, (0.0, 0.0, 0.0)), normalize=False, quick=False),
    StressCase("poses x 1e3, no normalisation", _transformed(1e3, (0.0, 0.0, 0.0)), normalize=False, quick=False),
    StressCase("translated +1e3 x, no normalisation", _transformed(1.0, FAR_OFF), normalize=False, quick=False),
    StressCase("translated +1e6 x, no normalisation", _transformed(1.0, FAR_FAR_OFF), normalize=False, quick=False),
)
"""The table, in order (the issue's list). Reference cases come before the cases that compare
with them. The ``no normalisation`` rows (full form only) show what the load-time normalisation
changes; they are reported, with their PSNR difference, but are not required to match."""


# ---------------------------------------------------------------------------------------------
# Running


@dataclass
class CaseResult:
    """What happened in one case with one backbone (one row of the table)."""

    case: str
    backbone: str
    outcome: str
    """``ok``, or why not: ``error: <message>``, ``NaN ...``, ``PSNR ... below ...``."""
    test_psnr: float | None
    guard_events: list[dict[str, Any]] | None
    """``summary.json["guard_events"]`` of the fit (None when the fit loop does not write the key)."""
    nan_seen: bool
    time_s: float
    psnr_gap: float | None = None
    """Test PSNR minus the reference case's, for cases with a reference (or a ``no normalisation`` twin)."""
    note: str = ""
    chamfer_pct: float | None = None
    """Chamfer distance of the fit's surface (% of the diagonal), for cases with a ``truth``."""
    chamfer_gap: float | None = None
    """``chamfer_pct`` minus the reference case's (percentage points)."""

    @property
    def ok(self) -> bool:
        return self.outcome == "ok"


class NanWatch:
    """Fit callback: notes the first iteration with a non-finite training loss or parameter."""

    def __init__(self) -> None:
        self.first: str | None = None

    def __call__(self, record: StepRecord, model: torch.nn.Module, state: Any) -> None:
        if self.first is not None:
            return
        if not math.isfinite(record.train_psnr) and not record.train_psnr == math.inf:
            self.first = f"iter {record.iter}: training PSNR {record.train_psnr}"
            return
        for name, p in model.named_parameters():
            if not bool(torch.isfinite(p).all()):
                self.first = f"iter {record.iter}: non-finite {name}"
                return


def nonfinite_tensors(path: Path) -> list[str]:
    """Names of the floating-point tensors in a safetensors file that hold NaN or inf."""
    return [k for k, v in load_tensors(path).items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]


def _fit_case(case: StressCase, backbone: str, settings: StressSettings, scene: Path, out: Path) -> CaseResult:
    overrides = dict(settings.models.get(backbone, {}))
    if case.model is not None:
        overrides = case.model(backbone, overrides)
    config = RunConfig(scene=str(scene), backbone=backbone, model=overrides, fit=settings.fit, normalize=case.normalize)
    watch = NanWatch()
    summary = run_fit(config, out, callbacks=[watch])
    bad = nonfinite_tensors(out / CHECKPOINT_NAME)
    psnr = summary.get("test_psnr")
    events = summary.get("guard_events") or []
    nan_events = [e for e in events if any(k in str(e.get("reason", "")) for k in NAN_WORDS)]
    nan_seen = watch.first is not None or bool(bad) or bool(nan_events) or psnr is None or math.isnan(psnr)
    outcome = "ok"
    if watch.first is not None:
        outcome = f"NaN during training ({watch.first})"
    elif bad:
        outcome = f"NaN in saved parameters ({', '.join(bad[:3])})"
    result = CaseResult(case.name, backbone, outcome, psnr, summary.get("guard_events"), nan_seen, 0.0)
    norm = summary.get("normalization")
    if norm and (norm["scale"] != 1.0 or any(norm["offset"])):
        result.note = f"normalised: scale {norm['scale']:.4g}, offset [{', '.join(f'{v:.4g}' for v in norm['offset'])}]"
    geometry = summary.get("geometry") or {}
    if case.truth is not None:  # measured the same way for a case and its reference, scaled or not
        result.chamfer_pct = surface_chamfer(out, case.truth(scene))
        result.note = (result.note + "; " if result.note else "") + f"Chamfer {result.chamfer_pct:.2f}% of the diagonal (128^3, 100k points)"
    elif "chamfer_pct_diagonal" in geometry:
        result.note = (result.note + "; " if result.note else "") + f"Chamfer {geometry['chamfer_pct_diagonal']:.2f}% of the diagonal"
    return result


def _meta_case(case: StressCase, backbone: str, settings: StressSettings, folder: Path, out: Path) -> CaseResult:
    from nerfmeta.collection.generate import CollectionConfig, generate_collection
    from nerfmeta.collection.render import RenderConfig
    from pretrain.meta import MetaConfig
    from pretrain.meta_run import meta_train, read_metrics

    collection = folder.parent / "meta-collection"
    if not collection.exists():
        generate_collection(CollectionConfig(**settings.collection, render=RenderConfig(supersample=1, max_steps=48)), collection)
    meta = {k: v for k, v in settings.meta.items() if k != "models"}
    base = MetaConfig(backbone=backbone, algo=case.meta_algo or "reptile", model=dict(settings.meta["models"].get(backbone, {})), **meta)
    lr, groups = base.inner_lr_resolved
    config = dataclasses.replace(base, inner_lr=lr * case.meta_lr_factor,
                                 inner_lr_groups={k: v * case.meta_lr_factor for k, v in groups.items()})
    summary = meta_train(config, collection, out)
    records = read_metrics(out / "metrics.jsonl")
    query = [r["query_psnr"] for r in records]
    bad = nonfinite_tensors(out / "model.safetensors")
    held = summary.get("held_out") or {}
    psnr = held.get("query_psnr_after", query[-1] if query else None)
    nan_seen = bool(bad) or any(not math.isfinite(q) for q in query) or psnr is None or not math.isfinite(psnr)
    outcome = "ok" if not nan_seen else "NaN in the meta-training" + (f" ({', '.join(bad[:3])})" if bad else "")
    result = CaseResult(case.name, backbone, outcome, psnr, summary.get("guard_events"), nan_seen, 0.0)
    before = held.get("query_psnr_before", float("nan"))
    worse = ", adaptation lowers it: the inner steps overshoot" if psnr is not None and psnr < before else ""
    result.note = (f"held-out query PSNR after {config.inner_steps} inner steps ({before:.2f} dB before{worse}); "
                   f"inner lr {config.inner_lr:g}" + (f", groups {', '.join(f'{k} {v:g}' for k, v in config.inner_lr_groups.items())}"
                                                     if config.inner_lr_groups else ""))
    return result


def _built_scene(case: StressCase, folder: Path, settings: StressSettings) -> Path:
    """The case's scene, written into ``folder`` by its first backbone and reused by the next ones.

    A builder may return a path below ``folder`` (a generated collection's scene), so the path it
    returned is kept beside the folder (``<folder>.scene``) rather than assumed to be the folder.
    """
    record = folder.with_name(folder.name + ".scene")
    if folder.exists() and record.is_file():
        return Path(record.read_text())
    scene = case.build(folder, settings)  # type: ignore[misc]
    record.write_text(str(scene))
    return scene


def run_case(case: StressCase, backbone: str, settings: StressSettings, workdir: Path) -> CaseResult:
    """Write the case's scene under ``workdir``, fit it with ``backbone`` and check the outcome.

    An exception in writing, loading or fitting becomes the result's ``error: ...`` outcome (the
    traceback is logged at debug level); the PSNR checks are applied by :func:`check_results`.
    """
    slug = "".join(c if c.isalnum() else "-" for c in case.name.lower()).strip("-")
    folder = workdir / slug
    out = workdir / f"run-{slug}-{backbone}"
    start = time.perf_counter()
    try:
        if case.meta_algo is not None:
            result = _meta_case(case, backbone, settings, folder, out)
        else:
            scene = _built_scene(case, folder, settings)
            result = _fit_case(case, backbone, settings, scene, out)
        if case.expect_error is not None:
            result.outcome = f"ran, but {case.expect_error} was expected"
    except Exception as err:  # recorded as the case's outcome, see the module docstring
        log.debug("stress case %s (%s) failed", case.name, backbone, exc_info=True)
        message = " ".join(str(err).replace(str(folder), "SCENE").split()) or type(err).__name__
        if type(err).__name__ == case.expect_error:
            result = CaseResult(case.name, backbone, "ok", None, None, False, 0.0, note=f"expected error: {message}")
        else:
            nan = isinstance(err, FloatingPointError) or any(k in message for k in NAN_WORDS)
            result = CaseResult(case.name, backbone, f"error: {type(err).__name__}: {message}", None, None, nan, 0.0)
    result.time_s = time.perf_counter() - start
    return result


def check_results(results: Sequence[CaseResult], cases: Sequence[StressCase] = CASES) -> None:
    """Apply the PSNR checks in place: finite, at least ``min_psnr``, within the reference's gap (and, for
    surface cases with a ``truth``, a Chamfer within :data:`MAX_CHAMFER_GAP` of the reference's).

    Also fills ``psnr_gap`` of the ``no normalisation`` rows (against the normalised twin), for
    information.
    """
    by_name = {c.name: c for c in cases}
    psnr = {(r.case, r.backbone): r.test_psnr for r in results}
    chamfer = {(r.case, r.backbone): r.chamfer_pct for r in results}
    for r in results:
        case = by_name[r.case]
        if case.expect_error is not None:
            continue
        if r.ok and (r.test_psnr is None or not math.isfinite(r.test_psnr)):
            r.outcome = f"test PSNR is {r.test_psnr}"
            r.nan_seen = r.nan_seen or r.test_psnr is None or math.isnan(r.test_psnr)
        elif r.ok and r.test_psnr < case.min_psnr:
            r.outcome = f"test PSNR {r.test_psnr:.2f} dB below the sane floor {case.min_psnr:g} dB"
        twin = case.reference or (r.case.replace(", no normalisation", "") if not case.normalize else None)
        if twin is not None and r.test_psnr is not None and psnr.get((twin, r.backbone)) is not None:
            r.psnr_gap = r.test_psnr - psnr[(twin, r.backbone)]
            if r.ok and case.reference is not None and abs(r.psnr_gap) > MAX_PSNR_GAP:
                r.outcome = f"test PSNR {r.psnr_gap:+.2f} dB from {case.reference}, more than {MAX_PSNR_GAP:g} dB"
        ref_chamfer = chamfer.get((case.reference, r.backbone))
        if r.chamfer_pct is not None and ref_chamfer is not None:
            r.chamfer_gap = r.chamfer_pct - ref_chamfer
            if r.ok and abs(r.chamfer_gap) > MAX_CHAMFER_GAP:
                r.outcome = f"Chamfer {r.chamfer_gap:+.2f} points from {case.reference}, more than {MAX_CHAMFER_GAP:g}"


def run_table(
    settings: StressSettings,
    workdir: str | Path,
    *,
    cases: Sequence[StressCase] | None = None,
    progress: Callable[[CaseResult], None] | None = None,
) -> list[CaseResult]:
    """Run every case (those of the quick form for :data:`QUICK`) with each of its backbones.

    Args:
        settings: :data:`QUICK` or :data:`FULL` (or your own).
        workdir: an empty scratch folder for the scenes and run folders.
        cases: the cases (default :data:`CASES`, filtered by ``quick`` for the quick form).
        progress: called with each result as it is done.

    Returns:
        One :class:`CaseResult` per (case, backbone), checked by :func:`check_results`.
    """
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    chosen = list(cases if cases is not None else [c for c in CASES if c.quick or settings.name != "quick"])
    results = []
    for case in chosen:
        for backbone in case.backbones:
            result = run_case(case, backbone, settings, workdir)
            results.append(result)
            if progress is not None:
                progress(result)
    check_results(results, chosen)
    return results


def format_table(results: Sequence[CaseResult]) -> list[str]:
    """The results as Markdown table lines."""
    lines = ["| case | backbone | what happened | test PSNR (dB) | vs reference (dB) | guard events | NaN seen | time (s) | notes |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        psnr = "-" if r.test_psnr is None else f"{r.test_psnr:.2f}"
        gap = "" if r.psnr_gap is None else f"{r.psnr_gap:+.2f}"
        if r.chamfer_gap is not None:
            gap += f"; Chamfer {r.chamfer_gap:+.2f} points"
        if r.guard_events is None:
            guard = "n/a"
        elif not r.guard_events:
            guard = "0"
        else:
            reasons = sorted({str(e.get("reason", "?")) for e in r.guard_events})
            guard = f"{len(r.guard_events)} ({'; '.join(reasons)})"
        outcome = r.outcome.replace("|", "/")
        note = r.note.replace("|", "/")
        lines.append(f"| {r.case} | {r.backbone} | {outcome} | {psnr} | {gap} | {guard} | {'yes' if r.nan_seen else 'no'} "
                     f"| {r.time_s:.1f} | {note} |")
    return lines
