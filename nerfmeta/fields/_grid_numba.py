"""numba kernels of :mod:`nerfmeta.fields.grid_kernels` (imported only when numba is installed).

Grids are channels-first ``(C, X, Y, Z)`` and points are corner coordinates ``(3, N)``, as in
:mod:`nerfmeta.fields.grid_ops`; a coordinate is clamped to ``[0, size - 1]`` (NaN to 0, so no
index ever leaves the grid: numba does not check bounds) and its lower corner to ``size - 2``.
Each call runs on one thread and releases the GIL; a lookup splits its points, and a scatter its
corner planes, over concurrent calls (:mod:`~nerfmeta.fields.grid_kernels`).

The lookups visit the points in a given ``order`` (:func:`block_order`; an empty one: as they are) and read
their coordinates already in that order, so points of a large grid can be visited block by block of the grid
rather than ray by ray; values and gradients still go to each point's own column.
"""

from __future__ import annotations

import numba
import numpy


@numba.njit(cache=True, nogil=True)
def corner(v: float, top: int) -> tuple[int, float]:
    """Lower corner index along one axis of ``top + 1`` corners, and the upper corner's weight."""
    if not v > 0.0:  # NaN too
        v = 0.0
    if v > top:
        v = float(top)
    i = min(int(v), top - 1)
    return i, v - i


@numba.njit(cache=True, nogil=True)
def cell(x, p: int, sx: int, sy: int, sz: int) -> tuple[int, int, int, float, float, float]:
    """Lower corner (i, j, k) of point ``p`` of ``x`` (3, N) in a grid of sx x sy x sz corners, and the upper corners' weights."""
    i, ax = corner(x[0, p], sx - 1)
    j, ay = corner(x[1, p], sy - 1)
    k, az = corner(x[2, p], sz - 1)
    return i, j, k, ax, ay, az


@numba.njit(cache=True, nogil=True)
def block_order(x, sx: int, sy: int, sz: int, shift: int):  # pragma: no cover - compiled
    """The points of ``x`` (3, N) ordered by the block of ``2**shift`` cells a side their lower corner lies in, blocks in
    the grid's memory order (x, then y, then z) and points within a block as given (a stable counting sort):
    ``(order, x[:, order])``, order int64 (N,)."""
    n = x.shape[1]
    by, bz = ((sy - 2) >> shift) + 1, ((sz - 2) >> shift) + 1
    key = numpy.empty(n, numpy.int64)
    start = numpy.zeros((((sx - 2) >> shift) + 1) * by * bz + 1, numpy.int64)
    for p in range(n):
        i, j, k, _, _, _ = cell(x, p, sx, sy, sz)
        key[p] = ((i >> shift) * by + (j >> shift)) * bz + (k >> shift)
        start[key[p] + 1] += 1
    for b in range(1, start.shape[0]):
        start[b] += start[b - 1]
    order, ordered = numpy.empty(n, numpy.int64), numpy.empty_like(x)
    for p in range(n):
        q = start[key[p]]
        start[key[p]] = q + 1
        order[q] = p
        for a in range(3):
            ordered[a, q] = x[a, p]
    return order, ordered


@numba.njit(cache=True, nogil=True)
def gather(grid, x, out, order, lo: int, hi: int):  # pragma: no cover - compiled
    """``out[c, order[q]]`` = trilinear value of ``grid[c]`` (C, X, Y, Z) at ``x[:, q]`` (3, N) for ``lo <= q < hi``;
    out (C, N). An empty ``order`` stands for ``order[q] = q``."""
    n_channels, sx, sy, sz = grid.shape
    identity = order.shape[0] == 0
    for q in range(lo, hi):
        p = q if identity else order[q]
        i, j, k, ax, ay, az = cell(x, q, sx, sy, sz)
        bx, by, bz = 1.0 - ax, 1.0 - ay, 1.0 - az
        for c in range(n_channels):
            g = grid[c]
            v0 = (g[i, j, k] * bz + g[i, j, k + 1] * az) * by + (g[i, j + 1, k] * bz + g[i, j + 1, k + 1] * az) * ay
            v1 = (g[i + 1, j, k] * bz + g[i + 1, j, k + 1] * az) * by + (g[i + 1, j + 1, k] * bz + g[i + 1, j + 1, k + 1] * az) * ay
            out[c, p] = v0 * bx + v1 * ax


@numba.njit(cache=True, nogil=True)
def add_plane(g, i: int, j: int, k: int, w: float, ay: float, az: float) -> None:
    """Adds ``w`` to the 4 corners of plane ``i`` around ``(j, k)`` of ``g`` (X, Y, Z), bilinearly weighted."""
    w0, w1 = w * (1.0 - ay), w * ay
    g[i, j, k] += w0 * (1.0 - az)
    g[i, j, k + 1] += w0 * az
    g[i, j + 1, k] += w1 * (1.0 - az)
    g[i, j + 1, k + 1] += w1 * az


@numba.njit(cache=True, nogil=True)
def scatter(grad_out, x, grad, order, part: int, parts: int):  # pragma: no cover - compiled
    """Adds each ``grad_out[c, order[q]]`` (C, N) to the 8 corners around ``x[:, q]`` in ``grad`` (C, X, Y, Z),
    trilinearly weighted, writing only the corner planes ``i`` with ``i % parts == part`` (empty ``order``: ``q``).

    ``parts`` calls with ``part = 0 .. parts - 1`` may run at once: no two write the same value, and each adds to a
    value in the points' order, so the sums are those of one call with ``parts = 1``, bit for bit.
    """
    n_channels, sx, sy, sz = grad.shape
    identity = order.shape[0] == 0
    for q in range(x.shape[1]):
        i, j, k, ax, ay, az = cell(x, q, sx, sy, sz)
        lower, upper = i % parts == part, (i + 1) % parts == part
        if not (lower or upper):
            continue
        p = q if identity else order[q]
        for c in range(n_channels):
            go = grad_out[c, p]
            if lower:
                add_plane(grad[c], i, j, k, go * (1.0 - ax), ay, az)
            if upper:
                add_plane(grad[c], i + 1, j, k, go * ax, ay, az)
