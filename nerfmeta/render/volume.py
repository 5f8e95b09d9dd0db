"""Volume rendering: density activation, alpha, transmittance and compositing.

Pure functions. :func:`render_packed` is the one compositor every backbone renders with, in
training and evaluation alike: samples come *packed* (one flat list sorted by ray, see
:mod:`nerfmeta.render.estimators`), so a ray costs what its samples cost. The dense forms
(:func:`render_weights`, :func:`composite`) serve fixed-count samplers and tests. Compositing works from *optical depths* ``tau = sigma * delta`` rather than from
alphas, so the transmittance ``T_i = exp(-sum_{j<i} tau_j)`` is computed in log space exactly:
``log(1 - alpha_i) = -tau_i`` needs no ``log(1 - alpha)`` that would be ``-inf`` at ``alpha = 1``.
For any finite non-negative ``sigma`` (tested up to 1e6) and ``delta`` (1e-10 to 1e10, and 0)
the outputs and their gradients are finite, every weight is in [0, 1] and the weights of a ray
sum to ``1 - T_final`` (at most 1, to float rounding).

On a CPU the packed compositor runs as two fused kernels (numba; :mod:`nerfmeta.render._volume_numba`): the
weights from the optical depths, and the weighted sums of colour and depth, each with its backward in one pass,
where PyTorch takes some twenty whole-array operations for the same. On the 2-core CPU, at the size of a 4096-ray
step of the beer capture (about 430k samples), a forward and backward through this function took 15 ms against 23
in PyTorch's ops, and 120-s fits of beer made 1155 steps against 988 (medians of five; BENCHMARKS.md, *Fused
compositing*; lego at 100 x 100, a fifth of the samples a step, showed no gain). Values and gradients match
PyTorch's path to float rounding (the kernels compute the transmittance in float64); a second derivative (MAML) is
taken through PyTorch's ops. Without numba, on a GPU, or with ``NERFMETA_FUSED_LOOKUPS=0``, PyTorch's path runs
(:mod:`nerfmeta.fused`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import ModuleType
from typing import Callable

import numpy
import torch
import torch.nn.functional as F

from nerfmeta import fused


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


# ----- packed samples: the one compositor every backbone renders with ----------------------------


def packed_weights(tau: torch.Tensor, ray_idx: torch.Tensor, n_rays: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Compositing weights ``T_i * alpha_i`` of packed samples (the packed form of :func:`render_weights`).

    The transmittance in front of a sample, ``T_i = exp(-sum of the ray's earlier tau)``, takes its
    exclusive per-ray sum from one running sum in float64 (exact enough for any batch).

    Args:
        tau: (M,) non-negative optical depths, samples of a ray contiguous and front to back.
        ray_idx: (M,) non-decreasing ray of each sample.
        n_rays: number of rays.

    Returns:
        weights (M,) in [0, 1]; t_final (n_rays,) transmittance after each ray's last sample
        (1 for rays without samples), so that per ray ``sum(weights) + t_final == 1``.
    """
    if _fused_for(tau, ray_idx):
        return _PackedWeights.apply(tau, ray_idx.contiguous(), n_rays)
    return _packed_weights_torch(tau, ray_idx, n_rays)


def _packed_weights_torch(tau: torch.Tensor, ray_idx: torch.Tensor, n_rays: int) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`packed_weights` in PyTorch's ops (differentiable to any order)."""
    log_t_before, ray_sum = _packed_log_transmittance(tau, ray_idx, n_rays)
    return torch.exp(log_t_before).to(tau.dtype) * alpha_from_tau(tau), torch.exp(-ray_sum).to(tau.dtype)


def packed_transmittance(tau: torch.Tensor, ray_idx: torch.Tensor, n_rays: int) -> torch.Tensor:
    """(M,) transmittance in front of each packed sample (``T_i``, 1 for a ray's first sample); see :func:`packed_weights`."""
    return torch.exp(_packed_log_transmittance(tau, ray_idx, n_rays)[0]).to(tau.dtype)


def packed_exclusive_sum(x: torch.Tensor, ray_idx: torch.Tensor, n_rays: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-ray sums of packed values: (M,) float64 sum of the ray's *earlier* samples, (n_rays,) float64 ray totals.

    One running sum in float64 minus the running sum at each ray's start (exact enough for any batch;
    differentiable).

    Args:
        x: (M,) values, samples of a ray contiguous; ray_idx: (M,) non-decreasing ray of each sample.
    """
    x64 = x.double()
    ray_sum = x64.new_zeros(n_rays).index_add(0, ray_idx, x64)
    before_ray = torch.cumsum(ray_sum, 0) - ray_sum
    # index_select, not before_ray[ray_idx]: its backward is an index_add_, not an accumulating index_put_.
    return torch.cumsum(x64, 0) - x64 - before_ray.index_select(0, ray_idx), ray_sum


def _packed_log_transmittance(tau: torch.Tensor, ray_idx: torch.Tensor, n_rays: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(M,) float64 ``log T_i`` in front of each sample and (n_rays,) float64 per-ray sums of ``tau``."""
    before, ray_sum = packed_exclusive_sum(tau, ray_idx, n_rays)
    return -before.clamp(min=0.0), ray_sum


def packed_distortion(weights: torch.Tensor, s: torch.Tensor, ds: torch.Tensor, ray_idx: torch.Tensor,
                      n_rays: int) -> torch.Tensor:
    """mip-NeRF 360's distortion loss of each ray (Barron et al., CVPR 2022, eq. 15), packed, in O(M).

    ``sum_{i,j} w_i w_j |s_i - s_j| + 1/3 sum_i w_i^2 ds_i``: small when a ray's weight sits in one
    short interval, large when it is smeared along the ray (haze, floaters). With the samples of a
    ray sorted by ``s``, the double sum is ``2 sum_i w_i (s_i W_i - S_i)``, ``W_i`` and ``S_i`` the
    sums of ``w`` and ``w s`` over the ray's earlier samples.

    Args:
        weights: (M,) compositing weights; s: (M,) sample positions along the ray (normalised, e.g. to
            [0, 1]), non-decreasing within a ray; ds: (M,) the intervals' lengths in the same units.
        ray_idx: (M,) non-decreasing ray of each sample; n_rays: number of rays.

    Returns:
        (n_rays,) in the weights' dtype (0 for rays without samples).
    """
    w64, s64 = weights.double(), s.double()
    w_before, _ = packed_exclusive_sum(w64, ray_idx, n_rays)
    ws_before, _ = packed_exclusive_sum(w64 * s64, ray_idx, n_rays)
    per_sample = 2.0 * w64 * (s64 * w_before - ws_before) + w64.square() * ds.double() / 3.0
    return per_sample.new_zeros(n_rays).index_add(0, ray_idx, per_sample).to(weights.dtype)


@dataclass
class Composite:
    """What :func:`render_packed` returns.

    Attributes:
        rgb: (n_rays, 3) colour composited on the background.
        acc: (n_rays,) opacity ``1 - T_final``.
        depth: (n_rays,) expected termination distance (``far`` for what passes through).
        weights: (M,) compositing weight of every sample.
    """

    rgb: torch.Tensor
    acc: torch.Tensor
    depth: torch.Tensor
    weights: torch.Tensor


def render_packed(
    tau: torch.Tensor,
    t: torch.Tensor,
    ray_idx: torch.Tensor,
    far: torch.Tensor,
    background: torch.Tensor,
    rgb_fn: Callable[[torch.Tensor | None, torch.Tensor], torch.Tensor],
    *,
    color_thres: float = 0.0,
) -> Composite:
    """Composite packed samples into colour, opacity and depth (nerfacc's ``rendering``, packed).

    Colour is asked for only where it counts: with ``color_thres > 0``, samples whose (detached)
    weight is not above it get no colour (their contribution is below the threshold).

    Args:
        tau: (M,) optical depths ``sigma * delta``, samples of a ray contiguous and front to back.
        t: (M,) sample distances.
        ray_idx: (M,) non-decreasing ray of each sample.
        far: (n_rays,) where rays that pass through are taken to end (for the depth).
        background: (3,) or (n_rays, 3) colour behind the content.
        rgb_fn: ``rgb_fn(sel, ray_idx_sel)`` returns (K, 3) colours of the samples ``sel`` (K,)
            (None: all M samples), ``ray_idx_sel`` (K,) being their rays.
        color_thres: weight a sample must exceed to be coloured (0: every sample).

    Returns:
        :class:`Composite`.
    """
    n_rays = far.shape[0]
    weights, t_final = packed_weights(tau, ray_idx, n_rays)
    if color_thres > 0.0:
        sel = torch.nonzero(weights.detach() > color_thres)[:, 0]
        if sel.numel() == weights.numel():
            sel = None
    else:
        sel = None
    ray_c = ray_idx if sel is None else ray_idx.index_select(0, sel)
    colour = rgb_fn(sel, ray_c)
    if _fused_for(weights, ray_idx) and colour.dtype == weights.dtype and not t.requires_grad:
        rgb, depth = _WeightedSums.apply(weights, colour, sel, ray_c, ray_idx, t, n_rays)
    else:
        rgb, depth = _weighted_sums_torch(weights, colour, sel, ray_c, ray_idx, t, n_rays)
    return Composite(rgb=rgb + t_final[:, None] * background, acc=1.0 - t_final, depth=depth + t_final * far,
                     weights=weights)


def _weighted_sums_torch(weights: torch.Tensor, colour: torch.Tensor, sel: torch.Tensor | None, ray_c: torch.Tensor,
                         ray_idx: torch.Tensor, t: torch.Tensor, n_rays: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Per ray, the weighted sum of the colours (K, 3) of the samples ``sel`` (None: all), whose rays are ``ray_c``
    (K,), and of the distances ``t`` (M,) of every sample: (n_rays, 3), (n_rays,). PyTorch's ops (differentiable to
    any order)."""
    w_c = weights if sel is None else weights.index_select(0, sel)
    rgb = weights.new_zeros(n_rays, 3).index_add(0, ray_c, w_c[:, None] * colour)
    return rgb, weights.new_zeros(n_rays).index_add(0, ray_idx, weights * t)


# ----- the fused CPU kernels of the compositor ------------------------------------------------------------------

_EVERY = numpy.empty(0, dtype=numpy.int64)


def _smoke(kernels: ModuleType) -> None:
    """Runs the four kernels on one float32 sample, with colours in both memory orders a field returns them in (a
    grid lookup's ``(3, K)`` transposed, an MLP's ``(K, 3)``), so none compiles inside a fit (:func:`nerfmeta.fused.load`)."""
    one, ray = numpy.ones(1, numpy.float32), numpy.zeros(1, numpy.int64)
    em1, decay, t64, f64 = numpy.full(1, -0.5), numpy.full(1, 0.5), numpy.ones(1), numpy.ones(1)
    kernels.weights_forward(em1, decay, ray, t64, one.copy(), f64)
    kernels.weights_backward(em1, decay, ray, t64, f64, one, one, one.copy())
    rgb = numpy.zeros((1, 3), numpy.float32)
    for colour in (numpy.ones((1, 3), numpy.float32), numpy.ones((3, 1), numpy.float32).T):
        kernels.composite_forward(one, colour, _EVERY, ray, one, rgb, one.copy())
        kernels.composite_backward(one, colour, _EVERY, ray, one, rgb, one, one.copy(), numpy.empty_like(colour))


def _kernels() -> ModuleType | None:
    return fused.load("nerfmeta.render._volume_numba", _smoke, "compositing kernels")


def fused_compositing() -> bool:
    """True when :func:`render_packed` composites CPU tensors with the fused kernels (numba importable, its kernels
    compiled or loaded, which this call does once per process, and not switched off)."""
    return fused.enabled() and _kernels() is not None


def _fused_for(values: torch.Tensor, ray_idx: torch.Tensor) -> bool:
    """True when the compositor's kernels take these CPU float32/float64 samples."""
    return (fused.takes(values) and ray_idx.device.type == "cpu" and ray_idx.dtype == torch.int64
            and fused_compositing())


class _PackedWeights(torch.autograd.Function):
    """:func:`packed_weights` by the fused kernels; a second derivative goes through PyTorch's ops."""

    @staticmethod
    def forward(ctx, tau: torch.Tensor, ray_idx: torch.Tensor, n_rays: int):  # type: ignore[override]
        minus = -tau.detach().double()
        em1, decay = torch.expm1(minus), torch.exp(minus)
        t_before, weights, t_final = torch.empty_like(em1), torch.empty_like(tau), em1.new_ones(n_rays)
        _kernels().weights_forward(em1.numpy(), decay.numpy(), ray_idx.numpy(), t_before.numpy(), weights.numpy(),
                                   t_final.numpy())
        ctx.save_for_backward(tau, ray_idx, em1, decay, t_before, t_final)
        ctx.n_rays = n_rays
        return weights, t_final.to(tau.dtype)

    @staticmethod
    def backward(ctx, grad_w: torch.Tensor | None, grad_t: torch.Tensor | None):  # type: ignore[override]
        tau, ray_idx, em1, decay, t_before, t_final = ctx.saved_tensors
        grad_w = torch.zeros_like(tau) if grad_w is None else grad_w.contiguous()
        grad_t = t_final.new_zeros(ctx.n_rays, dtype=tau.dtype) if grad_t is None else grad_t.contiguous()
        if torch.is_grad_enabled():  # create_graph: a gradient that is itself differentiable
            with torch.enable_grad():
                outputs = _packed_weights_torch(tau, ray_idx, ctx.n_rays)
            return torch.autograd.grad(outputs, tau, (grad_w, grad_t), create_graph=True)[0], None, None
        grad_tau = torch.empty_like(tau)
        _kernels().weights_backward(em1.numpy(), decay.numpy(), ray_idx.numpy(), t_before.numpy(), t_final.numpy(),
                                    grad_w.detach().numpy(), grad_t.detach().numpy(), grad_tau.numpy())
        return grad_tau, None, None


class _WeightedSums(torch.autograd.Function):
    """:func:`_weighted_sums_torch` by the fused kernels; a second derivative goes through PyTorch's ops."""

    @staticmethod
    def forward(ctx, weights: torch.Tensor, colour: torch.Tensor, sel: torch.Tensor | None,  # type: ignore[override]
                ray_c: torch.Tensor, ray_idx: torch.Tensor, t: torch.Tensor, n_rays: int):
        weights, t = weights.contiguous(), t.to(weights.dtype).contiguous()  # colour as it comes (numba takes strides)
        sel_np = _EVERY if sel is None else sel.contiguous().numpy()
        rgb, depth = weights.new_zeros(n_rays, 3), weights.new_zeros(n_rays)
        _kernels().composite_forward(weights.detach().numpy(), colour.detach().numpy(), sel_np, ray_idx.numpy(),
                                     t.numpy(), rgb.numpy(), depth.numpy())
        ctx.save_for_backward(weights, colour, ray_c, ray_idx, t)
        ctx.sel, ctx.sel_np, ctx.n_rays = sel, sel_np, n_rays
        return rgb, depth

    @staticmethod
    def backward(ctx, grad_rgb: torch.Tensor | None, grad_depth: torch.Tensor | None):  # type: ignore[override]
        weights, colour, ray_c, ray_idx, t = ctx.saved_tensors
        grad_rgb = weights.new_zeros(ctx.n_rays, 3) if grad_rgb is None else grad_rgb.contiguous()
        grad_depth = weights.new_zeros(ctx.n_rays) if grad_depth is None else grad_depth.contiguous()
        if torch.is_grad_enabled():  # create_graph: a gradient that is itself differentiable
            with torch.enable_grad():
                outputs = _weighted_sums_torch(weights, colour, ctx.sel, ray_c, ray_idx, t, ctx.n_rays)
            grads = torch.autograd.grad(outputs, (weights, colour), (grad_rgb, grad_depth), create_graph=True)
            return grads[0], grads[1], None, None, None, None, None
        grad_w, grad_colour = torch.empty_like(weights), torch.empty_like(colour)
        _kernels().composite_backward(weights.detach().numpy(), colour.detach().numpy(), ctx.sel_np, ray_idx.numpy(),
                                      t.numpy(), grad_rgb.detach().numpy(), grad_depth.detach().numpy(),
                                      grad_w.numpy(), grad_colour.numpy())
        return grad_w, grad_colour, None, None, None, None, None
