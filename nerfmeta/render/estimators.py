"""Where along each ray to evaluate a field: packed ray marching and the occupancy-grid estimator.

An *estimator* turns rays into :class:`PackedSamples`: one flat list of samples sorted by ray, so
the work follows the samples that exist, not ``rays x longest ray``. :class:`OccupancyGrid` is the
estimator every backbone can share (nerfacc's ``OccGridEstimator``): it marches every ``step``
through its box, drops the samples whose nearest grid corner is marked empty (empty-space
skipping) and, given a density callback, the samples behind an opaque layer (early termination:
transmittance below ``early_stop_eps``). Its marks come from the field's own density: pruned
(:meth:`OccupancyGrid.prune`, marks only leave) or refreshed (:meth:`OccupancyGrid.refresh`,
marks follow the field) on the model's schedule.

A field that needs no estimator samples its own way (e.g. the NeRF MLP's stratified +
importance sampling in :mod:`nerfmeta.render.sampling`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import nn

from nerfmeta.render.rays import clip_to_aabb
from nerfmeta.render.volume import alpha_from_tau, packed_transmittance


@dataclass
class PackedSamples:
    """Samples of a batch of rays, flat and sorted by ray (front to back within a ray).

    Attributes:
        ray_idx: (M,) int64 non-decreasing, the ray of each sample.
        t: (M,) distance of each sample along its ray.
        delta: (M,) length of the interval each sample stands for (``tau = sigma * delta``).
        far: (n_rays,) where each ray's marched interval ends (for the depth of rays that pass through).
    """

    ray_idx: torch.Tensor
    t: torch.Tensor
    delta: torch.Tensor
    far: torch.Tensor

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def select(self, keep: torch.Tensor) -> "PackedSamples":
        """The samples at the sorted indices ``keep`` (K,) (order, hence packing, is preserved)."""
        return PackedSamples(self.ray_idx.index_select(0, keep), self.t.index_select(0, keep),
                             self.delta.index_select(0, keep), self.far)

    def points(self, origins: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
        """(M, 3) positions ``o + t d`` of the samples, from the rays' origins and directions (n_rays, 3).

        Stored component-major (the (M, 3) result is the transpose of a contiguous (3, M) tensor):
        a CPU gathers and updates long rows of one axis much faster than M rows of three values,
        and elementwise maths on the points keeps that layout.
        """
        o = origins.t().contiguous().index_select(1, self.ray_idx)
        d = directions.t().contiguous().index_select(1, self.ray_idx)
        return torch.addcmul(o, self.t[None], d).t()


def march_packed(
    near: torch.Tensor, far: torch.Tensor, step: float, jitter: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Samples every ``step`` from ``near`` to ``far``, packed (the packed form of ``fixed_step_samples``).

    Args:
        near, far: (n_rays,) with ``far >= near`` (equal: no samples).
        step: distance between samples.
        jitter: (n_rays,) in [0, 1): where each sample sits in its bin (0.5: the bin middle).

    Returns:
        ray_idx (M,) int64 non-decreasing, the ray of each sample; t (M,) distances; delta (M,)
        bin lengths (``step``, the last bin of a ray clipped at ``far``, so a ray's deltas sum
        to ``far - near``).
    """
    counts = torch.ceil((far - near) / step).clamp_(min=0)
    counts = (counts - ((counts > 0) & (near + step * (counts - 1) >= far)).to(counts.dtype)).long()  # rounding
    total = int(counts.sum())
    n = near.shape[0]
    ray_idx = torch.repeat_interleave(torch.arange(n, device=near.device), counts, output_size=total)
    first = torch.cumsum(counts, 0) - counts
    k = (torch.arange(total, device=near.device) - first.index_select(0, ray_idx)).to(near.dtype)
    t = torch.add((near + step * jitter).index_select(0, ray_idx), k, alpha=step)
    delta = torch.full_like(t, step)
    # The last bin of each ray ends at ``far``.
    rays = torch.nonzero(counts)[:, 0]
    last = first.index_select(0, rays) + counts.index_select(0, rays) - 1
    last_start = near.index_select(0, rays) + step * (counts.index_select(0, rays) - 1).to(near.dtype)
    last_delta = (far.index_select(0, rays) - last_start).clamp_(min=0.0)
    delta.index_copy_(0, last, last_delta)
    t.index_copy_(0, last, last_start + last_delta * jitter.index_select(0, rays))
    return ray_idx, t, delta


def early_termination_keep(tau: torch.Tensor, ray_idx: torch.Tensor, n_rays: int, eps: float) -> torch.Tensor:
    """(M,) bool: the samples whose transmittance in front, ``T_i``, is at least ``eps``.

    Args:
        tau: (M,) optical depths of packed samples; ray_idx: (M,) their rays; n_rays: number of rays.
        eps: transmittance below which a ray counts as terminated (0: keep everything).
    """
    return packed_transmittance(tau, ray_idx, n_rays) >= eps


def nearest_from_coords(x: torch.Tensor, size: tuple[int, int, int]) -> torch.Tensor:
    """(N,) flat index of the grid corner nearest each corner coordinate (3, N) (clamped to the grid)."""
    top = torch.tensor([s - 1 for s in size], dtype=x.dtype, device=x.device)[:, None]
    ijk = x.clamp(torch.zeros_like(top), top).round_().long()
    return (ijk[0] * size[1] + ijk[1]) * size[2] + ijk[2]


def grid_points(aabb: torch.Tensor, size: tuple[int, int, int]) -> torch.Tensor:
    """(X, Y, Z, 3) world positions of the corners of a ``size`` grid spanning ``aabb`` (2, 3)."""
    axes = [torch.linspace(float(aabb[0, a]), float(aabb[1, a]), size[a], dtype=aabb.dtype, device=aabb.device) for a in range(3)]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), -1)


class OccupancyGrid(nn.Module):
    """Occupancy-grid estimator: packed ray marching with empty-space skipping and early termination.

    The grid is a boolean per corner of a ``(X, Y, Z)`` lattice spanning ``aabb`` (corner ``(i, j,
    k)`` at ``aabb[0] + (i, j, k) * (aabb[1] - aabb[0]) / (size - 1)``); a sample is kept when its
    nearest corner is marked occupied. A ``(1, 1, 1)`` grid holding True means "no grid": nothing is
    skipped and nothing is looked up.

    Buffers: ``binaries`` (X, Y, Z) bool, ``aabb`` (2, 3) the marched box.
    """

    def __init__(self, aabb: torch.Tensor, binaries: torch.Tensor | None = None):
        super().__init__()
        self.register_buffer("aabb", aabb.detach().clone().float())
        if binaries is None:
            binaries = torch.ones(1, 1, 1, dtype=torch.bool, device=aabb.device)
        self.register_buffer("binaries", binaries)

    @property
    def size(self) -> tuple[int, int, int]:
        return tuple(self.binaries.shape)  # type: ignore[return-value]

    @property
    def skips(self) -> bool:
        """Whether the grid can skip anything (False for the "no grid" (1, 1, 1) placeholder)."""
        return self.binaries.numel() > 1

    def occupied_fraction(self) -> float:
        return float(self.binaries.float().mean())

    def sampling(
        self,
        origins: torch.Tensor,
        directions: torch.Tensor,
        near: torch.Tensor,
        far: torch.Tensor,
        *,
        step: float,
        jitter: torch.Tensor,
        skip_empty: bool = True,
        sigma_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
        early_stop_eps: float = 0.0,
        alpha_thre: float = 0.0,
    ) -> PackedSamples:
        """March the rays through ``aabb`` every ``step``, keeping only samples that can matter.

        Args:
            origins, directions: (n_rays, 3).
            near, far: (n_rays,) the rays' intervals (clipped to ``aabb`` here).
            step: distance between samples (world units).
            jitter: (n_rays,) in [0, 1): where each sample sits in its bin (0.5: midpoints).
            skip_empty: drop samples in empty cells (False: march the whole box).
            sigma_fn: ``sigma_fn(points (K, 3), samples) -> (K,)`` density per world unit, evaluated
                without gradient; needed for ``early_stop_eps`` and ``alpha_thre``.
            early_stop_eps: drop samples whose transmittance in front is below this (0: off).
            alpha_thre: drop samples whose alpha is below this (0: off).

        Returns:
            The kept samples; ``far`` is the clipped far of every ray.
        """
        near, far, _ = clip_to_aabb(origins, directions, near, far, self.aabb.to(origins.dtype))
        ray_idx, t, delta = march_packed(near, far, step, jitter)
        samples = PackedSamples(ray_idx, t, delta, far)
        if skip_empty and self.skips and len(samples):
            samples = samples.select(torch.nonzero(self.lookup(samples, origins, directions))[:, 0])
        if sigma_fn is not None and (early_stop_eps > 0.0 or alpha_thre > 0.0) and len(samples):
            with torch.no_grad():
                tau = sigma_fn(samples.points(origins, directions), samples) * samples.delta
                keep = torch.ones_like(tau, dtype=torch.bool)
                if alpha_thre > 0.0:
                    keep &= alpha_from_tau(tau) >= alpha_thre
                    tau = torch.where(keep, tau, torch.zeros_like(tau))
                if early_stop_eps > 0.0:
                    keep &= early_termination_keep(tau, samples.ray_idx, origins.shape[0], early_stop_eps)
            samples = samples.select(torch.nonzero(keep)[:, 0])
        return samples

    def lookup(self, samples: PackedSamples, origins: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
        """(M,) bool: the grid's mark at the corner nearest each sample."""
        dtype = origins.dtype
        lo = self.aabb[0].to(dtype)
        to_grid = torch.tensor([s - 1 for s in self.size], dtype=dtype, device=origins.device) / (self.aabb[1].to(dtype) - lo)
        x = torch.addcmul(((origins - lo) * to_grid).t().contiguous().index_select(1, samples.ray_idx), samples.t[None],
                          (directions * to_grid).t().contiguous().index_select(1, samples.ray_idx))
        return self.binaries.view(-1)[nearest_from_coords(x, self.size)]

    @torch.no_grad()
    def occupied_by(self, alpha_fn: Callable[[torch.Tensor], torch.Tensor], size: tuple[int, int, int], threshold: float,
                    dilation: int, chunk: int = 1 << 18) -> torch.Tensor:
        """(X, Y, Z) bool: corners of a ``size`` grid over ``aabb`` where ``alpha_fn`` exceeds ``threshold``, dilated.

        Args:
            alpha_fn: ``alpha_fn(points (K, 3)) -> (K,)`` alpha of one marching step at world points.
            size: the grid's corners per axis.
            threshold: alpha above which a corner is occupied.
            dilation: voxels the occupied set grows by (a cube of side ``2 * dilation + 1``).
        """
        pts = grid_points(self.aabb, size).reshape(-1, 3)
        alpha = torch.cat([alpha_fn(p) for p in pts.split(chunk)]) if len(pts) else pts.new_zeros(0)
        return dilate(alpha.view(size) > threshold, dilation)

    @torch.no_grad()
    def prune(self, alpha_fn: Callable[[torch.Tensor], torch.Tensor], threshold: float, dilation: int = 1) -> None:
        """Unmark the corners whose alpha fell to ``threshold`` or below (dilated); marks never come back.

        An update that would leave nothing marked is refused: an all-empty grid could never learn anything back.
        """
        if not self.skips:
            return
        pruned = self.binaries & self.occupied_by(alpha_fn, self.size, threshold, dilation)
        if bool(pruned.any()):
            self.binaries = pruned

    @torch.no_grad()
    def refresh(self, alpha_fn: Callable[[torch.Tensor], torch.Tensor], size: tuple[int, int, int], threshold: float,
                dilation: int = 1) -> None:
        """Mark exactly the corners whose alpha exceeds ``threshold`` (dilated): marks follow the field both ways.

        An update that would leave nothing marked keeps every corner marked instead.
        """
        occupied = self.occupied_by(alpha_fn, size, threshold, dilation)
        self.binaries = occupied if bool(occupied.any()) else torch.ones_like(occupied)


def dilate(mask: torch.Tensor, radius: int) -> torch.Tensor:
    """Grow a (X, Y, Z) boolean mask by ``radius`` voxels along each axis (a cube, by max pooling)."""
    if radius <= 0:
        return mask.clone()
    k = 2 * radius + 1
    return torch.nn.functional.max_pool3d(mask[None, None].float(), k, stride=1, padding=radius)[0, 0] > 0
