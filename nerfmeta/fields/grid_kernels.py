"""Fused trilinear lookups for training on a CPU (numba), with PyTorch's gather path as the fallback.

A training lookup of a dense grid at N points is, in PyTorch, a chain of whole-array passes: the
corner indices and weights (8, N) each, one ``index_select`` per channel, a weighted sum, and
backward one ``index_add_`` per channel (:func:`~nerfmeta.fields.grid_ops.trilinear_gather`).
Each pass streams 8N values through memory. The kernels here do the same arithmetic point by
point in compiled loops: a point's corners and weights are computed in registers, its C values
read from the 8 corners, and backward its output gradient scattered to the same 8 corners, so
nothing of size 8N is ever written. On the 2-core CPU a grid fit of a generated 128 px object makes
its 1000 steps in 0.79-0.85 of the time, and a 60-s lego fit 15 % more steps (BENCHMARKS.md, *Fused grid
lookups*).

A lookup is split over as many threads as torch may use (``torch.get_num_threads()``): its points in
contiguous ranges, and its gradient scatter by the corner planes each thread owns (plane ``i`` to thread
``i % threads``), so no two threads write the same value and every value is summed in the points' order,
bit for bit the one-thread result. The threads are Python threads running compiled loops that release
the GIL; no numba threading layer is started, so there is no second OpenMP runtime beside PyTorch's.
Lookups split only while PyTorch's own OpenMP workers spin briefly after their work
(:func:`nerfmeta.fused.short_openmp_wait`; importing :mod:`nerfmeta` before torch sets that up), else a spinning
worker holds the core the second thread needs. On the 2-core CPU the split gives a beer fit 1.26x the steps in 120 s and a lego fit 1.12x in
60 s (medians; BENCHMARKS.md, *Fused grid lookups*).

A lookup of a grid larger than the CPU's last-level cache (:data:`SORT_MIN_BYTES`) first orders its points by the
16-cell block of the grid they fall in (a counting sort, :func:`~nerfmeta.fields._grid_numba.block_order`), and
its gather and backward scatter visit them in that order: points arrive ray by ray, each ray crossing the grid,
so in ray order most corner reads miss the caches. On the 2-core CPU a beer fit's steps on its grown 160^3 grid
(a 49 MB colour grid) took 137 ms against 171 (medians of three 120-s fits; 955 steps against 862), and smaller
grids measured no faster, so they keep the ray order (BENCHMARKS.md, *Fused grid lookups*). The order changes only
which point is visited when: a gather is the same bit for bit, a scatter adds each value's terms in another order
(float rounding), the same on every run and for any number of threads. Lookups without a gradient (test renders,
videos) keep the ray order: a render chunk's rays are of neighbouring pixels, coherent already, and sorted the
full-size beer render ran at 93.5k rays/s against 103.8k.

A scatter's gradient of :data:`RECYCLE_MIN_BYTES` or more goes into a recycled buffer, zeroed in place, once no tensor
made from it is alive (:func:`_zeros`), rather than a fresh mapping whose pages fault in at every step.

The kernels are compiled on first use and cached on disk (numba's ``cache=True``): about 1.4 s once per machine, then
about 0.6 s a process to import numba and load them, which the backbones' ``warm_up`` spends before a
fit's clock starts (measured on the 2-core CPU).

numba is optional: without it (or for tensors on a GPU, or with ``NERFMETA_FUSED_LOOKUPS=0``)
:func:`trilinear_coords` uses the PyTorch path, whose values it matches (tests compare both with
a float64 reference).
"""

from __future__ import annotations

import sys
import threading
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy
import torch

from nerfmeta import fused
from nerfmeta.fields.grid_ops import corners_from_coords, grid_coords, trilinear_gather

__all__ = ["fused_available", "fused_for", "fused_lookups", "interp_points", "last_level_cache_bytes",
           "trilinear_coords"]


SPLIT_MIN_POINTS = 16384
"""Lookups of at least this many points are split over torch's threads (below, a thread hand-off costs more than it saves)."""


def last_level_cache_bytes(cpu_dir: Path = Path("/sys/devices/system/cpu/cpu0/cache")) -> int:
    """The size of the CPU's largest cache level (Linux's sysfs), or 32 MiB where it cannot be read."""
    sizes = {}
    for index in cpu_dir.glob("index*"):
        try:
            level, size = int((index / "level").read_text()), (index / "size").read_text().strip().upper()
            sizes[level] = int(size[:-1]) * {"K": 1 << 10, "M": 1 << 20}[size[-1]] if size[-1] in "KM" else int(size)
        except (OSError, ValueError):
            continue
    return sizes[max(sizes)] if sizes else 32 << 20


SORT_MIN_BYTES = last_level_cache_bytes()
"""Lookups of at least :data:`SPLIT_MIN_POINTS` points in a grid larger than this (the CPU's last-level cache, read
at import) visit their points block by block. On the 2-core CPU (32 MB L3), steps of a beer fit alternating the
two orders: with its 49 MB colour grid sorted 127 against 157 ms a step; sorting its 25 MB colour grid or its 16 MB
density grid as well was no faster (BENCHMARKS.md, *Fused grid lookups*)."""
SORT_BLOCK_SHIFT = 4
"""The blocks :data:`SORT_MIN_BYTES`'s sort orders points by are ``2**SORT_BLOCK_SHIFT`` cells a side (8 and 16 measured alike)."""
_NO_ORDER = numpy.empty(0, dtype=numpy.int64)


def _smoke(kernels: Any) -> None:
    """Runs the block sort, a gather and a scatter for float32 on a 2 x 2 x 2 grid (:func:`nerfmeta.fused.load`)."""
    grid, x = numpy.zeros((1, 2, 2, 2), numpy.float32), numpy.full((3, 1), 0.5, numpy.float32)
    out = numpy.empty((1, 1), numpy.float32)
    order, x = kernels.block_order(x, 2, 2, 2, SORT_BLOCK_SHIFT)
    kernels.gather(grid, x, out, order, 0, 1)
    kernels.scatter(out, x, grid, order, 0, 1)


def _kernels() -> Any:
    """The compiled kernels' module (:mod:`nerfmeta.fields._grid_numba`), or None without a working numba."""
    return fused.load("nerfmeta.fields._grid_numba", _smoke, "grid lookups")


def fused_available() -> bool:
    """True when the fused CPU kernels can be used (numba importable and not switched off)."""
    return fused.enabled() and _kernels() is not None


def fused_for(grid: torch.Tensor, x: torch.Tensor) -> bool:
    """True when :func:`trilinear_coords` looks ``grid`` up at ``x`` with the fused kernels: they are available, and
    both tensors are on the CPU in the same float32 or float64 dtype."""
    return fused.takes(grid, x) and grid.dtype == x.dtype and fused_available()


fused_lookups = fused.fused_kernels
"""Switch the fused kernels on or off inside a block (tests compare both paths; :func:`nerfmeta.fused.fused_kernels`)."""


def _parts(n_points: int) -> int:
    """How many concurrent calls a kernel over ``n_points`` is split into (:func:`nerfmeta.fused.parts` with
    :data:`SPLIT_MIN_POINTS`)."""
    return fused.parts(n_points, SPLIT_MIN_POINTS)


def _ordered(grid_shape: tuple[int, ...], itemsize: int, x: torch.Tensor, by_block: bool = True,
             ) -> tuple[numpy.ndarray, numpy.ndarray]:
    """The order a lookup of a ``grid_shape`` grid visits the points ``x`` (3, N) in, and their coordinates in that
    order: by block of the grid when ``by_block`` and the lookup is large (:data:`SORT_MIN_BYTES`), else as given
    (an empty order)."""
    xs = x.numpy()
    if not by_block or x.shape[1] < SPLIT_MIN_POINTS or numpy.prod(grid_shape) * itemsize <= SORT_MIN_BYTES:
        return _NO_ORDER, xs
    return _kernels().block_order(xs, *grid_shape[1:], SORT_BLOCK_SHIFT)


def _gather(grid: torch.Tensor, points: tuple[numpy.ndarray, numpy.ndarray]) -> torch.Tensor:
    order, xs = points
    grid = grid.detach().contiguous()
    n = xs.shape[1]
    out = grid.new_empty(grid.shape[0], n)
    g, o, parts = grid.numpy(), out.numpy(), _parts(n)
    fused.split(_kernels().gather, [(g, xs, o, order, n * q // parts, n * (q + 1) // parts) for q in range(parts)])
    return out


RECYCLE_MIN_BYTES = 32 << 20
"""Gradient buffers of at least this size are recycled (:func:`_zeros`): glibc maps each allocation above 32 MiB
afresh from the kernel and every page the scatter touches then faults in. On the 2-core CPU the scatter of beer's
grown colour grid (3 x 160^3, 49 MB) took 29.5 ms into a fresh buffer and 18.7 ms into a recycled one zeroed in
place; the 16 MB density grid 13.0 against 11.5 (below 32 MiB glibc reuses its heap). In a beer fit, alternating every
20 steps: 102.8 against 108.9 ms a step, and 107.3 against 114.7 in the other order (BENCHMARKS.md, *Fused
compositing*)."""
_SPARES: OrderedDict[tuple[tuple[int, ...], str], list[numpy.ndarray]] = OrderedDict()
_SPARE_KEYS = 4  # the shapes kept: a fit's density and colour grids, and the pair before the last growth
_SPARES_PER_SHAPE = 2  # more gradients of one shape alive at once (MAML's inner steps) get unpooled buffers
_SPARES_LOCK = threading.Lock()


def _refs(spares: list[numpy.ndarray], i: int) -> int:
    return sys.getrefcount(spares[i])


_FREE_REFS = _refs([numpy.empty(0)], 0)
"""What :func:`_refs` reads for an array only a list holds (asked the same way, so the interpreter's own count of the
call's references cancels out)."""


def _zeros(shape: tuple[int, ...], dtype: Any) -> numpy.ndarray:
    """A zeroed array; one of :data:`RECYCLE_MIN_BYTES` or more is a recycled buffer when one of this shape is free.

    A buffer is free once no tensor made from it is alive (``torch.from_numpy`` holds a reference to the array, so
    its reference count says so), and is zeroed in place before it is handed out again: a gradient still held (by
    a parameter's ``.grad``, a graph kept for a second derivative, a caller) is never reused. At most
    :data:`_SPARES_PER_SHAPE` buffers a shape are kept (more alive at once, as in MAML's inner steps, get buffers of
    their own), so the pool holds no more than a plain fit's gradients.
    """
    size = int(numpy.prod(shape)) * numpy.dtype(dtype).itemsize
    if size < RECYCLE_MIN_BYTES:
        return numpy.zeros(shape, dtype=dtype)  # from calloc: pages no point touches are never written
    key = (tuple(shape), numpy.dtype(dtype).str)
    with _SPARES_LOCK:
        spares = _SPARES.setdefault(key, [])
        _SPARES.move_to_end(key)
        while len(_SPARES) > _SPARE_KEYS:
            _SPARES.popitem(last=False)
        free = next((i for i in range(len(spares)) if _refs(spares, i) == _FREE_REFS), None)
        if free is None:
            if len(spares) >= _SPARES_PER_SHAPE:
                return numpy.zeros(shape, dtype=dtype)
            spares.append(numpy.zeros(shape, dtype=dtype))
            return spares[-1]
        spares[free].fill(0)
        return spares[free]


def _scatter(values: torch.Tensor, points: tuple[numpy.ndarray, numpy.ndarray], shape: tuple[int, ...]) -> torch.Tensor:
    order, xs = points
    v, parts = values.detach().contiguous().numpy(), _parts(xs.shape[1])
    grad = _zeros(shape, v.dtype)
    fused.split(_kernels().scatter, [(v, xs, grad, order, q, parts) for q in range(parts)])
    return torch.from_numpy(grad)


class _TrilinearCoords(torch.autograd.Function):
    """``out[c, n]`` = trilinear value of ``grid[c]`` at corner coordinates ``x[:, n]``; gradient to the grid only."""

    @staticmethod
    def forward(ctx, grid: torch.Tensor, x: torch.Tensor, by_block: bool) -> torch.Tensor:  # type: ignore[override]
        ctx.save_for_backward(x)
        ctx.grid_shape = tuple(grid.shape)
        ctx.points = _ordered(ctx.grid_shape, grid.element_size(), x, by_block)  # the backward's scatter visits them alike
        return _gather(grid, ctx.points)

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):  # type: ignore[override]
        (x,) = ctx.saved_tensors
        if not ctx.needs_input_grad[0]:
            return None, None, None
        return _ScatterCoords.apply(grad_out, x, ctx.grid_shape, ctx.points), None, None


class _ScatterCoords(torch.autograd.Function):
    """The lookup's adjoint, ``grid[c, corners of n] += w * values[c, n]``; its own backward is the lookup, so second
    derivatives (MAML) pass through."""

    @staticmethod
    def forward(ctx, values: torch.Tensor, x: torch.Tensor, shape: tuple[int, ...],  # type: ignore[override]
                points: tuple[numpy.ndarray, numpy.ndarray]) -> torch.Tensor:
        ctx.save_for_backward(x)
        return _scatter(values, points, shape)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        (x,) = ctx.saved_tensors
        return _TrilinearCoords.apply(grad, x, True), None, None, None


def trilinear_coords(grid: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Trilinear interpolation of a (C, X, Y, Z) grid at corner coordinates, differentiable in the grid.

    Args:
        grid: (C, X, Y, Z), each side >= 2, float32 or float64.
        x: (3, N) corner coordinates (:func:`~nerfmeta.fields.grid_ops.grid_coords`), the grid's dtype;
            clamped to the grid's faces. No gradient flows to them.

    Returns:
        (C, N): the values of :func:`~nerfmeta.fields.grid_ops.trilinear_gather` with
        :func:`~nerfmeta.fields.grid_ops.corners_from_coords`, from the fused kernels when :func:`fused_for`
        says so, else from those.
    """
    x = x.detach()
    if fused_for(grid, x):
        # by block only where a gradient is taken: a render's chunk is rays of neighbouring pixels, coherent already
        return _TrilinearCoords.apply(grid, x.contiguous(), torch.is_grad_enabled() and grid.requires_grad)
    size = tuple(grid.shape[1:])
    return trilinear_gather(grid.reshape(grid.shape[0], -1), *corners_from_coords(x, size))  # type: ignore[arg-type]


def interp_points(grid: torch.Tensor, points: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
    """Trilinear interpolation of a (C, X, Y, Z) grid over the box ``bounds`` (2, 3) at (N, 3) world points: (N, C).

    :func:`~nerfmeta.fields.grid_ops.interp_gather`'s values through :func:`trilinear_coords` (fused on a CPU).
    Points outside the box are clamped to its faces; no gradient flows to them.
    """
    size = tuple(grid.shape[1:])
    return trilinear_coords(grid, grid_coords(points.detach(), bounds, size).contiguous()).t()  # type: ignore[arg-type]
