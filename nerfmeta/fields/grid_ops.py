"""Dense voxel-grid operations (pure functions).

Grids are stored like DirectVoxGO's: channels-first ``(C, X, Y, Z)``, a value per voxel corner
over an axis-aligned box ``bounds`` (2, 3), corner ``(i, j, k)`` at
``bounds[0] + (i, j, k) * (bounds[1] - bounds[0]) / (size - 1)``. Whole-grid work (resampling,
the alpha of every voxel) uses ``grid_sample``/``interpolate`` (:func:`interp_cf`,
:func:`resample_cf`; :func:`project_cf` moves a grid onto another lattice with the least mean-square change); the
training path uses :func:`corner_indices_weights` and :func:`trilinear_gather` on the flat view
``grid.view(C, -1)`` (flattened in ``(x, y, z)`` order).

Per-point data on the training path is *component-major*: coordinates (3, N), corner indices and
weights (8, N), values (C, N), so every elementwise step runs over long contiguous rows.
:func:`trilinear_gather` is a custom autograd function: one flat gather per channel forward, and
plain ``index_add_`` scatters of the weighted output gradients backward, one per channel.
PyTorch's own backwards for this (``embedding_bag``'s sorts its indices, ``grid_sample``'s also
computes the gradient of the sample positions, a row scatter into a channels-last grid misses
the cache on every row) cost two to four times more on a CPU. The corner indices and weights are
computed once per point and shared by every grid of the same size. Points outside the box are
clamped to its faces.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager

import torch
import torch.nn.functional as F

from nerfmeta.render.estimators import dilate, grid_points, nearest_from_coords

__all__ = [
    "channels_last",
    "corner_indices_weights",
    "corners_from_coords",
    "dilate",
    "grid_coords",
    "grid_points",
    "hat_projection",
    "interp_cf",
    "interp_coords",
    "interp_gather",
    "nearest_from_coords",
    "nearest_index",
    "nearest_lookup",
    "project_cf",
    "resample_cf",
    "take_columns",
    "to_unit",
    "total_variation",
    "total_variation_grad",
    "trilinear_gather",
    "voxel_layout",
]


def voxel_layout(bounds: torch.Tensor, num_voxels: int) -> tuple[tuple[int, int, int], float]:
    """Grid size per axis and voxel side for about ``num_voxels`` cubic voxels in ``bounds`` (2, 3).

    As in DirectVoxGO: ``voxel = (volume / num_voxels) ** (1/3)``, ``size = extent / voxel``.
    """
    extent = (bounds[1] - bounds[0]).double()
    voxel = float((extent.prod() / num_voxels) ** (1.0 / 3.0))
    size = tuple(max(2, int(math.floor(e / voxel)) + 1) for e in extent.tolist())
    return size, voxel  # type: ignore[return-value]


def to_unit(points: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
    """(N, 3) points to [0, 1]^3 box coordinates (not clamped)."""
    return (points - bounds[0]) / (bounds[1] - bounds[0])


def interp_cf(grid: torch.Tensor, points: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
    """Trilinear interpolation of a channels-first grid (``grid_sample``; for whole-grid work).

    Args:
        grid: (C, X, Y, Z).
        points: (N, 3) world points.
        bounds: (2, 3) the grid's box.

    Returns:
        (N, C).
    """
    return _sample_unit(grid, to_unit(points, bounds) * 2.0 - 1.0).t()


def _sample_unit(grid: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """(C, N) trilinear values of a (C, X, Y, Z) grid at (N, 3) ``(x, y, z)`` positions in [-1, 1] (corners at
    +-1, outside clamped to the faces): one ``grid_sample``, which wants ``(z, y, x)``."""
    out = F.grid_sample(grid.unsqueeze(0), u.flip(-1).reshape(1, 1, 1, -1, 3), mode="bilinear", padding_mode="border",
                        align_corners=True)
    return out.view(grid.shape[0], -1)


def grid_coords(points: torch.Tensor, bounds: torch.Tensor, size: tuple[int, int, int]) -> torch.Tensor:
    """Continuous corner coordinates (3, N) of (N, 3) world points: corner ``(i, j, k)`` is at ``(i, j, k)``.

    Coordinates are component-major (one row per axis), the layout the functions below work in.
    """
    top = torch.tensor([s - 1 for s in size], dtype=points.dtype, device=points.device)
    lo = bounds[0].to(points.dtype)
    return ((points - lo) * (top / (bounds[1].to(points.dtype) - lo))).t()


_OFFSETS = [(dx, dy, dz) for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)]


def corners_from_coords(x: torch.Tensor, size: tuple[int, int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`corner_indices_weights` from corner coordinates (3, N) (see :func:`grid_coords`)."""
    top = torch.tensor([s - 1 for s in size], dtype=x.dtype, device=x.device)[:, None]
    x = x.detach().clamp(torch.zeros_like(top), top)
    i0 = torch.minimum(x.floor(), top - 1)
    f = x - i0
    n_corners = size[0] * size[1] * size[2]
    stride_dtype = torch.float64 if n_corners >= 1 << 24 else x.dtype  # integer-exact below 2**24 (2**53)
    strides = torch.tensor([size[1] * size[2], size[2], 1], dtype=stride_dtype, device=x.device)[:, None]
    base = (i0.to(stride_dtype) * strides).sum(0).long()
    offs = torch.tensor([(dx * size[1] + dy) * size[2] + dz for dx, dy, dz in _OFFSETS], device=x.device)
    g = torch.stack([1 - f, f], 1)  # (3, 2, N): weights of the lower and upper corner along each axis
    wxy = (g[0][:, None] * g[1][None]).reshape(4, -1)
    w = (wxy[:, None] * g[2][None]).reshape(8, -1)
    return base[None] + offs[:, None], w


def corner_indices_weights(
    points: torch.Tensor, bounds: torch.Tensor, size: tuple[int, int, int]
) -> tuple[torch.Tensor, torch.Tensor]:
    """The 8 voxel corners around each point and their trilinear weights, corner-major.

    Args:
        points: (N, 3) world points (clamped to the box).
        bounds: (2, 3) the grid's box.
        size: (X, Y, Z) corners per axis, each >= 2.

    Returns:
        indices (8, N) int64 into a flat ``(C, X*Y*Z)`` grid, corners in ``(dx, dy, dz)`` order
        ``000, 001, 010, 011, 100, ...``; weights (8, N) in the points' dtype, non-negative and
        summing to 1 over the corners. No gradient flows to ``points``.
    """
    return corners_from_coords(grid_coords(points.detach(), bounds, size), size)


class _TrilinearGather(torch.autograd.Function):
    """``out[c, n] = sum_k w[k, n] * grid[c, idx[k, n]]`` with ``index_add_`` backwards (grid only)."""

    @staticmethod
    def forward(ctx, grid: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        ctx.save_for_backward(idx, w)
        ctx.voxels = grid.shape[1]
        flat = idx.reshape(-1)
        return torch.stack([(row.index_select(0, flat).view(idx.shape) * w).sum(0) for row in grid])

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):  # type: ignore[override]
        idx, w = ctx.saved_tensors
        if not ctx.needs_input_grad[0]:
            return None, None, None
        # Differentiable ops only (the zeros take no gradient), so double backward works too.
        flat = idx.reshape(-1)
        grad = grad_out.new_zeros(grad_out.shape[0], ctx.voxels)
        for c in range(grad_out.shape[0]):  # one 1-D scatter per channel
            grad[c].index_add_(0, flat, (w * grad_out[c]).reshape(-1))
        return grad, None, None


def trilinear_gather(grid: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Weighted sums of grid values: trilinear interpolation from :func:`corner_indices_weights`.

    Args:
        grid: (C, V) flat channels-first grid (differentiable), e.g. ``g.view(C, -1)`` of a (C, X, Y, Z) ``g``.
        idx: (8, N) int64 corner indices, corner-major.
        w: (8, N) weights, same dtype as ``grid`` (no gradient flows to them).

    Returns:
        (C, N) ``sum_k w[k] * grid[:, idx[k]]``.
    """
    return _TrilinearGather.apply(grid, idx, w.detach())


def interp_gather(grid: torch.Tensor, points: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
    """Trilinear interpolation of a (C, X, Y, Z) grid with :func:`trilinear_gather` (the values of :func:`interp_cf`).

    Args:
        grid: (C, X, Y, Z); points: (N, 3) world points; bounds: (2, 3).

    Returns:
        (N, C).
    """
    size = tuple(grid.shape[1:])
    idx, w = corner_indices_weights(points, bounds, size)  # type: ignore[arg-type]
    return trilinear_gather(grid.reshape(grid.shape[0], -1), idx, w.to(grid.dtype)).t()


def interp_coords(grid: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Trilinear interpolation of a (C, X, Y, Z) grid at corner coordinates (3, N) (see :func:`grid_coords`).

    One fused ``grid_sample`` (points outside the grid clamped to its faces, as in
    :func:`corners_from_coords`), for test-time renders: it has no cheap backward, but forward it
    is two to three times faster on a CPU than :func:`corners_from_coords` plus
    :func:`trilinear_gather`, the more so when ``grid`` is in ``torch.channels_last_3d`` memory
    (one read of all channels per corner). Values equal :func:`trilinear_gather`'s to float rounding.

    Returns:
        (C, N).
    """
    scale = torch.tensor([2.0 / (s - 1) for s in grid.shape[1:]], dtype=x.dtype, device=x.device)[:, None]
    return _sample_unit(grid, (x * scale - 1.0).t())


def channels_last(grid: torch.Tensor) -> torch.Tensor:
    """A (C, X, Y, Z) copy of ``grid`` (no gradient) stored channels-last: one read per corner in :func:`interp_coords`."""
    return grid.detach().unsqueeze(0).contiguous(memory_format=torch.channels_last_3d)[0]


class ChannelsLastCopies:
    """Channels-last copies of a module's grids, kept only while a whole-view render runs (:meth:`kept`).

    A test-time render split into many chunks then copies each grid once, not once per chunk; outside
    :meth:`kept` nothing is kept, so a copy can never outlive a change of its grid (optimiser steps,
    fused ones included, and ``.data`` assignments leave no trace a cache could check). A deep copy or a
    pickle of the owner starts empty.
    """

    def __init__(self) -> None:
        self._copies: dict[str, torch.Tensor] = {}
        self._depth = 0

    @contextmanager
    def kept(self) -> Iterator[None]:
        """Keep the copies made inside the block (nested blocks share them); drop them all at its end."""
        self._depth += 1
        try:
            yield
        finally:
            self._depth -= 1
            if self._depth == 0:
                self._copies.clear()

    @property
    def keeping(self) -> bool:
        """Inside :meth:`kept`."""
        return self._depth > 0

    def get(self, name: str, grid: torch.Tensor) -> torch.Tensor:
        """A channels-last copy of the (C, X, Y, Z) ``grid``: the one kept as ``name`` inside :meth:`kept`."""
        if not self._depth:
            return channels_last(grid)
        copy = self._copies.get(name)
        if copy is None:  # two render threads may both make it: the same values either way
            copy = self._copies[name] = channels_last(grid)
        return copy

    def __deepcopy__(self, memo: dict) -> "ChannelsLastCopies":
        return ChannelsLastCopies()

    def __getstate__(self) -> dict:
        return {"_copies": {}, "_depth": 0}


def take_columns(a: torch.Tensor, cols: torch.Tensor) -> torch.Tensor:
    """``a[:, cols]`` for a component-major (K, N) tensor: row by row, which a CPU does several
    times faster than one ``index_select`` along dimension 1 (int64 above all)."""
    return torch.stack([row.index_select(0, cols) for row in a]) if a.shape[0] else a[:, cols]


def nearest_index(points: torch.Tensor, bounds: torch.Tensor, size: tuple[int, int, int]) -> torch.Tensor:
    """(N,) flat index of the voxel corner nearest each (N, 3) point (points clamped to the box)."""
    return nearest_from_coords(grid_coords(points, bounds, size), size)


def nearest_lookup(mask: torch.Tensor, points: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
    """Value of a (X, Y, Z) grid at the voxel corner nearest each (N, 3) point; False/0 outside the box."""
    u = to_unit(points, bounds)
    inside = ((u >= 0) & (u <= 1)).all(-1)
    idx = nearest_index(points, bounds, tuple(mask.shape))  # type: ignore[arg-type]
    return mask.reshape(-1)[idx] & inside


def resample_cf(grid: torch.Tensor, size: tuple[int, int, int]) -> torch.Tensor:
    """Trilinearly resample a (C, X, Y, Z) grid to ``size`` corners (same box)."""
    return F.interpolate(grid.unsqueeze(0), size=size, mode="trilinear", align_corners=True).squeeze(0)


def _hats(n: int, t: torch.Tensor) -> torch.Tensor:
    """(T, n) values at ``t`` in [0, 1] of the ``n`` piecewise-linear hat functions with corners ``i / (n - 1)``."""
    return (1.0 - (t[:, None] * (n - 1) - torch.arange(n, dtype=t.dtype, device=t.device)).abs()).clamp_min(0.0)


def hat_projection(n_from: int, n_to: int) -> torch.Tensor:
    """(n_to, n_from) float64 matrix of the L2 projection of 1-D piecewise-linear functions on ``n_from`` evenly spaced
    corners of [0, 1] onto those on ``n_to`` corners: ``M^-1 B``, with ``M`` the target hats' Gram matrix and ``B`` their
    inner products with the source hats. Both are integrated exactly: between consecutive corners of either lattice
    the products are quadratics, which two-point Gauss-Legendre quadrature integrates without error."""
    if n_from < 2 or n_to < 2:
        raise ValueError(f"hat_projection: lattices need at least 2 corners, got {n_from} and {n_to}")
    dt = torch.float64
    breaks = torch.unique(torch.cat([torch.linspace(0, 1, n_from, dtype=dt), torch.linspace(0, 1, n_to, dtype=dt)]))
    mid, half = (breaks[1:] + breaks[:-1]) / 2, (breaks[1:] - breaks[:-1]) / 2
    g = half / math.sqrt(3.0)
    t, w = torch.cat([mid - g, mid + g]), torch.cat([half, half])
    to, frm = _hats(n_to, t), _hats(n_from, t)
    return torch.linalg.solve(to.t() @ (w[:, None] * to), to.t() @ (w[:, None] * frm))


def project_cf(grid: torch.Tensor, size: tuple[int, int, int]) -> torch.Tensor:
    """The (C, X, Y, Z) grid's trilinear field L2-projected onto ``size`` corners (same box): of the fields the new
    lattice can hold, the nearest in the mean square over the box. The trilinear basis is a tensor product, so the
    projection is three 1-D ones (:func:`hat_projection`), one matrix product per axis. Unlike :func:`resample_cf`
    (which keeps the values at the new corners and smooths between them when the lattices are not nested) it keeps
    the field's mean over the box; a field the new lattice can hold (an affine one, or the same lattice) comes back
    unchanged. It rings a little beside a sharp step (the projection's weights decay by about 0.27 a corner), so use
    it for a post-activated density, not for values with hard limits."""
    out = grid
    for axis, n in enumerate(size):
        p = hat_projection(grid.shape[axis + 1], n).to(grid.device, grid.dtype)
        out = torch.tensordot(p, out.movedim(axis + 1, 0), dims=1).movedim(0, axis + 1)
    return out.contiguous()


def total_variation(grid: torch.Tensor) -> torch.Tensor:
    """Mean squared difference between neighbouring voxels of a (C, X, Y, Z) grid (a scalar): the mean over each
    axis's neighbour pairs, averaged over the three axes. Its gradient is written out (:func:`total_variation_grad`):
    value and gradient of a 100 x 100 x 110 grid take 4.2 ms on one idle CPU thread, against 12.5-13.3 ms through
    autograd's backward of the differences; the gradient is itself differentiable, for second-order meta-learning."""
    return _TotalVariation.apply(grid)


def total_variation_grad(grid: torch.Tensor) -> torch.Tensor:
    """The gradient of :func:`total_variation` with respect to ``grid``: per axis, ``2 / (3 n)`` times the
    difference to the previous neighbour minus the difference to the next (``n`` the axis's neighbour pairs). In
    place on one buffer when no graph is being built; from differentiable operations when one is."""
    if torch.is_grad_enabled() and grid.requires_grad:
        out = torch.zeros_like(grid)
        for axis in (1, 2, 3):
            d = grid.diff(dim=axis)
            edge = grid.new_zeros(()).expand(*(1 if i == axis else s for i, s in enumerate(grid.shape)))
            out = out + (torch.cat([edge, d], axis) - torch.cat([d, edge], axis)) * (2.0 / (3.0 * d.numel()))
        return out
    out = torch.zeros_like(grid)
    for axis in (1, 2, 3):
        d, n = grid.diff(dim=axis), grid.shape[axis]
        scale = 2.0 / (3.0 * d.numel())
        out.narrow(axis, 1, n - 1).add_(d, alpha=scale)
        out.narrow(axis, 0, n - 1).sub_(d, alpha=scale)
    return out


class _TotalVariation(torch.autograd.Function):
    @staticmethod
    def forward(ctx, grid: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(grid)
        return sum(grid.diff(dim=axis).square().mean() for axis in (1, 2, 3)) / 3.0

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor) -> torch.Tensor:
        (grid,) = ctx.saved_tensors
        return grad_out * total_variation_grad(grid)
