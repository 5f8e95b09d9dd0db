"""Rendering whole views and scoring them (kept out of the timed optimisation)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass

import torch

from nerfmeta.data.scene import RayBatch, Scene
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


CPU_CHUNK_RAYS = 1024
"""Most rays a test-time render chunk holds on a CPU: a small chunk's intermediates stay in the cores' caches,
and worker threads each render whole chunks. Two-core CPU, two threads, against 16384-ray chunks with
two-threaded operators: beer 180 x 320 (138 samples per ray) 2.1x the rays per second, lego 100 x 100
(24 samples per ray) 0.9-1.4x; 256 or 2048 rays were slower on one or the other (BENCHMARKS.md,
*Small chunks on every core*)."""


@contextmanager
def single_threaded_ops() -> Iterator[None]:
    """Run torch's CPU operators on one thread each while the block runs (restored after): the render's
    worker threads then share the cores among chunks, not the operators of one small chunk."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def render_rays(
    model: RadianceModel, rays: RayBatch, background: torch.Tensor, *, chunk: int = 16384, workers: int | None = None
) -> tuple[torch.Tensor, int]:
    """Render ``rays`` (no jitter) in chunks: (n_rays, 3) colours and the samples evaluated.

    On a GPU the chunks hold ``chunk`` rays and run one after another. On a CPU they hold at most
    :data:`CPU_CHUNK_RAYS` rays and ``workers`` threads (default: torch's thread count) render them, each
    operator on one thread: small chunks stay in cache, and threads over chunks keep every core busy where
    one chunk's small operators would not. Every ray is rendered on its own, so the colours do not depend
    on the chunking.
    """
    grad, workers = torch.is_grad_enabled(), max(1, workers or torch.get_num_threads())

    def one(start: int, size: int) -> tuple[torch.Tensor, int]:
        with torch.set_grad_enabled(grad):  # grad mode is per thread
            out = model(rays[start : start + size], background=background, train=False)
        return out.rgb, out.samples_evaluated

    with model.render_session():
        if background.device.type != "cpu":
            parts = [one(start, chunk) for start in range(0, len(rays), chunk)]
        else:
            size = min(chunk, CPU_CHUNK_RAYS)
            with single_threaded_ops(), ThreadPoolExecutor(workers) as pool:
                parts = list(pool.map(lambda start: one(start, size), range(0, len(rays), size)))
    return torch.cat([rgb for rgb, _ in parts]), sum(count for _, count in parts)


def strided_pixels(size: int, stride: int) -> range:
    """The pixel rows (or columns) of ``size`` that :func:`render_view` renders at ``stride``: every ``stride``-th, from ``stride // 2``."""
    return range(stride // 2, size, stride)


def strided_rays(n_views: int, height: int, width: int, stride: int) -> int:
    """Rays :func:`render_view` renders for ``n_views`` views of ``height`` x ``width`` at ``stride``."""
    return n_views * len(strided_pixels(height, stride)) * len(strided_pixels(width, stride))


def pixel_stride(n_views: int, height: int, width: int, max_rays: int) -> int:
    """The smallest stride ``s`` at which every ``s``-th pixel row and column of ``n_views`` views of ``height`` x
    ``width`` holds at most ``max_rays`` rays in all (1: every pixel; also for ``max_rays`` 0, no limit), but never
    less than one pixel a view."""
    s = 1
    while max_rays > 0 and s < max(height, width) and strided_rays(n_views, height, width, s) > max_rays:
        s += 1
    return s


@torch.no_grad()
def render_view(
    model: RadianceModel, scene: Scene, view: int, background: torch.Tensor, *, chunk: int = 16384, stride: int = 1
) -> ViewRender:
    """Render ``view`` (no jitter) through :func:`render_rays` (``chunk``: most rays at once): every pixel, or with
    ``stride`` s > 1 the pixels of every s-th row and column (from ``s // 2``), a regular sample of the view."""
    rays = view_rays(scene, view, background.device)
    h, w = scene.height, scene.width
    if stride > 1:
        rows, cols = (torch.tensor(strided_pixels(n, stride)) for n in (h, w))
        rays = rays[(rows[:, None] * w + cols[None, :]).reshape(-1).to(rays.origins.device)]
        h, w = len(rows), len(cols)
    rgb, samples = render_rays(model, rays, background, chunk=chunk)
    return ViewRender(view, rgb.clamp(0, 1).reshape(h, w, 3).cpu(), rays.target.reshape(h, w, 3).cpu(), samples / len(rays))


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
    view_psnrs: tuple[float, ...] = ()
    """Each view's PSNR, in the order rendered (``psnr`` is their mean)."""


def evaluate_views(
    model: RadianceModel,
    scene: Scene,
    views: list[int],
    background: torch.Tensor,
    *,
    with_ssim: bool = True,
    chunk: int = 16384,
    lpips_model: torch.nn.Module | None = None,
    on_view: Callable[[int, int], None] | None = None,
    stride: int = 1,
) -> EvalResult:
    """Render ``views`` and score them against the ground truth (LPIPS too with ``lpips_model``, see
    :func:`nerfmeta.metrics.load_lpips`). ``on_view(done, total)`` is called before the first view and after each.
    ``stride`` > 1 scores every ``stride``-th pixel row and column of each view (:func:`render_view`)."""
    was_training = model.training
    model.eval()
    renders: list[ViewRender] = []
    try:
        with model.render_session():  # the views share what the model keeps per render (e.g. the grid's copies)
            for v in views:
                if on_view is not None:
                    on_view(len(renders), len(views))
                renders.append(render_view(model, scene, v, background, chunk=chunk, stride=stride))
            if on_view is not None:
                on_view(len(renders), len(views))
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
        renders=tuple(renders),
        lpips=None if lpipses is None else sum(lpipses) / len(lpipses),
        view_psnrs=tuple(psnrs),
    )
