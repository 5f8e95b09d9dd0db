"""Forward-facing fits: NDC against today's bounded grid on the generated LLFF-layout scene (issue 16).

Workload: the scene of :mod:`nerfmeta.collection.forward` (20 views of 160 x 120 by default,
every 8th, 0, 8, 16, held out: 17 training and 3 test views), written once into a temporary
folder. Two arms, each ``nerfmeta fit SCENE --init scratch --time-budget BUDGET --eval-every 0
--checkpoint-every 0 --seed K``: ``ndc`` (the scene detected as forward: rays in NDC) and
``bounded`` (``--scene-type object``: world rays in the bounded box, as before NDC); ``--arms`` picks
others (``ndc-0.75``: NDC with NeRF's near plane, to compare near-plane factors). Arms are
interleaved (ndc, bounded, ndc, bounded, ...) so the machine's load falls on both; each fit is a
fresh process. After each fit the test views are rendered again from its checkpoint and timed
(rays per second of the rendering alone), and the renders are kept for looking at with ``--keep``.

Usage::

    flock /work/wt/bench.lock .venv/bin/python scripts/bench_forward.py [--reps 3] [--budget 60]
        [--width 160 --height 120] [--layout-seed 0 --scene-seed 0 --wall-distance 16 --grid 5 4 --spacing 0.15]
        [--keep DIR] [--set KEY=VALUE ...] [--ndc-set KEY=VALUE ...] [--arms ndc,bounded]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import nerfmeta  # noqa: E402,F401 - before torch, which then spins its OpenMP workers briefly (nerfmeta/__init__.py)
import torch

from nerfmeta.collection.forward import ForwardSceneConfig, make_forward_scene
from nerfmeta.data import load_scene
from nerfmeta.fit.evaluate import render_view
from nerfmeta.fit.restore import load_fitted_run

ARMS = {"ndc": ["--scene-type", "auto"], "bounded": ["--scene-type", "object"],
        "ndc-0.75": ["--scene-type", "auto", "--ndc-near-factor", "0.75"],
        "ndc-tiles": ["--scene-type", "auto", "--holdout-scene-types", "object,forward"],
        "ndc-1march": ["--scene-type", "auto", "--set", "render_phases=1"],
        "ndc-randombg": ["--scene-type", "auto", "--random-background", "forward"]}
"""Arms by name: the default route (NDC with the default near plane, every pixel trained on), the bounded grid, NDC
with NeRF's near plane at 0.75 x the near bound (the default before session 7), NDC with held-out tiles and their
early stop (session 44's default for fits of at most 20 views, which session 45 measured losing on these scenes), and
NDC with its test views rendered by one march at the bins' middles (``render_phases`` 1, the default before session
46; with ``--iters`` its fits are step for step those of ``ndc``, so only the test renders differ), and NDC trained on
random background colours (``--random-background forward``, session 47: not the default)."""


def fit_once(scene: Path, out: Path, arm: str, args: argparse.Namespace, seed: int) -> dict:
    """One fit in a fresh process; its summary plus the load average before it."""
    load = " / ".join(f"{v:.1f}" for v in os.getloadavg())
    cmd = [sys.executable, "-m", "nerfmeta", "fit", str(scene), "--out", str(out), "--init", "scratch",
           *(["--iters", str(args.iters)] if args.iters else ["--time-budget", f"{args.budget:g}"]),
           "--eval-every", "0", "--checkpoint-every", "0", "--seed", str(seed),
           *ARMS[arm], *sum((["--set", s] for s in args.set), []),
           *(sum((["--set", s] for s in args.ndc_set), []) if arm.startswith("ndc") else [])]
    with open(out.with_suffix(".log"), "w") as log:
        proc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT)
    if proc.returncode != 0:
        raise SystemExit(f"bench_forward: {arm} seed {seed} failed (exit {proc.returncode}); see {out.with_suffix('.log')}")
    return {**json.loads((out / "summary.json").read_text()), "load": load}


@torch.no_grad()
def render_speed(run: Path) -> tuple[float, list[np.ndarray]]:
    """Rays per second rendering the test views of a fitted run from its checkpoint, and the renders (H, W, 3)."""
    fitted = load_fitted_run(run, "cpu")
    scene, model = fitted.scene, fitted.model
    background = torch.tensor(fitted.config.background, dtype=torch.float32)
    views = scene.split_indices("test").tolist()
    start = time.perf_counter()
    renders = [render_view(model, scene, v, background) for v in views]
    seconds = time.perf_counter() - start
    return len(views) * scene.height * scene.width / seconds, [r.rgb.numpy() for r in renders]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--budget", type=float, default=60.0)
    parser.add_argument("--iters", type=int, default=0,
                        help="stop every fit after this many steps instead of --budget seconds (0: the budget); a fit "
                             "stopped by steps is deterministic for its seed, so the PSNRs do not depend on the load")
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--layout-seed", type=int, default=0, help="the scene's object layout (0: the fixed one)")
    parser.add_argument("--scene-seed", type=int, default=0, help="the scene's camera jitter seed")
    parser.add_argument("--wall-distance", type=float, default=ForwardSceneConfig.wall_distance)
    parser.add_argument("--grid", type=int, nargs=2, default=ForwardSceneConfig.grid, metavar=("ACROSS", "UP"))
    parser.add_argument("--spacing", type=float, default=ForwardSceneConfig.spacing)
    parser.add_argument("--keep", type=Path, default=None, help="write each run's test renders here (PNG)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="backbone override for both arms")
    parser.add_argument("--ndc-set", action="append", default=[], metavar="KEY=VALUE",
                        help="backbone override for the ndc arm only (e.g. a regulariser tried against the bounded grid)")
    parser.add_argument("--arms", default="ndc,bounded", help=f"comma-separated arms, interleaved ({', '.join(ARMS)})")
    args = parser.parse_args()
    arms = args.arms.split(",")
    unknown = [a for a in arms if a not in ARMS]
    if unknown:
        parser.error(f"--arms: unknown arm {unknown[0]!r} (choose from {', '.join(ARMS)})")
    results: dict[str, list[dict]] = {arm: [] for arm in arms}
    with tempfile.TemporaryDirectory(prefix="bench_forward_") as tmp:
        layout = ForwardSceneConfig(width=args.width, height=args.height, seed=args.scene_seed, layout_seed=args.layout_seed,
                                    wall_distance=args.wall_distance, grid=tuple(args.grid), spacing=args.spacing)
        scene = make_forward_scene(Path(tmp) / "scene", layout)
        for k in range(args.reps):
            for arm in arms:
                run = Path(tmp) / f"{arm}{k}"
                r = fit_once(scene, run, arm, args, k)
                r["rays_per_s"], renders = render_speed(run)
                results[arm].append(r)
                if args.keep is not None:
                    args.keep.mkdir(parents=True, exist_ok=True)
                    truth = load_scene(scene).subset("test").images.numpy()
                    strip = np.concatenate([np.concatenate([t, p], 1) for t, p in zip(truth, renders)], 0)
                    iio.imwrite(args.keep / f"{arm}_seed{k}.png", (strip * 255 + 0.5).astype(np.uint8))
                print(f"{arm} seed {k}: {r['test_psnr']:.2f} dB, {r['iters']} iters, {r['samples_per_ray']:.1f} samples/ray, "
                      f"{r['rays_per_s']:.0f} rays/s rendering, load before {r['load']}", flush=True)
    print(f"\nscene: {layout}")
    print(f"{args.reps} runs per arm, interleaved; {args.width} x {args.height}; "
          f"{f'{args.iters} steps' if args.iters else f'budget {args.budget:g} s'}; "
          f"{datetime.date.today().isoformat()}; load average now {' / '.join(f'{v:.1f}' for v in os.getloadavg())}\n")
    print("| figure | " + " | ".join(f"{a} median (min-max)" for a in arms) + " |")
    print("|---|" + "---|" * len(arms))
    for key, label, digits in (("test_psnr", "test PSNR (dB)", 2), ("iters", "iterations", 0), ("time_s", "fit seconds", 1),
                               ("samples_per_ray", "samples per ray (test)", 1), ("rays_per_s", "test rendering (rays/s)", 0),
                               ("peak_rss_mb", "peak RSS (MB)", 0)):
        cells = []
        for runs in results.values():
            values = [float(r[key]) for r in runs]
            cells.append(f"{statistics.median(values):.{digits}f} ({min(values):.{digits}f}-{max(values):.{digits}f})")
        print(f"| {label} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
