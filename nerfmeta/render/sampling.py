"""Sample placement along rays (pure functions).

All samplers return the sample distances ``t`` (n_rays, n_samples) and the length ``delta`` of
the interval each sample stands for, so ``tau = sigma(t) * delta``.
"""

from __future__ import annotations

import torch


def stratified_samples(
    near: torch.Tensor,
    far: torch.Tensor,
    n_samples: int,
    *,
    generator: torch.Generator | None = None,
    perturb: bool = True,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Split ``[near, far]`` into ``n_samples`` equal bins and take one point per bin.

    Args:
        near, far: (n_rays,) with ``far >= near`` (equal gives zero-length intervals).
        n_samples: samples per ray.
        generator: random source for the jitter (``perturb=True``).
        perturb: jitter inside each bin (training); else the bin midpoints (evaluation).

    Returns:
        t (n_rays, n_samples), delta (n_rays, n_samples) the bin widths, and the bin edges
        (n_rays, n_samples + 1), used by :func:`importance_samples`.
    """
    u = torch.linspace(0.0, 1.0, n_samples + 1, dtype=near.dtype, device=near.device)
    edges = near[:, None] + (far - near)[:, None] * u
    if perturb:
        jitter = torch.rand(near.shape[0], n_samples, generator=generator, dtype=near.dtype, device="cpu")
        jitter = jitter.to(near.device)
    else:
        jitter = torch.full((near.shape[0], n_samples), 0.5, dtype=near.dtype, device=near.device)
    t = edges[:, :-1] + (edges[:, 1:] - edges[:, :-1]) * jitter
    delta = edges[:, 1:] - edges[:, :-1]
    return t, delta, edges


def fixed_step_samples(
    near: torch.Tensor,
    far: torch.Tensor,
    step: float,
    max_samples: int,
    *,
    generator: torch.Generator | None = None,
    perturb: bool = True,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Samples every ``step`` world units from ``near`` (DirectVoxGO-style marching).

    Args:
        near, far: (n_rays,).
        step: distance between samples.
        max_samples: samples per ray in the returned (padded) layout; pick it to cover the
            longest ray, ``ceil(max(far - near) / step)``.
        generator, perturb: one shared jitter per ray (training) or none.

    Returns:
        t (n_rays, max_samples), delta (n_rays, max_samples) equal to ``step`` inside the ray's
        interval, the last bin clipped to ``far`` (so the deltas sum to ``far - near``) and 0 past
        it, and valid (n_rays, max_samples) bool (samples past ``far`` sit at ``far``).
    """
    k = torch.arange(max_samples, dtype=near.dtype, device=near.device)
    if perturb:
        jitter = torch.rand(near.shape[0], 1, generator=generator, dtype=near.dtype, device="cpu").to(near.device)
    else:
        jitter = torch.full((near.shape[0], 1), 0.5, dtype=near.dtype, device=near.device)
    start = near[:, None] + step * k  # bin starts
    valid = start < far[:, None]
    end = torch.minimum(start + step, far[:, None])
    width = torch.where(valid, end - start, torch.zeros_like(start))
    t = torch.where(valid, start + width * jitter, far[:, None].expand_as(start))
    return t, width, valid


def importance_samples(
    edges: torch.Tensor,
    weights: torch.Tensor,
    n_samples: int,
    *,
    generator: torch.Generator | None = None,
    perturb: bool = True,
    eps: float = 1e-5,
) -> torch.Tensor:
    """Draw distances from the piecewise-constant PDF given by coarse weights (inverse CDF).

    Args:
        edges: (n_rays, n_bins + 1) bin edges, non-decreasing.
        weights: (n_rays, n_bins) non-negative bin weights (need not sum to 1). A small
            ``eps`` is added to every bin so that rays with zero weight fall back to uniform.
        n_samples: samples to draw per ray.
        generator, perturb: random uniforms (training) or evenly spaced quantiles.

    Returns:
        (n_rays, n_samples) sorted distances inside ``[edges[:, 0], edges[:, -1]]``. No gradient
        flows to ``weights`` (detached), as in NeRF's hierarchical sampling.
    """
    w = weights.detach() + eps
    pdf = w / w.sum(-1, keepdim=True)
    cdf = torch.cumsum(pdf, -1)
    cdf = torch.cat([torch.zeros_like(cdf[:, :1]), cdf], -1).clamp(max=1.0)
    n_rays = edges.shape[0]
    if perturb:
        u = torch.rand(n_rays, n_samples, generator=generator, dtype=edges.dtype, device="cpu").to(edges.device)
        u, _ = torch.sort(u, dim=-1)
    else:
        u = (torch.arange(n_samples, dtype=edges.dtype, device=edges.device) + 0.5) / n_samples
        u = u.expand(n_rays, n_samples).contiguous()
    idx = torch.searchsorted(cdf.contiguous(), u, right=True).clamp(1, cdf.shape[-1] - 1)
    cdf_lo, cdf_hi = cdf.gather(-1, idx - 1), cdf.gather(-1, idx)
    e_lo, e_hi = edges.gather(-1, idx - 1), edges.gather(-1, idx)
    span = cdf_hi - cdf_lo
    frac = torch.where(span > 0, (u - cdf_lo) / torch.where(span > 0, span, torch.ones_like(span)), torch.zeros_like(span))
    return e_lo + frac.clamp(0.0, 1.0) * (e_hi - e_lo)


def intervals_from_points(t: torch.Tensor, near: torch.Tensor, far: torch.Tensor) -> torch.Tensor:
    """Interval lengths for sorted sample points: the Voronoi cell of each point inside ``[near, far]``.

    Args:
        t: (n_rays, n_samples) sorted distances within ``[near, far]``.
        near, far: (n_rays,).

    Returns:
        (n_rays, n_samples) non-negative lengths that sum to ``far - near`` per ray.
    """
    mids = 0.5 * (t[:, 1:] + t[:, :-1])
    lo = torch.cat([near[:, None], mids], -1)
    hi = torch.cat([mids, far[:, None]], -1)
    return (hi - lo).clamp(min=0.0)
