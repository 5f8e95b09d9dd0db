"""Held-out tiles: a square of some training views that the fit never trains on, to see when it starts to overfit.

A grid fit of few views memorises them: on generated objects with 16 training views (96 px) the test PSNR peaks
after 350-500 steps and falls 0.3-0.9 dB by 1000 while the training PSNR climbs to 49 dB (BENCHMARKS.md,
*Stopping where the held-out pixels stop improving*). Where that happens depends on the scene, not on a fixed count.

Training views keep one square tile each out of training (``FitConfig.holdout_tile``: its side as a fraction of the
view's shorter side), placed at random from the fit's seed; as many views as hold ``holdout_rays`` pixels in their
tiles, at least 8 (all of a 16-view scene at 96 px: 2.8 % of its pixels). The fit's sampler never draws those pixels;
every ``holdout_every`` steps the fit renders them (a regular subsample of at most ``holdout_rays``) and pools their
squared error into one PSNR. The fit keeps a copy of the parameters with the best held-out PSNR so far
(:class:`BestSnapshot`; scores start again after the model grows), stops once ``patience`` steps pass without a better
one and the last is ``patience_db`` below it, and then ends with the best copy. A fit still at its best score at
``holdout_release`` (3/4) of its length has not overfitted: it gives the tiles back to training for the rest.

Only fits of few views do this (``holdout_max_views``, 20): on 24- and 40-view scenes at 128 px the tiles' score
flattened or fell by 0.2 dB while the test views' still rose by 0.5-0.8 dB, so stopping there cost up to 0.5 dB. And
only fits of objects (``holdout_scene_types``): on generated forward-facing scenes of 14 and 17 views the same happened,
and the early stop cost 0.1-0.6 dB in 5 fits of 6; on a real unbounded capture of 20 views it gained 0.25 dB but lost
0.04 in LPIPS (a smoother picture).

Why tiles and not a held-out view: a whole view left out costs a sixteenth of the data of a 16-view scene (0.4 dB
on a generated chair at its peak), and one view's PSNR follows that view's own quirks (a lamp's view 0 scored
17.5 dB against 30 on the test views). A tile's pixels are still seen from the other views, so the information lost
is small, while the voxels behind it are fitted only through other views' rays. Tiles placed where a view's colours
vary most (tried) sat on silhouette edges, whose error kept falling while the test views' rose.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from nerfmeta.fields.base import RadianceModel


@dataclass(frozen=True)
class Tiles:
    """A square tile in some views of a split: pixels ``rows[v] <= row < rows[v] + side`` and ``cols[v] <= col <
    cols[v] + side`` of view ``v``; a view without a tile has ``rows[v]`` past its last row."""

    side: int
    rows: torch.Tensor
    """(V,) each view's tile's first row (the view's height where it has none)."""
    cols: torch.Tensor
    """(V,) each view's tile's first column."""
    views: torch.Tensor
    """(K,) the views (positions in the split) that have a tile, ascending."""

    def contains(self, view: torch.Tensor, row: torch.Tensor, col: torch.Tensor) -> torch.Tensor:
        """(N,) bool: is pixel (``row``, ``col``) of ``view`` in that view's tile."""
        r0, c0 = self.rows[view], self.cols[view]
        return (row >= r0) & (row < r0 + self.side) & (col >= c0) & (col < c0 + self.side)

    def held_fraction(self, height: int, width: int) -> float:
        """The fraction of the split's pixels held out (its views ``height`` x ``width``)."""
        return len(self.views) * self.side * self.side / (len(self.rows) * height * width)


MIN_TILED_VIEWS = 8
"""Views that get a tile at least (all where there are fewer): a score pooled over several views, not one view's quirks."""


def tile_side(height: int, width: int, fraction: float) -> int:
    """The side in pixels of a tile of ``fraction`` of the shorter side: at least 1, and 0 (no tile) where the view is
    too small to keep pixels for training beside it (fraction 0, or a tile as wide as the view)."""
    if fraction <= 0:
        return 0
    side = max(1, round(fraction * min(height, width)))
    return side if side < min(height, width) else 0


def tiled_views(n_views: int, side: int, pixels: int) -> int:
    """How many of ``n_views`` views get a tile of ``side`` px: enough for ``pixels`` held-out pixels (0: every view),
    at least :data:`MIN_TILED_VIEWS`, at most all."""
    if pixels <= 0:
        return n_views
    return min(n_views, max(MIN_TILED_VIEWS, math.ceil(pixels / (side * side))))


def place_tiles(n_views: int, height: int, width: int, fraction: float, seed: int, pixels: int = 0) -> Tiles | None:
    """A tile of :func:`tile_side` in :func:`tiled_views` of ``n_views`` views of ``height`` x ``width``, the views and
    each tile's position drawn uniformly (seeded by ``seed``); None where :func:`tile_side` gives none.

    Uniform, not where a view's colours vary most: tiles put there (session 44) sat on the object's silhouette edges,
    whose error kept falling as the edges sharpened while the test views' error rose."""
    side = tile_side(height, width, fraction)
    if side == 0 or n_views == 0:
        return None
    gen = torch.Generator().manual_seed(seed + 7_919)
    views = torch.randperm(n_views, generator=gen)[: tiled_views(n_views, side, pixels)].sort().values
    rows = torch.full((n_views,), height, dtype=torch.long)
    cols = torch.zeros(n_views, dtype=torch.long)
    rows[views] = torch.randint(height - side + 1, (len(views),), generator=gen)
    cols[views] = torch.randint(width - side + 1, (len(views),), generator=gen)
    return Tiles(side, rows, cols, views)


def tile_pixels(tiles: Tiles, max_rays: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(view, row, col) of the tiles' pixels, every s-th row and column of each tile (s the smallest stride that gives
    at most ``max_rays`` pixels in all; 0: every pixel), view by view."""
    n_tiles = len(tiles.views)
    stride = 1
    while max_rays > 0 and stride < tiles.side and n_tiles * math.ceil(tiles.side / stride) ** 2 > max_rays:
        stride += 1
    offsets = torch.arange(0, tiles.side, stride)
    dr, dc = torch.meshgrid(offsets, offsets, indexing="ij")
    dr, dc = dr.reshape(-1), dc.reshape(-1)
    view = tiles.views.repeat_interleave(len(dr))
    return view, tiles.rows[view] + dr.repeat(n_tiles), tiles.cols[view] + dc.repeat(n_tiles)


@dataclass
class BestSnapshot:
    """The parameters (and model structure) at the step with the best held-out PSNR so far."""

    step: int
    psnr: float
    structure: dict[str, Any]
    tensors: dict[str, torch.Tensor]

    @classmethod
    def of(cls, model: RadianceModel, step: int, psnr: float) -> "BestSnapshot":
        return cls(step, psnr, model.structure(), {k: v.detach().clone() for k, v in model.state_dict().items()})

    def restore(self, model: RadianceModel) -> None:
        """Put the snapshot's structure and parameters back into ``model`` (as a checkpoint's are:
        :meth:`~nerfmeta.fields.base.RadianceModel.load_state`)."""
        model.load_state(self.structure, self.tensors)

    def meta(self) -> dict[str, Any]:
        """The JSON part kept in a checkpoint (the tensors go beside it)."""
        return {"step": self.step, "psnr": self.psnr, "structure": self.structure}
