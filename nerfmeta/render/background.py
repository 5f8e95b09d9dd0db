"""A learned background: a colour per ray direction, for what a ray meets after everything a grid holds (pure functions).

Beyond an unbounded scene's contracted space, what a ray meets is in the limit a function of its direction alone
(NeRF++'s view of the far field: at infinity every camera sees the same thing along a direction); the voxel grid
also uses it past a forward-facing scene's NDC far plane, indexed there by the NDC direction
(:class:`~nerfmeta.fields.voxel_grid.VoxelGridConfig` ``background_map``). Stored as an equirectangular table,
``(C, H, W)``: row ``i`` is latitude ``(i + 0.5) / H * pi - pi / 2`` (``-pi/2`` looking along ``-z``), column ``j``
longitude ``(j + 0.5) / W * 2 pi - pi`` (``atan2(y, x)``), looked up bilinearly, wrapping round in longitude and
clamped at the poles.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def equirect_coords(directions: torch.Tensor) -> torch.Tensor:
    """(N, 3) directions (any length > 0) -> (N, 2) ``(longitude / pi, latitude / (pi / 2))``, each in [-1, 1]."""
    d = F.normalize(directions, dim=-1)
    lon = torch.atan2(d[:, 1], d[:, 0]) / math.pi
    lat = torch.asin(d[:, 2].clamp(-1.0, 1.0)) / (0.5 * math.pi)
    return torch.stack([lon, lat], dim=-1)


def equirect_lookup(table: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """Bilinear value of an equirectangular ``table`` (C, H, W) along each of ``directions`` (N, 3) -> (N, C).

    Longitude wraps (the last column blends into the first across ``lon = +-pi``); latitude is clamped to the
    first and last rows' centres. Differentiable in ``table``.
    """
    _, _, w = table.shape
    wrapped = torch.cat([table[:, :, -1:], table, table[:, :, :1]], dim=2)  # one column each side, for the seam
    uv = equirect_coords(directions).to(table.dtype)
    # ``align_corners=False`` puts column j of the padded table at ((j + 0.5) / (W + 2)) * 2 - 1: rescale the
    # longitude so that the unpadded columns keep their centres.
    uv = torch.stack([uv[:, 0] * (w / (w + 2)), uv[:, 1]], dim=-1)
    out = F.grid_sample(wrapped[None], uv[None, :, None], mode="bilinear", padding_mode="border", align_corners=False)
    return out[0, :, :, 0].t()


class _InwardClamp(torch.autograd.Function):
    """``clamp`` in the forward pass; in the backward pass the gradient also reaches values outside the range where a
    descent step would move them back towards it."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, low: float, high: float) -> torch.Tensor:  # type: ignore[override]
        ctx.save_for_backward(x)
        ctx.low, ctx.high = low, high
        return x.clamp(low, high)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, None, None]:  # type: ignore[override]
        (x,) = ctx.saved_tensors
        inside = (x >= ctx.low) & (x <= ctx.high)
        inward = ((x < ctx.low) & (grad < 0)) | ((x > ctx.high) & (grad > 0))  # descent moves x by -grad
        return grad * (inside | inward), None, None


def clamp_inward(x: torch.Tensor, low: float = 0.0, high: float = 1.0) -> torch.Tensor:
    """``x.clamp(low, high)`` whose gradient does not die outside the range: a learned colour pushed past 0 or 1 (the
    table's forward-facing colour goes to black) gets the gradient that would bring it back, and none that would push
    it further out. Inside the range it is the identity, gradient included."""
    return _InwardClamp.apply(x, low, high)
