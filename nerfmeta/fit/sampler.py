"""Training rays: seeded random pixels from the training views, rays computed per batch.

Rays are made in the space the scene is fitted in: the world for object and unbounded scenes, the
normalised device coordinates of :mod:`nerfmeta.render.ndc` for a forward-facing scene once
:func:`fit_space` has set its ``ndc`` (from the near plane, 0, to infinity).
"""

from __future__ import annotations

from dataclasses import replace

import torch

from nerfmeta.data.scene import RayBatch, Scene
from nerfmeta.errors import ConfigError
from nerfmeta.fit.holdout import Tiles, tile_pixels
from nerfmeta.render.ndc import NEAR_FACTOR, NDCSpace, ndc_box, ndc_space, to_ndc
from nerfmeta.render.rays import camera_rays, image_rays

NDC_DEPTH_SCALE = 0.5
"""Depth axis of a forward scene's NDC box, ``[-0.5, 0.5]`` (see :class:`~nerfmeta.render.ndc.NDCSpace`): a
grid of cubic voxels then has twice as many voxels across as in depth, as DirectVoxGO's LLFF grids have
more (362 x 362 x 128), and a ray marches fewer samples (82 instead of 118 per test ray on the generated
forward scene at 160 x 120)."""


def fit_space(scene: Scene, near_factor: float = NEAR_FACTOR) -> Scene:
    """The scene as a fit sees it: a forward-facing scene in NDC (its ``ndc`` set, ``bounds`` the NDC box
    holding every pixel ray, ``near`` 0 and ``far`` the box's diagonal); any other scene unchanged.

    ``near_factor``: the NDC near plane's distance as a fraction of the scene's near bound (see
    :func:`~nerfmeta.render.ndc.ndc_space`; a run passes its recorded ``ndc_near_factor``)."""
    if scene.scene_type.kind != "forward" or scene.ndc is not None:
        return scene
    space = ndc_space(scene.poses, scene.intrinsics, scene.height, scene.width, scene.near, depth_scale=NDC_DEPTH_SCALE,
                      near_factor=near_factor)
    try:
        box = ndc_box(space, scene.poses, scene.intrinsics, scene.height, scene.width).float()
    except ValueError as err:
        raise ConfigError(f"{scene.source}: fitted as forward-facing ({scene.scene_type.reason}), but {err}; "
                          "pass --scene-type object or unbounded") from err
    return replace(scene, ndc=space, bounds=box, near=0.0, far=float(torch.linalg.vector_norm(box[1] - box[0])))


def rays_in_space(
    ndc: NDCSpace | None, origins: torch.Tensor, directions: torch.Tensor, near: float, far: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """World rays (n, 3) each as the model sees them: origins, unit directions, near (n,) and far (n,).

    Without ``ndc``: unchanged, on ``[near, far]``. With it: in NDC from the near plane (0) to infinity.
    """
    if ndc is not None:
        o, u, length = to_ndc(ndc, origins, directions)
        return o, u, torch.zeros_like(length), length
    n = origins.shape[0]
    return (origins, directions, torch.full((n,), near, dtype=origins.dtype, device=origins.device),
            torch.full((n,), far, dtype=origins.dtype, device=origins.device))


class RaySampler:
    """Draws random training pixels (uniformly over all pixels of all views of a split, less any held-out tiles).

    Rays are built per batch from the pose and intrinsics of each pixel's view, so memory holds
    only the images, not one ray per pixel. With ``tiles`` (:func:`~nerfmeta.fit.holdout.place_tiles`, indexed by the
    views' positions in the split; a fit may set them to None to give them back to training) a draw that lands in a view's tile is drawn again, so the tiles' pixels are never trained on;
    :meth:`held_out` gives them as rays to score.
    """

    def __init__(self, scene: Scene, split: str, device: torch.device | str, tiles: Tiles | None = None):
        idx = scene.split_indices(split)
        if len(idx) == 0:
            raise ValueError(f"scene has no '{split}' views")
        self.images = scene.images[idx].to(device)
        self.alphas = None if scene.alphas is None else scene.alphas[idx].to(device)
        self.poses = scene.poses[idx].to(device)
        self.intrinsics = scene.intrinsics[idx].to(device)
        self.near, self.far = float(scene.near), float(scene.far)
        self.ndc = scene.ndc
        self.n_views, self.height, self.width = self.images.shape[:3]
        if tiles is not None and len(tiles.rows) != self.n_views:
            raise ValueError(f"{len(tiles.rows)} tiles for {self.n_views} '{split}' views")
        self.tiles = tiles

    @property
    def n_pixels(self) -> int:
        return self.n_views * self.height * self.width

    def sample(self, n_rays: int, generator: torch.Generator) -> RayBatch:
        """A batch of ``n_rays`` random training rays with their target colours."""
        return self.draw(n_rays, generator)[0]

    def _pixels(self, flat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        hw = self.height * self.width
        view, pix = flat // hw, flat % hw
        return view, pix // self.width, pix % self.width

    def draw(self, n_rays: int, generator: torch.Generator) -> tuple[RayBatch, torch.Tensor]:
        """:meth:`sample`'s batch and (n_rays,) the position of each ray's view in the split."""
        flat = torch.randint(self.n_pixels, (n_rays,), generator=generator)
        if self.tiles is not None:  # redraw what fell in a tile (a few percent of the pixels: a round or two)
            held = self.tiles.contains(*self._pixels(flat))
            while bool(held.any()):
                flat[held] = torch.randint(self.n_pixels, (int(held.sum()),), generator=generator)
                held = self.tiles.contains(*self._pixels(flat))
        view, row, col = (t.to(self.images.device) for t in self._pixels(flat))
        return self._batch(view, row, col), view

    def held_out(self, max_rays: int) -> RayBatch:
        """The held-out tiles' pixels as rays with their target colours (every s-th row and column of each tile where
        that keeps them within ``max_rays``, see :func:`~nerfmeta.fit.holdout.tile_pixels`)."""
        if self.tiles is None:
            raise ValueError("this sampler holds no tiles out")
        view, row, col = (t.to(self.images.device) for t in tile_pixels(self.tiles, max_rays))
        return self._batch(view, row, col)

    def _batch(self, view: torch.Tensor, row: torch.Tensor, col: torch.Tensor) -> RayBatch:
        dtype = self.poses.dtype
        xy = torch.stack([col.to(dtype) + 0.5, row.to(dtype) + 0.5], -1)
        origins, dirs = camera_rays(self.poses[view], self.intrinsics[view], xy)
        target = self.images[view, row, col]
        alpha = None if self.alphas is None else self.alphas[view, row, col]
        return RayBatch(*rays_in_space(self.ndc, origins, dirs, self.near, self.far), target, alpha)


def view_rays(scene: Scene, view: int, device: torch.device | str) -> RayBatch:
    """All pixel rays of one view, row-major, with the view's image as target."""
    pose, intr = scene.poses[view].to(device), scene.intrinsics[view].to(device)
    origins, dirs = image_rays(pose, intr, scene.height, scene.width)
    n = scene.height * scene.width
    target = scene.images[view].to(device).reshape(n, 3)
    return RayBatch(*rays_in_space(scene.ndc, origins.reshape(n, 3), dirs.reshape(n, 3), scene.near, scene.far), target)
