"""Input encodings (pure functions)."""

from __future__ import annotations

import torch


def positional_encoding(x: torch.Tensor, n_freqs: int, *, include_input: bool = True) -> torch.Tensor:
    """NeRF's frequency encoding ``[x, sin(2^k pi x), cos(2^k pi x)]`` for ``k < n_freqs``.

    Args:
        x: (..., D) inputs, ideally normalised to about [-1, 1].
        n_freqs: number of octaves (0 gives ``x`` alone, or an empty tensor without the input).

    Returns:
        (..., D * (include_input + 2 * n_freqs)).
    """
    parts = [x] if include_input else []
    if n_freqs > 0:
        freqs = (2.0 ** torch.arange(n_freqs, dtype=x.dtype, device=x.device)) * torch.pi
        xf = (x[..., None, :] * freqs[:, None]).flatten(-2)  # (..., n_freqs * D)
        parts += [torch.sin(xf), torch.cos(xf)]
    return torch.cat(parts, dim=-1) if parts else x[..., :0]


def encoding_dim(d: int, n_freqs: int, *, include_input: bool = True) -> int:
    """Output width of :func:`positional_encoding` for ``d`` inputs."""
    return d * (int(include_input) + 2 * n_freqs)


def normalize_to_box(points: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
    """Map points in the box ``bounds`` (2, 3) linearly to [-1, 1]^3. Points: (..., 3)."""
    centre = 0.5 * (bounds[0] + bounds[1])
    half = 0.5 * (bounds[1] - bounds[0])
    return (points - centre) / half
