"""Typed scene data.

Conventions used everywhere in nerfmeta:

- Poses are camera-to-world 4x4 matrices in the OpenGL/Blender convention: camera x points
  right, y up, and the camera looks along its -z axis.
- Intrinsics are ``(fx, fy, cx, cy)`` in pixels, with pixel ``(i, j)`` (column, row) centred at
  ``(i + 0.5, j + 0.5)``.
- Images are float32 RGB in [0, 1], already composited on ``background``.
- ``near``/``far`` are distances along normalised ray directions.
- Positions, ``near``/``far`` and ``bounds`` are in the *loaded* frame: the file's frame after the
  scene's :class:`Normalization` (identity for scenes already in range; see
  :mod:`nerfmeta.data.normalize`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path, PurePath

import torch

from nerfmeta.data.scene_type import SceneType
from nerfmeta.errors import SceneError
from nerfmeta.render.ndc import NDCSpace

SPLITS = ("train", "val", "test")


@dataclass(frozen=True)
class Normalization:
    """The similarity transform from a scene file's frame to the loaded frame.

    ``x_loaded = scale * x_file + offset`` for points; lengths (``near``, ``far``, depths) are
    multiplied by ``scale``; rotations are unchanged. The default is the identity.

    Attributes:
        scale: positive factor applied to every length.
        offset: translation added after scaling, in loaded units.
    """

    scale: float = 1.0
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def is_identity(self) -> bool:
        return self.scale == 1.0 and all(v == 0.0 for v in self.offset)

    def apply_points(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) file-frame points -> loaded frame, in the dtype of ``points``."""
        offset = torch.tensor(self.offset, dtype=points.dtype, device=points.device)
        return points * self.scale + offset

    def invert_points(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) loaded-frame points (e.g. a model's box) -> the file's frame."""
        offset = torch.tensor(self.offset, dtype=points.dtype, device=points.device)
        return (points - offset) / self.scale

    def apply_poses(self, poses: torch.Tensor) -> torch.Tensor:
        """(..., 4, 4) file-frame camera-to-world matrices -> loaded frame (rotation kept)."""
        out = poses.clone()
        out[..., :3, 3] = self.apply_points(poses[..., :3, 3])
        return out

    def invert_poses(self, poses: torch.Tensor) -> torch.Tensor:
        """(..., 4, 4) loaded-frame camera-to-world matrices -> the file's frame."""
        out = poses.clone()
        out[..., :3, 3] = self.invert_points(poses[..., :3, 3])
        return out

    def as_json(self) -> dict:
        return {"scale": self.scale, "offset": list(self.offset)}


@dataclass(frozen=True)
class Scene:
    """A set of posed images of one scene, with its splits.

    Attributes:
        images: (n_views, H, W, 3) float32 RGB in [0, 1], composited on ``background``.
        poses: (n_views, 4, 4) float32 camera-to-world, OpenGL convention.
        intrinsics: (n_views, 4) float32 ``(fx, fy, cx, cy)`` in pixels.
        near: distance to start rays at.
        far: distance to end rays at.
        bounds: (2, 3) float32 axis-aligned box ``[min_xyz, max_xyz]`` that holds the content.
        splits: split name -> tuple of view indices; ``train`` and ``test`` always present.
        holdout: how the test split was chosen, e.g. ``"from file"`` or ``"every 8th view"``.
        source: the folder or file the scene was read from.
        format: the name of the parser that read it.
        category: the scene's category when known (generated collections record it).
        background: RGB the alpha channel was composited on, None for opaque images.
        alphas: (n_views, H, W) float32 alpha in [0, 1] when the images had one, else None.
        image_names: one name per view, for reports.
        downscale: the factor the images were reduced by when read.
        normalization: the transform from the file's frame to the loaded one (poses, near, far
            and bounds are already transformed); the identity unless the loader applied one.
        near_far_source: where ``near``/``far`` came from (the file, a format's default, or
            derived from the cameras), for ``inspect`` and reports.
        scene_type: object, forward-facing or unbounded, and why
            (:mod:`nerfmeta.data.scene_type`).
        ndc: set when the scene is fitted in normalised device coordinates (a forward-facing scene
            after :func:`nerfmeta.fit.sampler.fit_space`): rays are made in this space, ``bounds`` is
            the NDC box and ``near``/``far`` are NDC distances (:mod:`nerfmeta.render.ndc`).
    """

    images: torch.Tensor
    poses: torch.Tensor
    intrinsics: torch.Tensor
    near: float
    far: float
    bounds: torch.Tensor
    splits: dict[str, tuple[int, ...]]
    holdout: str
    source: Path
    format: str
    category: str | None = None
    background: tuple[float, float, float] | None = (1.0, 1.0, 1.0)
    alphas: torch.Tensor | None = None
    image_names: tuple[str, ...] = field(default_factory=tuple)
    downscale: float = 1.0
    normalization: Normalization = field(default_factory=Normalization)
    near_far_source: str = "from file"
    scene_type: SceneType = field(default_factory=SceneType)
    ndc: NDCSpace | None = None

    @property
    def n_views(self) -> int:
        return int(self.images.shape[0])

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    def split_indices(self, split: str) -> torch.Tensor:
        """View indices of ``split`` as a LongTensor (empty if the split is absent)."""
        return torch.tensor(self.splits.get(split, ()), dtype=torch.long)

    def without_views(self, names: Sequence[str]) -> "Scene":
        """The scene without the views ``names`` (an image's name as :attr:`image_names` holds it, or its file
        name), from every split; the other views keep their splits.

        Raises:
            SceneError: a name that is not a view of the scene, or no training view left.
        """
        if not names:
            return self
        by_name: dict[str, set[int]] = {}
        for i, name in enumerate(self.image_names):
            for key in {name, PurePath(name).name}:
                by_name.setdefault(key, set()).add(i)
        unknown = [n for n in names if n not in by_name]
        if unknown:
            named = (f"views are named as in {', '.join(self.image_names[:3])}, ..." if self.image_names
                     else "its views have no names")
            raise SceneError(f"{self.source}: --drop-views names {', '.join(unknown)}, not a view of this scene "
                             f"({named})")
        ambiguous = [n for n in names if len(by_name[n]) > 1]
        if ambiguous:
            n = ambiguous[0]
            raise SceneError(f"{self.source}: --drop-views {n} is more than one view "
                             f"({', '.join(self.image_names[i] for i in sorted(by_name[n]))}); give its full name")
        drop = {next(iter(by_name[n])) for n in names}
        keep = [i for i in range(self.n_views) if i not in drop]
        new_index = {old: new for new, old in enumerate(keep)}
        splits = {k: tuple(new_index[i] for i in v if i in new_index) for k, v in self.splits.items()}
        if not splits.get("train"):
            raise SceneError(f"{self.source}: --drop-views leaves no training view")
        return self._views(torch.tensor(keep, dtype=torch.long), splits)

    def subset(self, split: str) -> "Scene":
        """The views of one split as a scene of their own (splits renumbered)."""
        idx = self.split_indices(split)
        return self._views(idx, {split: tuple(range(len(idx)))})

    def _views(self, idx: torch.Tensor, splits: dict[str, tuple[int, ...]]) -> "Scene":
        """The scene of the views ``idx`` (in that order) with ``splits`` over their new positions."""
        names = tuple(self.image_names[i] for i in idx.tolist()) if self.image_names else ()
        return replace(
            self,
            images=self.images[idx],
            poses=self.poses[idx],
            intrinsics=self.intrinsics[idx],
            alphas=None if self.alphas is None else self.alphas[idx],
            splits=splits,
            image_names=names,
        )


@dataclass(frozen=True)
class RayBatch:
    """A batch of rays.

    Attributes:
        origins: (n_rays, 3) ray origins in world space.
        directions: (n_rays, 3) unit ray directions in world space.
        near: (n_rays,) distance where sampling starts.
        far: (n_rays,) distance where sampling ends (``far >= near``).
        target: (n_rays, 3) ground-truth RGB, or None when rendering novel views.
        alpha: (n_rays,) ground-truth opacity when the scene has alphas (an SDF's mask loss), else None.
    """

    origins: torch.Tensor
    directions: torch.Tensor
    near: torch.Tensor
    far: torch.Tensor
    target: torch.Tensor | None = None
    alpha: torch.Tensor | None = None

    def __len__(self) -> int:
        return int(self.origins.shape[0])

    def to(self, device: torch.device | str) -> "RayBatch":
        return RayBatch(
            self.origins.to(device),
            self.directions.to(device),
            self.near.to(device),
            self.far.to(device),
            None if self.target is None else self.target.to(device),
            None if self.alpha is None else self.alpha.to(device),
        )

    def __getitem__(self, idx: slice | torch.Tensor) -> "RayBatch":
        return RayBatch(
            self.origins[idx],
            self.directions[idx],
            self.near[idx],
            self.far[idx],
            None if self.target is None else self.target[idx],
            None if self.alpha is None else self.alpha[idx],
        )
