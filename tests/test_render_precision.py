"""Float32 rendering and its gradient stay close to a float64 reference, adversarial cases included.

Each case builds optical-depth inputs, renders colour with :func:`render_weights` and
:func:`composite` in float32 and in float64, and compares the colour and its gradient with respect
to density and colour. The error is relative to the scale of the reference (max |ref|, at least a
small floor), so cases whose exact values are zero still measure a meaningful error.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import pytest
import torch

from nerfmeta.render.volume import composite, render_weights


@dataclass(frozen=True)
class PrecisionCase:
    """Inputs of one case: sigma and delta (n_rays, n_samples) non-negative, colours (n_rays, n_samples, 3)."""

    name: str
    sigma: torch.Tensor
    delta: torch.Tensor
    colors: torch.Tensor


@dataclass(frozen=True)
class PrecisionResult:
    name: str
    rgb_rel_error: float
    grad_sigma_rel_error: float
    grad_color_rel_error: float
    finite: bool

    @property
    def worst(self) -> float:
        return max(self.rgb_rel_error, self.grad_sigma_rel_error, self.grad_color_rel_error)


def _render(sigma, delta, colors):
    w, t_final = render_weights(sigma * delta)
    return composite(w, colors, t_final, torch.ones(3, dtype=sigma.dtype))


def _rel(a: torch.Tensor, ref: torch.Tensor, floor: float = 1e-6) -> float:
    scale = max(float(ref.abs().max()), floor)
    return float((a.double() - ref).abs().max()) / scale


def compare_precision(case: PrecisionCase) -> PrecisionResult:
    """Render one case in float32 and float64 and measure the relative errors."""
    outs = {}
    for dtype in (torch.float32, torch.float64):
        sigma = case.sigma.to(dtype).requires_grad_()
        colors = case.colors.to(dtype).requires_grad_()
        rgb = _render(sigma, case.delta.to(dtype), colors)
        # a fixed, non-trivial upstream gradient so every output element matters
        upstream = torch.linspace(0.5, 1.5, rgb.numel(), dtype=dtype).view_as(rgb)
        g_sigma, g_color = torch.autograd.grad((rgb * upstream).sum(), (sigma, colors))
        outs[dtype] = (rgb.detach(), g_sigma, g_color)
    f32, f64 = outs[torch.float32], outs[torch.float64]
    finite = all(bool(torch.isfinite(t).all()) for t in f32)
    return PrecisionResult(case.name, _rel(f32[0], f64[0]), _rel(f32[1], f64[1]), _rel(f32[2], f64[2]), finite)


def standard_cases(seed: int = 0) -> list[PrecisionCase]:
    """Random rays plus adversarial ones: huge densities, tiny and huge intervals, long rays, a wall."""
    g = torch.Generator().manual_seed(seed)

    def rand(*shape):
        return torch.rand(*shape, generator=g, dtype=torch.float64)

    def log_uniform(lo, hi, *shape):
        return torch.exp(torch.empty(*shape, dtype=torch.float64).uniform_(lo, hi, generator=g))

    n, s = 128, 64
    cases: list[tuple[str, Callable[[], tuple]]] = [
        ("random", lambda: (log_uniform(-7, 7, n, s), log_uniform(-7, 0, n, s))),
        ("huge densities (1e6)", lambda: (torch.full((n, s), 1e6, dtype=torch.float64) * rand(n, s), torch.full((n, s), 1e-3, dtype=torch.float64))),
        ("tiny intervals (1e-10)", lambda: (log_uniform(-3, 3, n, s), torch.full((n, s), 1e-10, dtype=torch.float64))),
        ("huge intervals (1e10)", lambda: (log_uniform(-3, 3, n, s), torch.full((n, s), 1e10, dtype=torch.float64))),
        ("long rays (1024 samples)", lambda: (log_uniform(-8, 0, n, 1024), torch.full((n, 1024), 1e-2, dtype=torch.float64))),
        ("opaque wall after empty space", lambda: (torch.cat([torch.zeros(n, s - 4, dtype=torch.float64), torch.full((n, 4), 1e4, dtype=torch.float64)], 1),
                                                   torch.full((n, s), 0.01, dtype=torch.float64))),
        ("zero-length intervals", lambda: (log_uniform(-3, 3, n, s), torch.zeros(n, s, dtype=torch.float64))),
    ]
    out = []
    for name, make in cases:
        sigma, delta = make()
        colors = rand(sigma.shape[0], sigma.shape[1], 3)
        out.append(PrecisionCase(name, sigma, delta, colors))
    return out


CASES = standard_cases()


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_float32_close_to_float64(case):
    result = compare_precision(case)
    assert result.finite
    assert result.rgb_rel_error < 1e-5, result
    assert result.grad_color_rel_error < 1e-5, result
    assert result.grad_sigma_rel_error < 1e-4, result
