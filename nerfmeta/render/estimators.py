"""Where along each ray to evaluate a field: packed ray marching and the occupancy-grid estimator.

An *estimator* turns rays into :class:`PackedSamples`: one flat list of samples sorted by ray, so
the work follows the samples that exist, not ``rays x longest ray``. :class:`OccupancyGrid` is the
estimator every backbone can share (nerfacc's ``OccGridEstimator``): it marches every ``step``
through its box, drops the samples whose nearest grid corner is marked empty (empty-space
skipping) and, given a density callback, the samples behind an opaque layer (early termination:
transmittance below ``early_stop_eps``). Its marks come from the field's own density: pruned
(:meth:`OccupancyGrid.prune`, marks only leave) or refreshed (:meth:`OccupancyGrid.refresh`,
marks follow the field) on the model's schedule.

On a CPU the march is one compiled kernel (numba; :func:`contracted_march_fused` for a contracted space,
:func:`march_fused` for a box): each ray's samples made one after another (in a contracted space each bin's far edge
contracted once and reused as the next bin's near edge), the occupancy looked up at the sample's position, and only
the kept samples written, the rays split over torch's threads. The same samples to float rounding (the kernel works
in float64 inside, so it is closer to a float64 march than PyTorch's float32 ops are). A beer training step's march,
430k samples: about 8 ms against 17-24 on the 2-core CPU; lego's at 100 x 100, 88k samples: 2.5-3.5 ms against
7.7-11.4 (BENCHMARKS.md, *Fused march*).

A field that needs no estimator samples its own way (e.g. the NeRF MLP's stratified +
importance sampling in :mod:`nerfmeta.render.sampling`).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType
from typing import Callable

import numpy
import torch
from torch import nn

from nerfmeta import fused
from nerfmeta.render.contraction import InnerBox, from_march, inner_exit, to_march
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


def split_sections(samples: PackedSamples, split: torch.Tensor, parts: int) -> PackedSamples:
    """Replace the sections ``split`` marks by ``parts`` equal sub-sections each (up-sampling where it matters).

    A sample stands for the section ``[t - delta / 2, t + delta / 2]`` (the form NeuS's opacity reads); a marked
    one becomes ``parts`` samples at the middles of that section's equal parts, each with ``delta / parts``. The
    packing (by ray, front to back) is kept and every ray's total length ``sum(delta)`` is unchanged.

    Args:
        samples: packed samples.
        split: (M,) bool, the sections to split.
        parts: sub-sections per split section (>= 1; 1 returns ``samples``).

    Returns:
        The refined samples (``far`` unchanged).
    """
    if parts < 1:
        raise ValueError(f"split_sections: parts={parts} must be >= 1")
    if parts == 1 or not bool(split.any()):
        return samples
    counts = torch.where(split, parts, 1)
    total = int(counts.sum())
    src = torch.repeat_interleave(torch.arange(len(samples), device=samples.t.device), counts, output_size=total)
    first = torch.cumsum(counts, 0) - counts
    j = (torch.arange(total, device=samples.t.device) - first.index_select(0, src)).to(samples.t.dtype)
    whole = samples.delta.index_select(0, src)
    delta = whole / counts.index_select(0, src).to(samples.t.dtype)
    t = samples.t.index_select(0, src) - 0.5 * whole + (j + 0.5) * delta
    return PackedSamples(samples.ray_idx.index_select(0, src), t, delta, samples.far)


def march_counts(near: torch.Tensor, far: torch.Tensor, step: float) -> torch.Tensor:
    """(n_rays,) int64 number of samples :func:`march_packed` puts every ``step`` in ``[near, far)``."""
    counts = torch.ceil((far - near) / step).clamp_(min=0)
    return (counts - ((counts > 0) & (near + step * (counts - 1) >= far)).to(counts.dtype)).long()  # rounding


def march_packed(
    near: torch.Tensor, far: torch.Tensor, step: float, jitter: torch.Tensor, first: int = 0, limit: int | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Samples every ``step`` from ``near`` to ``far``, packed (the packed form of ``fixed_step_samples``).

    Args:
        near, far: (n_rays,) with ``far >= near`` (equal: no samples).
        step: distance between samples.
        jitter: (n_rays,) in [0, 1): where each sample sits in its bin (0.5: the bin middle).
        first, limit: only the samples ``first .. first + limit - 1`` of each ray (a window of the
            march, exactly those samples of the whole one; ``limit`` None: to the end).

    Returns:
        ray_idx (M,) int64 non-decreasing, the ray of each sample; t (M,) distances; delta (M,)
        bin lengths (``step``, the last bin of a ray clipped at ``far``, so a ray's deltas sum
        to ``far - near``).
    """
    counts = march_counts(near, far, step)
    window = (counts - first).clamp_(min=0)
    if limit is not None:
        window = window.clamp_(max=limit)
    total = int(window.sum())
    n = near.shape[0]
    ray_idx = torch.repeat_interleave(torch.arange(n, device=near.device), window, output_size=total)
    start = torch.cumsum(window, 0) - window
    k = (torch.arange(total, device=near.device) - start.index_select(0, ray_idx)).to(near.dtype)
    if first:
        k += first
    t = torch.add((near + step * jitter).index_select(0, ray_idx), k, alpha=step)
    delta = torch.full_like(t, step)
    # The last bin of each ray ends at ``far`` (for the rays whose last sample is in the window).
    rays = torch.nonzero((window > 0) & (window + first == counts))[:, 0]
    last = start.index_select(0, rays) + window.index_select(0, rays) - 1
    last_start = near.index_select(0, rays) + step * (counts.index_select(0, rays) - 1).to(near.dtype)
    last_delta = (far.index_select(0, rays) - last_start).clamp_(min=0.0)
    delta.index_copy_(0, last, last_delta)
    t.index_copy_(0, last, last_start + last_delta * jitter.index_select(0, rays))
    return ray_idx, t, delta


def contracted_interval(origins: torch.Tensor, directions: torch.Tensor, near: torch.Tensor,
                        box: InnerBox) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(n_rays,) each: the inner-box exit ``t1`` and the marching interval ``[near_m, far_m]`` of :func:`contracted_march`."""
    t1 = inner_exit(origins, directions, near, box)
    near_m = to_march(near, t1, box.shell * box.radius)
    far_m = t1 + box.shell * box.radius * (1.0 - 1e-6)
    return t1, near_m, torch.maximum(far_m, near_m)


def contracted_march(origins: torch.Tensor, directions: torch.Tensor, near: torch.Tensor, box: InnerBox, step: float,
                     jitter: torch.Tensor, first: int = 0, limit: int | None = None) -> PackedSamples:
    """Packed samples of rays through the contracted space of ``box``, from ``near`` to (almost) infinity.

    Marches every ``step * box.radius`` in the marching distance of
    :func:`~nerfmeta.render.contraction.to_march` (world distance inside the inner box, disparity-like
    beyond it with ``L = box.shell * box.radius``), so that samples are about ``step`` apart in the
    contracted space everywhere: a ray crossing the shell gets about ``shell / step`` samples there
    however far the scene goes on. Each sample's ``delta`` is the contracted-space length of its
    interval (its two ends contracted), ``t`` its world distance. The march ends where the
    contracted position is within ``1e-6`` of the cube's face: that is the background.

    Args:
        origins, directions: (n_rays, 3) world rays (unit directions).
        near: (n_rays,) where each ray starts.
        box: the inner box and shell width.
        step: distance between samples in contracted units.
        jitter: (n_rays,) in [0, 1).
        first, limit: a window of each ray's samples, as in :func:`march_packed`.

    Returns:
        The samples, ``far`` being each ray's last world distance.
    """
    t1, near_m, far_m = contracted_interval(origins, directions, near, box)
    scale = box.shell * box.radius
    ray_idx, m, delta_m = march_packed(near_m, far_m, step * box.radius, jitter, first, limit)
    t1_s = t1.index_select(0, ray_idx)
    start = m - jitter.index_select(0, ray_idx) * delta_m
    edges = from_march(torch.stack([start, start + delta_m]), t1_s[None], scale)  # (2, M)
    o = origins.t().contiguous().index_select(1, ray_idx)  # (3, M): component-major, see PackedSamples.points
    d = directions.t().contiguous().index_select(1, ray_idx)
    a, b = (box.contract(torch.addcmul(o, e[None], d).t()).t() for e in edges)
    delta = (b - a).square().sum(0).sqrt()
    return PackedSamples(ray_idx, from_march(m, t1_s, scale), delta, from_march(far_m, t1, scale))


MARCH_SPLIT_MIN_SAMPLES = 65536
"""A fused march of at least this many samples is split over torch's threads (:func:`nerfmeta.fused.parts`)."""


def _smoke(kernels: ModuleType) -> None:
    """Marches one float32 ray of two samples through a contracted space and through a box (radius 0), with and
    without an occupancy grid (:func:`nerfmeta.fused.load`)."""
    one, two, starts = numpy.ones(1, numpy.float32), numpy.full(1, 2, numpy.int64), numpy.array([0, 2], numpy.int64)
    rays = numpy.zeros((1, 3), numpy.float32), numpy.ones((1, 3), numpy.float32), one * 0, one, one
    out = numpy.empty(2, numpy.int64), numpy.empty(2, numpy.float32), numpy.empty(2, numpy.float32)
    for occupied in (numpy.ones((1, 1, 1), numpy.bool_), numpy.ones((2, 2, 2), numpy.bool_)):
        for radius in (1.0, 0.0):
            kernels.march(two, two, starts, *rays, one * 0.5, 0.5, 0, 1.0, 1e-38, numpy.zeros(3), radius, 1.0, occupied,
                          numpy.zeros(3), numpy.ones(3), *out, 0, 1)


def _kernels() -> ModuleType | None:
    return fused.load("nerfmeta.render._march_numba", _smoke, "march kernel")


def fused_march_available() -> bool:
    """True when the march's kernel can be used (numba importable, the kernel compiled or loaded, which this call
    does once per process, and not switched off: :mod:`nerfmeta.fused`)."""
    return fused.enabled() and _kernels() is not None


def fused_march(origins: torch.Tensor) -> bool:
    """True when :meth:`OccupancyGrid.march` marches with one fused kernel (:func:`contracted_march_fused`,
    :func:`march_fused`): rays on a CPU in float32 or float64 and the kernels available."""
    return fused.takes(origins) and fused_march_available()


def _occupancy_args(occupied: torch.Tensor | None, aabb: torch.Tensor | None) -> tuple[numpy.ndarray, ...]:
    """The kernels' occupancy arguments: the marks, and the corner coordinates' origin and scale (float64); a single
    set corner when there is no grid (nothing skipped)."""
    if occupied is None or aabb is None:
        return numpy.ones((1, 1, 1), numpy.bool_), numpy.zeros(3), numpy.ones(3)
    lo = aabb[0].double()
    to_grid = torch.tensor([n - 1 for n in occupied.shape], dtype=torch.float64) / (aabb[1].double() - lo)
    return occupied.contiguous().numpy(), lo.numpy(), to_grid.numpy()


def _march_split(args: tuple, counts: torch.Tensor, first: int, limit: int | None,
                 dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Runs the march's kernel (:func:`nerfmeta.render._march_numba.march`, ``args`` its arguments after the first
    three) over the windows ``first .. first + limit - 1`` of rays of ``counts`` samples, the rays split where the
    samples are shared out evenly over torch's threads, each part writing its kept samples packed from the offset of
    its first ray: ``ray_idx``, ``t``, ``delta`` of the kept samples, packed."""
    window = (counts - first).clamp_(min=0)
    if limit is not None:
        window = window.clamp_(max=limit)
    starts = torch.cat([window.new_zeros(1), torch.cumsum(window, 0)])  # (n_rays + 1,): rays' first samples, total
    total = int(starts[-1])
    ray_idx = torch.empty(total, dtype=torch.long)
    t, delta = torch.empty(total, dtype=dtype), torch.empty(total, dtype=dtype)
    common = (counts.numpy(), window.numpy(), starts.numpy(), *args, ray_idx.numpy(), t.numpy(), delta.numpy())
    n_parts = fused.parts(total, MARCH_SPLIT_MIN_SAMPLES)
    cuts = [0, *torch.searchsorted(starts[:-1], torch.arange(1, n_parts) * total // n_parts).tolist(), len(counts)]
    kept = fused.split(_kernels().march, [(*common, cuts[p], cuts[p + 1]) for p in range(n_parts)])
    pieces = [slice(int(starts[cuts[p]]), int(starts[cuts[p]]) + kept[p]) for p in range(n_parts)]
    return tuple(torch.cat([a[piece] for piece in pieces]) if n_parts > 1 else a[pieces[0]]  # type: ignore[return-value]
                 for a in (ray_idx, t, delta))


def contracted_march_fused(origins: torch.Tensor, directions: torch.Tensor, near: torch.Tensor, box: InnerBox,
                           step: float, jitter: torch.Tensor, first: int = 0, limit: int | None = None,
                           occupied: torch.Tensor | None = None, aabb: torch.Tensor | None = None) -> PackedSamples:
    """:func:`contracted_march`'s samples from one compiled pass (the same to float rounding), less those whose
    nearest corner of ``occupied`` (X, Y, Z) bool over the contracted cube ``aabb`` (2, 3) is not set (None: all
    kept); rays on a CPU (:func:`fused_march`)."""
    t1, near_m, far_m = contracted_interval(origins, directions, near, box)
    scale, step_m = box.shell * box.radius, step * box.radius
    marks, lo, to_grid = _occupancy_args(occupied, aabb)
    args = (origins.contiguous().numpy(), directions.contiguous().numpy(), near_m.numpy(), far_m.numpy(), t1.numpy(),
            jitter.contiguous().numpy(), step_m, first, scale, torch.finfo(origins.dtype).tiny,
            numpy.asarray(box.centre, numpy.float64), box.radius, box.shell, marks, lo, to_grid)
    columns = _march_split(args, march_counts(near_m, far_m, step_m), first, limit, origins.dtype)
    return PackedSamples(*columns, from_march(far_m, t1, scale))


def march_fused(origins: torch.Tensor, directions: torch.Tensor, near: torch.Tensor, far: torch.Tensor, step: float,
                jitter: torch.Tensor, first: int = 0, limit: int | None = None, occupied: torch.Tensor | None = None,
                aabb: torch.Tensor | None = None) -> PackedSamples:
    """:func:`march_packed`'s samples from one compiled pass (the same to float rounding), less those whose nearest
    corner of ``occupied`` (X, Y, Z) bool over the box ``aabb`` (2, 3) is not set (None: all kept); rays on a CPU
    (:func:`fused_march`), ``near``/``far`` already clipped to the box."""
    near, far = near.contiguous(), far.contiguous()
    no_box = (0.0, 0.0, numpy.zeros(3), 0.0, 0.0)  # scale, tiny, centre, radius 0 (no contraction), shell
    args = (origins.contiguous().numpy(), directions.contiguous().numpy(), near.numpy(), far.numpy(),
            far.numpy(),  # in the inner-box exit's place: unread without a box
            jitter.contiguous().numpy(), step, first, *no_box, *_occupancy_args(occupied, aabb))
    return PackedSamples(*_march_split(args, march_counts(near, far, step), first, limit, origins.dtype), far)


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

    With an inner ``box`` (:class:`~nerfmeta.render.contraction.InnerBox`) the grid lives in the
    contracted space of an unbounded scene (``aabb`` is then the contracted cube): rays are marched
    to infinity by :func:`contracted_march`, samples are looked up at their contracted positions and
    their ``delta`` is in contracted units.

    Buffers: ``binaries`` (X, Y, Z) bool, ``aabb`` (2, 3) the marched box.
    """

    def __init__(self, aabb: torch.Tensor, binaries: torch.Tensor | None = None, box: InnerBox | None = None):
        super().__init__()
        self.register_buffer("aabb", aabb.detach().clone().float())
        if binaries is None:
            binaries = torch.ones(1, 1, 1, dtype=torch.bool, device=aabb.device)
        self.register_buffer("binaries", binaries)
        self.box = box

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
        round_samples: int = 0,
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
            round_samples: with ``early_stop_eps``, march and evaluate ``round_samples`` samples of
                every ray still alive at a time, so the density of what lies behind an opaque layer
                is never evaluated (0: the whole march at once). The same samples are kept either way
                (up to rounding of the transmittance at ``early_stop_eps``).

        Returns:
            The kept samples; ``far`` is the clipped far of every ray.
        """
        if self.box is None:
            near, far, _ = clip_to_aabb(origins, directions, near, far, self.aabb.to(origins.dtype))
        if sigma_fn is not None and early_stop_eps > 0.0 and round_samples > 0:
            return self._sampling_in_rounds(origins, directions, near, far, step, jitter, skip_empty, sigma_fn,
                                            early_stop_eps, alpha_thre, round_samples)
        samples = self.march(origins, directions, near, far, step, jitter, skip_empty)
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

    def march(self, origins: torch.Tensor, directions: torch.Tensor, near: torch.Tensor, far: torch.Tensor, step: float,
              jitter: torch.Tensor, skip_empty: bool, first: int = 0, limit: int | None = None) -> PackedSamples:
        """The samples ``first .. first + limit - 1`` of each ray (``near``/``far`` already clipped), empty ones skipped."""
        if fused_march(origins):
            skip = skip_empty and self.skips
            marks, aabb = (self.binaries, self.aabb) if skip else (None, None)
            if self.box is None:
                return march_fused(origins, directions, near, far, step, jitter, first, limit, marks, aabb)
            return contracted_march_fused(origins, directions, near, self.box, step, jitter, first, limit,
                                          marks, aabb)
        if self.box is not None:
            samples = contracted_march(origins, directions, near, self.box, step, jitter, first, limit)
        else:
            samples = PackedSamples(*march_packed(near, far, step, jitter, first, limit), far)
        if skip_empty and self.skips and len(samples):
            samples = samples.select(torch.nonzero(self.lookup(samples, origins, directions))[:, 0])
        return samples

    @torch.no_grad()
    def _sampling_in_rounds(self, origins, directions, near, far, step, jitter, skip_empty, sigma_fn, eps, alpha_thre,
                            round_samples) -> PackedSamples:
        """:meth:`sampling` with early termination, ``round_samples`` samples of the rays still alive at a time."""
        n = origins.shape[0]
        if self.box is not None:
            _, near_m, far_m = contracted_interval(origins, directions, near, self.box)
            counts = march_counts(near_m, far_m, step * self.box.radius)
        else:
            counts = march_counts(near, far, step)
        passed = torch.zeros(n, dtype=torch.float64, device=origins.device)  # optical depth in front of the window
        pieces: list[PackedSamples] = []
        rays = torch.arange(n, device=origins.device)
        first, ray_far = 0, None
        while True:
            rays = rays[counts.index_select(0, rays) > first]
            if not len(rays):
                break
            o, d = origins.index_select(0, rays), directions.index_select(0, rays)
            s = self.march(o, d, near.index_select(0, rays), far.index_select(0, rays), step, jitter.index_select(0, rays),
                           skip_empty, first, round_samples)
            first += round_samples
            if not len(s):
                continue
            tau = sigma_fn(s.points(o, d), s) * s.delta
            keep = torch.ones_like(tau, dtype=torch.bool)
            if alpha_thre > 0.0:
                keep &= alpha_from_tau(tau) >= alpha_thre
                tau = torch.where(keep, tau, torch.zeros_like(tau))
            before = passed.index_select(0, rays).index_select(0, s.ray_idx)
            keep &= packed_transmittance(tau, s.ray_idx, len(rays)) * torch.exp(-before).to(tau.dtype) >= eps
            passed.index_add_(0, rays, tau.double().new_zeros(len(rays)).index_add_(0, s.ray_idx, tau.double()))
            sel = torch.nonzero(keep)[:, 0]
            pieces.append(PackedSamples(rays.index_select(0, s.ray_idx.index_select(0, sel)), s.t.index_select(0, sel),
                                        s.delta.index_select(0, sel), s.far))
            rays = rays[torch.exp(-passed.index_select(0, rays)) >= eps]
        if self.box is not None:
            t1 = inner_exit(origins, directions, near, self.box)
            ray_far = from_march(far_m, t1, self.box.shell * self.box.radius)
        else:
            ray_far = far
        if not pieces:
            empty = origins.new_zeros(0)
            return PackedSamples(torch.zeros(0, dtype=torch.long, device=origins.device), empty, empty, ray_far)
        ray_idx = torch.cat([p.ray_idx for p in pieces])
        order = torch.sort(ray_idx, stable=True).indices
        return PackedSamples(ray_idx.index_select(0, order), torch.cat([p.t for p in pieces]).index_select(0, order),
                             torch.cat([p.delta for p in pieces]).index_select(0, order), ray_far)

    def lookup(self, samples: PackedSamples, origins: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
        """(M,) bool: the grid's mark at the corner nearest each sample."""
        dtype = origins.dtype
        lo = self.aabb[0].to(dtype)
        to_grid = torch.tensor([s - 1 for s in self.size], dtype=dtype, device=origins.device) / (self.aabb[1].to(dtype) - lo)
        if self.box is not None:
            x = ((self.box.contract(samples.points(origins, directions)) - lo) * to_grid).t()
            return self.binaries.view(-1)[nearest_from_coords(x, self.size)]
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
        alpha = evaluate_in_chunks(alpha_fn, grid_points(self.aabb, size).reshape(-1, 3), chunk)
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
        self.mark(self.occupied_by(alpha_fn, size, threshold, dilation))

    @torch.no_grad()
    def mark(self, occupied: torch.Tensor) -> None:
        """Mark exactly the corners of ``occupied`` (X, Y, Z) bool; nothing marked marks every corner instead."""
        self.binaries = occupied if bool(occupied.any()) else torch.ones_like(occupied)


@torch.no_grad()
def values_near(fn: Callable[[torch.Tensor], torch.Tensor], points: torch.Tensor, known: torch.Tensor | None, limit: float,
                chunk: int = 1 << 18) -> tuple[torch.Tensor, int]:
    """``fn`` again at the ``points`` whose ``known`` value is below ``limit``, ``known`` kept elsewhere.

    A narrow-band refresh: where ``fn`` is a distance that moves little between calls, only the points that
    were near the band need a new value. ``known=None`` evaluates every point.

    Returns:
        (K,) the values, and how many points were evaluated.
    """
    if known is None:
        return evaluate_in_chunks(fn, points, chunk), len(points)
    idx = torch.nonzero(known < limit)[:, 0]
    values = known.clone()
    values[idx] = evaluate_in_chunks(fn, points.index_select(0, idx), chunk).to(values.dtype)
    return values, len(idx)


def evaluate_in_chunks(fn: Callable[[torch.Tensor], torch.Tensor], points: torch.Tensor, chunk: int) -> torch.Tensor:
    """(K,) ``fn`` at ``points`` (K, 3), ``chunk`` points at a time so a whole grid fits memory."""
    return torch.cat([fn(c) for c in points.split(chunk)]) if len(points) else points.new_zeros(0)


def dilate(mask: torch.Tensor, radius: int) -> torch.Tensor:
    """Grow a (X, Y, Z) boolean mask by ``radius`` voxels along each axis (a cube, by max pooling)."""
    if radius <= 0:
        return mask.clone()
    k = 2 * radius + 1
    return torch.nn.functional.max_pool3d(mask[None, None].float(), k, stride=1, padding=radius)[0, 0] > 0
