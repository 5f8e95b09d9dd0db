"""Contracted space for unbounded scenes: all of space squashed into a bounded cube (pure functions).

As in mip-NeRF 360 (Barron et al., 2022) and DirectVoxGO v2's unbounded scenes: world points are
first normalised into the *inner box*, ``p = (x - centre) / radius``, which holds the object the
cameras look at and what surrounds it; inside it (``|p|_inf <= 1``) space is kept as it is, outside it is squashed
into a shell of width ``shell``::

    contract(p) = p                                              if |p| <= 1
                = (1 + shell - shell / |p|) * p / |p|            otherwise

with ``|.|`` the inf-norm, so the inner box stays a cube and the whole of space maps onto the cube
``[-(1 + shell), 1 + shell]^3`` that a voxel grid fills (``shell = 1`` is mip-NeRF 360's ``2 - 1/|p|``
in the inf-norm; DirectVoxGO v2 calls ``shell`` ``bg_len``). The map is continuous (at ``|p| = 1``
both sides give ``p``), injective, and along every ray from the centre the contracted norm grows
monotonically towards ``1 + shell``: the far field gets ever fewer voxels.

Rays are marched through the contracted space with :func:`contracted_march`: evenly in world
distance inside the inner box and evenly in a disparity-like distance beyond it, so that the samples
fall about evenly in the contracted space and the far field gets fewer of them; each sample's
``delta`` is its interval's length *in the contracted space* (the field's densities are per unit of
that space, as DirectVoxGO v2's).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType

import numpy
import torch

from nerfmeta import fused
from nerfmeta.render.rays import intersect_aabb


def contract(p: torch.Tensor, shell: float = 1.0) -> torch.Tensor:
    """Squash normalised points into the cube of half-side ``1 + shell`` (inf-norm contraction).

    Args:
        p: (N, 3) points in inner-box units (the inner box is ``[-1, 1]^3``).
        shell: width of the shell the outside of the inner box is squashed into (> 0).

    Returns:
        (N, 3) contracted points: ``p`` itself inside the inner box, else
        ``(1 + shell - shell / |p|_inf) * p / |p|_inf``; stored component-major (the transpose of a
        contiguous (3, N)), which is what a CPU works fastest on.
    """
    q = p.t()  # (3, N): one row per axis, contiguous when ``p`` is component-major (as packed sample points are)
    norm = torch.maximum(torch.maximum(q[0].abs(), q[1].abs()), q[2].abs())
    outside = norm > 1.0
    safe = torch.where(outside, norm, torch.ones_like(norm))
    scale = torch.where(outside, (1.0 + shell - shell / safe) / safe, torch.ones_like(norm))
    return (q * scale).t()


def _smoke(kernels: ModuleType) -> None:
    """Runs the kernel on two float32 points in both layouts points come in: component-major (sample points, whose
    transpose is a C-contiguous (3, N)) and row-major (grid points), so neither compiles inside a fit."""
    for x in (numpy.full((3, 2), 2.0, numpy.float32), numpy.full((2, 3), 2.0, numpy.float32).T):
        kernels.contract(x, 0.0, 0.0, 0.0, 1.0, 1.0, numpy.empty((3, 2), numpy.float32))


def _kernels() -> ModuleType | None:
    return fused.load("nerfmeta.render._contraction_numba", _smoke, "contraction kernel")


def fused_contraction_available() -> bool:
    """True when the contraction's kernel can be used (numba importable, the kernel compiled or loaded, which this
    call does once per process, and not switched off: :mod:`nerfmeta.fused`)."""
    return fused.enabled() and _kernels() is not None


def fused_contraction(x: torch.Tensor) -> bool:
    """True when :meth:`InnerBox.contract` takes the points ``x`` (N, 3) through the fused kernel: float32 or float64
    on a CPU, no gradient wanted, and the kernel available (:func:`fused_contraction_available`)."""
    return (fused.takes(x) and x.ndim == 2 and x.shape[1] == 3 and not (x.requires_grad and torch.is_grad_enabled())
            and fused_contraction_available())


@dataclass(frozen=True)
class InnerBox:
    """The cube kept at full resolution: ``centre`` (3,) world position and half-side ``radius``."""

    centre: tuple[float, float, float]
    radius: float
    shell: float = 1.0

    def normalise(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 3) world points -> inner-box units (the inner box becomes ``[-1, 1]^3``)."""
        return (x - torch.tensor(self.centre, dtype=x.dtype, device=x.device)) / self.radius

    def contract(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 3) world points -> (N, 3) contracted points in ``[-(1 + shell), 1 + shell]^3``, component-major.

        On a CPU, where no gradient is taken, one fused pass (:mod:`nerfmeta.render._contraction_numba`; the same
        values to float rounding, :func:`fused_contraction`), else :func:`contract` of :meth:`normalise`.
        """
        if fused_contraction(x):
            out = torch.empty(3, x.shape[0], dtype=x.dtype)
            _kernels().contract(x.detach().t().numpy(), *self.centre, self.radius, self.shell, out.numpy())
            return out.t()
        return contract(self.normalise(x), self.shell)

    def aabb(self, dtype=torch.float32, device=None) -> torch.Tensor:
        """(2, 3) the inner box in world coordinates."""
        c = torch.tensor(self.centre, dtype=dtype, device=device)
        return torch.stack([c - self.radius, c + self.radius])

    @property
    def extent(self) -> float:
        """Half-side of the contracted cube, ``1 + shell``."""
        return 1.0 + self.shell


INNER_FRACTION = 0.5
"""Half-side of the inner box as a fraction of the cameras' median distance to what they look at."""


def inner_box_from_cameras(centres: torch.Tensor, focus: torch.Tensor | None, *, fraction: float = INNER_FRACTION,
                           shell: float = 1.0) -> InnerBox:
    """The inner box of a capture: centred on what the cameras look at, reaching ``fraction`` of the way to them.

    The cameras stand in the shell: a grid a 2-core CPU can fit in minutes has to spend its
    full-resolution voxels on the object and what surrounds it, not on the air around the cameras
    (with the cameras inside, as in mip-NeRF 360, beer's can would get a voxel per ~20 pixels).

    Args:
        centres: (n, 3) camera centres.
        focus: (3,) the point the cameras look at (e.g. the least-squares nearest point to their
            optical axes), or None to use the mean of the centres.
        fraction: the half-side is ``fraction`` times the median inf-norm distance of a camera from the centre.
        shell: the shell width of the contraction.
    """
    c = centres.double()
    centre = c.mean(0) if focus is None else focus.double()
    radius = float((c - centre).abs().amax(-1).median()) * fraction
    if not radius > 0:
        radius = 1.0
    return InnerBox(tuple(float(v) for v in centre), radius, shell)  # type: ignore[arg-type]


def inner_exit(origins: torch.Tensor, directions: torch.Tensor, near: torch.Tensor, box: InnerBox) -> torch.Tensor:
    """(n_rays,) distance at which each ray leaves the inner box (``near`` for rays that miss it or have left it)."""
    _, t_out, hit = intersect_aabb(origins, directions, box.aabb(origins.dtype, origins.device))
    return torch.where(hit, torch.maximum(t_out, near), near)


def to_march(t: torch.Tensor, t1: torch.Tensor, scale: float) -> torch.Tensor:
    """Marching distance ``m(t)``: ``t`` up to the inner exit ``t1``, then ``t1 + L (1 - L / (t - t1 + L))``.

    ``L = scale`` (world units). ``m`` is continuous with slope 1 at ``t1``, strictly increasing and
    tends to ``t1 + L`` as ``t -> inf``: even steps in ``m`` beyond ``t1`` are even steps in
    disparity ``1 / (t - t1 + L)``. All arguments broadcast; ``t`` may be ``inf``.
    """
    beyond = t - t1 + scale
    outer = t1 + scale * (1.0 - scale / beyond.clamp(min=scale))
    return torch.where(t > t1, outer, t)


def from_march(m: torch.Tensor, t1: torch.Tensor, scale: float) -> torch.Tensor:
    """The inverse of :func:`to_march`: ``t(m)`` for ``m < t1 + scale``."""
    left = (t1 + scale - m).clamp(min=torch.finfo(m.dtype).tiny)
    return torch.where(m > t1, t1 - scale + scale * scale / left, m)
