"""Test-view rendering speed of a trained fit run (rays per second), recorded in BENCHMARKS.md.

Loads a fit run folder (its ``config.json`` and ``checkpoint.safetensors``), the scene at the run's
downscale, and renders every test view through :func:`nerfmeta.fit.evaluate.evaluate_views` (the
path of the final evaluation and of videos), timing each view on its own. Prints the rays per
second of every view, their median, the test PSNR and the samples evaluated per ray. With
``--profile`` it also prints the torch profiler's table of the first view's hot spots.

Usage::

    .venv/bin/python scripts/bench_render.py RUN [--views N] [--profile] [--chunk N] [--stop-eps X] [--phases N]
        [--orbit N --out DIR] [--weights] [--device DEV]

Renders use torch's thread count (one worker thread per torch thread on a CPU, see
:func:`nerfmeta.fit.evaluate.render_rays`); ``OMP_NUM_THREADS=1`` measures one core, as sessions 5-8 did.

With ``--weights`` it also prints, for the first test view, how the samples' alphas and compositing
weights are spread (what decides how many samples must be coloured and whether early termination pays).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import nerfmeta  # noqa: E402,F401 - before torch, which then spins its OpenMP workers briefly (nerfmeta/__init__.py)
import torch  # noqa: E402

from nerfmeta.errors import ConfigError  # noqa: E402
from nerfmeta.fit.evaluate import evaluate_views  # noqa: E402
from nerfmeta.fit.restore import load_fitted_run  # noqa: E402


def load_run(folder: Path, device: str = "cpu"):
    """The run's config, scene and trained model (on ``device``)."""
    fitted = load_fitted_run(folder, device)
    return fitted.config, fitted.scene, fitted.model


def orbit_pose(pose: torch.Tensor, centre: torch.Tensor, up: torch.Tensor, angle: float) -> torch.Tensor:
    """(4, 4) ``pose`` turned by ``angle`` radians about the axis ``up`` (3,) through ``centre`` (3,)."""
    k = up / up.norm()
    kx = torch.tensor([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]], dtype=pose.dtype)
    rot = torch.eye(3, dtype=pose.dtype) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx  # Rodrigues
    out = pose.clone()
    out[:3, :3] = rot @ pose[:3, :3]
    out[:3, 3] = rot @ (pose[:3, 3] - centre) + centre
    return out


def write_orbit(model, scene, background: torch.Tensor, frames: int, folder: Path) -> None:
    """Render ``frames`` views of the first test camera turned about the cameras' mean up axis through the
    scene's centre (the inner box's centre for a contracted grid, else the bounds' centre); write PNGs."""
    import imageio.v3 as iio

    from nerfmeta.fit.evaluate import render_view

    folder.mkdir(parents=True, exist_ok=True)
    view = int(scene.split_indices("test")[0])
    box = getattr(model, "box", None)
    centre = torch.tensor(box.centre, dtype=scene.poses.dtype) if box is not None else scene.bounds.mean(0).to(scene.poses.dtype)
    up = scene.poses[:, :3, 1].mean(0)
    for k in range(frames):
        pose = orbit_pose(scene.poses[view], centre, up, 2 * math.pi * k / frames)
        moved = dataclasses.replace(scene, poses=torch.cat([pose[None], scene.poses[1:]]) if view == 0 else scene.poses)
        rgb = render_view(model, moved, 0 if view == 0 else view, background).rgb
        iio.imwrite(folder / f"orbit_{k:03d}.png", (rgb.clamp(0, 1) * 255).round().to(torch.uint8).numpy())


@torch.no_grad()
def weight_spread(model, scene, view: int, chunk: int, device: str = "cpu") -> str:
    """One line: the share of the samples of ``view``'s pixel rays by alpha and by compositing weight, and the
    mean transmittance left behind the last sample (a haze leaves much, an opaque scene little)."""
    from nerfmeta.fit.evaluate import view_rays
    from nerfmeta.render.volume import alpha_from_tau, packed_weights

    rays = view_rays(scene, view, device)
    alphas, weights, finals = [], [], []
    for start in range(0, len(rays), chunk):
        batch = rays[start : start + chunk]
        samples = model.sample(batch, train=False, generator=None).samples
        tau = model.get_density(samples.points(batch.origins, batch.directions))[0] * samples.delta
        w, t_final = packed_weights(tau, samples.ray_idx, len(batch))
        alphas.append(alpha_from_tau(tau))
        weights.append(w)
        finals.append(t_final)
    a, w, t = torch.cat(alphas), torch.cat(weights), torch.cat(finals)
    return (f"view {view}: {len(a) / len(t):.1f} samples/ray; alpha < 1e-3: {(a < 1e-3).float().mean():.1%}, "
            f"< 1e-2: {(a < 1e-2).float().mean():.1%}; weight > 1e-3: {(w > 1e-3).float().mean():.1%}; "
            f"mean final transmittance {t.mean():.3f}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a fit run folder with a checkpoint")
    parser.add_argument("--views", type=int, default=0, help="render only the first N test views (0: all)")
    parser.add_argument("--chunk", type=int, default=0, help="most rays per chunk (0: the run's chunk_rays; a CPU also caps it at CPU_CHUNK_RAYS)")
    parser.add_argument("--profile", action="store_true", help="print the torch profiler's table for the first view")
    parser.add_argument("--stop-eps", type=float, default=None,
                        help="grid: test-time early termination threshold (0: the one-pass path without it; default: the run's)")
    parser.add_argument("--phases", type=int, default=None,
                        help="grid: marches a test render averages (render_phases; default: the run's)")
    parser.add_argument("--orbit", type=int, default=0, help="also write N frames orbiting the scene's centre to --out")
    parser.add_argument("--out", type=Path, default=None, help="folder for the orbit frames (PNG)")
    parser.add_argument("--weights", action="store_true",
                        help="also print the spread of the first test view's sample alphas and weights")
    parser.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default cpu)")
    args = parser.parse_args(argv)
    try:
        config, scene, model = load_run(args.run, args.device)
        if args.stop_eps is not None:
            model.config = dataclasses.replace(model.config, render_stop_eps=args.stop_eps)
        if args.phases is not None:
            if not hasattr(model.config, "render_phases"):
                raise ConfigError(f"--phases {args.phases}: only a grid run averages marches ({args.run} is not one)")
            model.config = dataclasses.replace(model.config, render_phases=args.phases)
    except ConfigError as err:
        print(f"bench_render: error: {err}", file=sys.stderr)
        return 2
    if args.orbit:
        write_orbit(model, scene, torch.tensor(config.background, dtype=torch.float32, device=args.device), args.orbit, args.out)
    views = scene.split_indices("test")
    views = views[: args.views] if args.views else views
    background = torch.tensor(config.background, dtype=torch.float32, device=args.device)
    chunk = args.chunk or config.fit.chunk_rays
    if args.profile:
        from torch.profiler import ProfilerActivity, profile

        with profile(activities=[ProfilerActivity.CPU]) as prof:
            evaluate_views(model, scene, [views[0]], background, with_ssim=False, chunk=chunk)
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))
    if args.weights:
        print(weight_spread(model, scene, int(views[0]), chunk, args.device))
    rates, psnrs, spr = [], [], []
    for view in views:
        start = time.perf_counter()
        result = evaluate_views(model, scene, [view], background, with_ssim=False, chunk=chunk)
        seconds = time.perf_counter() - start
        rays = scene.height * scene.width
        rates.append(rays / seconds)
        psnrs.append(result.psnr)
        spr.append(result.samples_per_ray)
        print(f"view {view}: {rays} rays in {seconds:.2f} s = {rays / seconds:,.0f} rays/s, "
              f"{result.psnr:.2f} dB, {result.samples_per_ray:.1f} samples/ray")
    print(f"median {statistics.median(rates):,.0f} rays/s over {len(rates)} views ({scene.height}x{scene.width}); "
          f"mean PSNR {statistics.fmean(psnrs):.2f} dB; {statistics.fmean(spr):.1f} samples/ray")
    return 0


if __name__ == "__main__":
    sys.exit(main())
