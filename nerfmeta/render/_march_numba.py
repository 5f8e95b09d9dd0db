"""numba kernel of the occupancy grid's march with its empty-space skip, through a contracted space
(:func:`nerfmeta.render.estimators.contracted_march`) and through a box (:func:`~nerfmeta.render.estimators.march_packed`)
(imported only when numba is installed).

PyTorch's march of a contracted space is a chain of whole-array passes over every sample (the marching distances,
two edges and the sample mapped back to world distances, three contractions, the edge lengths, then the occupancy
lookup's contraction, nearest corner and gather, and a selection): about 17 ms for the 430k samples of a beer
training step on the 2-core CPU. Here each ray's samples are made one after another in registers, each bin's far
edge contracted once and reused as the next bin's near edge, and only the kept samples are written. A box's march is
the same kernel without the contraction. It runs on one thread over a range of rays and releases the GIL.
"""

from __future__ import annotations

import math

import numba
import numpy


@numba.njit(cache=True, nogil=True, inline="always")
def from_march(m: float, t1: float, scale: float, tiny: float) -> float:
    """:func:`nerfmeta.render.contraction.from_march` of one marching distance."""
    if m > t1:
        return t1 - scale + scale * scale / max(t1 + scale - m, tiny)
    return m


@numba.njit(cache=True, nogil=True, inline="always")
def contract(px: float, py: float, pz: float, cx: float, cy: float, cz: float, radius: float, shell: float):
    """:meth:`nerfmeta.render.contraction.InnerBox.contract` of one world point (NaN coordinates: not scaled)."""
    a, b, c = (px - cx) / radius, (py - cy) / radius, (pz - cz) / radius
    m = max(abs(a), abs(b), abs(c))
    if m > 1.0 and a == a and b == b and c == c:
        s = (1.0 + shell - shell / m) / m
        a, b, c = a * s, b * s, c * s
    return a, b, c


@numba.njit(cache=True, nogil=True, inline="always")
def nearest(v: float, top: int) -> int:
    """Index of the corner nearest corner coordinate ``v`` on ``0 .. top``: clamped, halves to even (as
    ``torch.round``), NaN to 0."""
    if not v > 0.0:
        return 0
    if v > top:
        return top
    return int(numpy.rint(v))  # one rounding instruction (a floor-and-compare version took 2.5x the whole march)


@numba.njit(cache=True, nogil=True)
def march(counts, window, starts, origins, directions, near, far, t1, jitter, step: float, first: int,
          scale: float, tiny: float, centre, radius: float, shell: float, occupied, lo, to_grid,
          ray_idx, t, delta, r0: int, r1: int) -> int:  # pragma: no cover - compiled
    """The samples ``first .. first + window[r] - 1`` of the rays ``r0 <= r < r1``, those whose nearest corner of
    ``occupied`` (X, Y, Z) bool is set (all when it has one corner), written to ``ray_idx``, ``t``, ``delta`` from
    ``starts[r0]`` on, packed; returns how many (``starts`` (n_rays + 1,): where each ray's window would start if every
    sample were kept, then the total).

    Per ray: ``[near, far]`` its marching interval, ``counts`` its whole march's sample count, ``jitter`` where its
    samples sit in their bins, as :func:`~nerfmeta.render.estimators.march_packed` makes them (the last bin ends at
    ``far``); ``lo`` (3,) and ``to_grid`` (3,) map a sample's position to corner coordinates of ``occupied``.

    Through a contracted space (``radius > 0``; :func:`~nerfmeta.render.estimators.contracted_march`): the interval
    is in marching distance, ``t1`` each ray's inner-box exit and ``scale`` the shell's marching length; a sample's
    ``t`` is its world distance, its ``delta`` its bin's length in the contracted space and its position for the
    occupancy its contracted one (inner box of ``centre`` (3,), ``radius``, ``shell``). Through a box (``radius``
    0; ``t1``, ``scale``, ``centre`` and ``shell`` unused): ``t`` and ``delta`` are world distance and bin length.
    """
    cx, cy, cz = centre[0], centre[1], centre[2]
    contracted = radius > 0.0
    sx, sy, sz = occupied.shape
    skip = sx * sy * sz > 1
    q = starts[r0]
    for r in range(r0, r1):
        n = window[r]
        if n <= 0:
            continue
        ox, oy, oz = origins[r, 0], origins[r, 1], origins[r, 2]
        dx, dy, dz = directions[r, 0], directions[r, 1], directions[r, 2]
        start, j = near[r], jitter[r]
        exit_, ax, ay, az = 0.0, 0.0, 0.0, 0.0
        if contracted:  # the near edge of the window's first bin
            exit_ = t1[r]
            e = from_march(start + step * first, exit_, scale, tiny)
            ax, ay, az = contract(ox + e * dx, oy + e * dy, oz + e * dz, cx, cy, cz, radius, shell)
        for k in range(first, first + n):
            s0 = start + step * k
            dm = step if k < counts[r] - 1 else max(far[r] - s0, 0.0)
            if contracted:
                # the far edge as the next bin's near edge is computed, so a window's first edge is the same number
                e = from_march(start + step * (k + 1) if k < counts[r] - 1 else s0 + dm, exit_, scale, tiny)
                bx, by, bz = contract(ox + e * dx, oy + e * dy, oz + e * dz, cx, cy, cz, radius, shell)
                d = math.sqrt((bx - ax) ** 2 + (by - ay) ** 2 + (bz - az) ** 2)
                ax, ay, az = bx, by, bz
                ts = from_march(s0 + dm * j, exit_, scale, tiny)
            else:
                d, ts = dm, s0 + dm * j
            keep = True
            if skip:
                px, py, pz = ox + ts * dx, oy + ts * dy, oz + ts * dz
                if contracted:
                    px, py, pz = contract(px, py, pz, cx, cy, cz, radius, shell)
                keep = occupied[nearest((px - lo[0]) * to_grid[0], sx - 1), nearest((py - lo[1]) * to_grid[1], sy - 1),
                                nearest((pz - lo[2]) * to_grid[2], sz - 1)]
            if keep:
                ray_idx[q], t[q], delta[q] = r, ts, d
                q += 1
    return q - starts[r0]
