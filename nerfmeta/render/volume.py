"""Volume rendering: density activation, alpha, transmittance and compositing.

Pure functions. Compositing works from *optical depths* ``tau = sigma * delta`` rather than from
alphas, so the transmittance ``T_i = exp(-sum_{j<i} tau_j)`` is computed in log space exactly:
``log(1 - alpha_i) = -tau_i`` needs no ``log(1 - alpha)`` that would be ``-inf`` at ``alpha = 1``.
For any finite non-negative ``sigma`` (tested up to 1e6) and ``delta`` (1e-10 to 1e10, and 0)
the outputs and their gradients are finite, every weight is in [0, 1] and the weights of a ray
sum to ``1 - T_final`` (at most 1, to float rounding).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def softplus_shift_for_alpha(alpha_init: float, interval: float = 1.0) -> float:
    """The shift ``b`` such that ``raw = 0`` gives alpha ``alpha_init`` over an ``interval``.

    With ``sigma = softplus(raw + b)``, a sample of length ``interval`` has
    ``alpha = 1 - exp(-softplus(b) * interval)``; solving for ``alpha = alpha_init`` gives
    ``b = log(expm1(-log1p(-alpha_init) / interval))`` (DirectVoxGO's ``act_shift`` for
    ``interval = 1``). Accurate down to ``alpha_init = 1e-12``.
    """
    if not 0.0 < alpha_init < 1.0:
        raise ValueError(f"alpha_init must be in (0, 1), got {alpha_init}")
    if interval <= 0.0:
        raise ValueError(f"interval must be > 0, got {interval}")
    target = -math.log1p(-alpha_init) / interval  # required softplus(b)
    if target > 30.0:
        return target  # softplus(x) == x to double precision here
    return math.log(math.expm1(target))


def shifted_softplus(raw: torch.Tensor, shift: float) -> torch.Tensor:
    """Density ``sigma = softplus(raw + shift)``: non-negative, smooth, never saturating to 0 gradient."""
    return F.softplus(raw + shift)


def alpha_from_tau(tau: torch.Tensor) -> torch.Tensor:
    """Alpha ``1 - exp(-tau)`` computed as ``-expm1(-tau)`` (exact for tiny ``tau``).

    Args:
        tau: (...) non-negative optical depths.
    """
    return -torch.expm1(-tau)


def render_weights(tau: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Compositing weights ``w_i = T_i * alpha_i`` from optical depths.

    Args:
        tau: (n_rays, n_samples) non-negative optical depths ``sigma_i * delta_i``, samples ordered
            front to back. Zero for samples that are skipped or lie outside the ray's interval.

    Returns:
        weights (n_rays, n_samples) in [0, 1], and the transmittance left after the last sample,
        (n_rays,) in [0, 1], so that ``weights.sum(-1) + t_final == 1`` up to rounding.
    """
    log_t = -torch.cumsum(tau, dim=-1)  # log transmittance *after* each sample
    log_t_before = F.pad(log_t[..., :-1], (1, 0))  # exclusive: T_0 = 1
    weights = torch.exp(log_t_before) * alpha_from_tau(tau)
    t_final = torch.exp(log_t[..., -1]) if tau.shape[-1] > 0 else torch.ones(tau.shape[:-1], dtype=tau.dtype, device=tau.device)
    return weights, t_final


def composite(
    weights: torch.Tensor, values: torch.Tensor, t_final: torch.Tensor, background: torch.Tensor | float | None
) -> torch.Tensor:
    """Weighted sum of per-sample values, with the remaining transmittance on a background.

    Args:
        weights: (n_rays, n_samples).
        values: (n_rays, n_samples, C).
        t_final: (n_rays,) transmittance after the last sample.
        background: (C,) or (n_rays, C) or a scalar colour, or None for no background (black).

    Returns:
        (n_rays, C).
    """
    out = torch.einsum("rs,rsc->rc", weights, values)
    if background is not None:
        out = out + t_final[:, None] * torch.as_tensor(background, dtype=out.dtype, device=out.device)
    return out


def expected_depth(weights: torch.Tensor, t: torch.Tensor, t_final: torch.Tensor, far: torch.Tensor) -> torch.Tensor:
    """Expected ray termination distance; rays that pass through count as reaching ``far``.

    Args:
        weights: (n_rays, n_samples); t: (n_rays, n_samples) sample distances;
        t_final: (n_rays,); far: (n_rays,).

    Returns:
        (n_rays,) depth.
    """
    return (weights * t).sum(-1) + t_final * far
