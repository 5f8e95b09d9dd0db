"""Rendering whole views and scoring them (kept out of the timed optimisation)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from nerfmeta.data.scene import Scene
from nerfmeta.fields.base import RadianceModel
from nerfmeta.fit.sampler import view_rays
from nerfmeta.metrics import lpips, mse_to_psnr, ssim


@dataclass(frozen=True)
class ViewRender:
    """One rendered view: ``rgb`` (H, W, 3), ``target`` (H, W, 3), and samples evaluated per ray."""

    view: int
    rgb: torch.Tensor
    target: torch.Tensor
    samples_per_ray: float


@torch.no_grad()
def render_view(
    model: RadianceModel, scene: Scene, view: int, background: torch.Tensor, *, chunk: int = 16384
) -> ViewRender:
    """Render every pixel of ``view`` (no jitter), in chunks of rays."""
    device = background.device
    rays = view_rays(scene, view, device)
    rgbs, samples = [], 0
    for start in range(0, len(rays), chunk):
        out = model(rays[start : start + chunk], background=background, train=False)
        rgbs.append(out.rgb)
        samples += out.samples_evaluated
    h, w = scene.height, scene.width
    rgb = torch.cat(rgbs).clamp(0, 1).reshape(h, w, 3).cpu()
    return ViewRender(view, rgb, rays.target.reshape(h, w, 3).cpu(), samples / len(rays))


MSE_FLOOR = 1e-10
"""A view's MSE is floored here before conversion, so a perfect render reports 100 dB, not +inf (an
empty scene rendered exactly as its background does that; +inf would make ``summary.json`` invalid JSON
and every mean over views infinite)."""


@dataclass(frozen=True)
class EvalResult:
    """Mean PSNR/SSIM/LPIPS over the rendered views (PSNR of the mean MSE per view, floored at
    :data:`MSE_FLOOR`, averaged in dB); SSIM and LPIPS None where not computed."""

    psnr: float
    ssim: float | None
    samples_per_ray: float
    renders: tuple[ViewRender, ...]
    lpips: float | None = None


def evaluate_views(
    model: RadianceModel,
    scene: Scene,
    views: list[int],
    background: torch.Tensor,
    *,
    with_ssim: bool = True,
    chunk: int = 16384,
    lpips_model: torch.nn.Module | None = None,
) -> EvalResult:
    """Render ``views`` and score them against the ground truth (LPIPS too with ``lpips_model``, see
    :func:`nerfmeta.metrics.load_lpips`)."""
    was_training = model.training
    model.eval()
    try:
        renders = tuple(render_view(model, scene, v, background, chunk=chunk) for v in views)
    finally:
        model.train(was_training)
    psnrs = [float(mse_to_psnr(((r.rgb - r.target) ** 2).mean().clamp(min=MSE_FLOOR))) for r in renders]
    ssims = [float(ssim(r.rgb, r.target)) for r in renders] if with_ssim else None
    lpipses = [float(lpips(r.rgb, r.target, lpips_model)) for r in renders] if lpips_model is not None else None
    spr = sum(r.samples_per_ray for r in renders) / max(1, len(renders))
    return EvalResult(
        psnr=sum(psnrs) / len(psnrs),
        ssim=None if ssims is None else sum(ssims) / len(ssims),
        samples_per_ray=spr,
        renders=renders,
        lpips=None if lpipses is None else sum(lpipses) / len(lpipses),
    )
