"""The default route against the scratch grid under one time budget (issue 14), recorded in BENCHMARKS.md.

Workload: for each scene, ``nerfmeta fit SCENE --out RUN --time-budget BUDGET --eval-every 0 --checkpoint-every 0
--seed K`` as a newcomer types it (``--init auto``, the shipped zoo) against the same command with ``--init scratch
--backbone grid``, each a fresh process, arms interleaved and their order swapped every run so that the machine's
load falls on both. The scenes: lego at ``--downscale 8`` (100 x 100) and ``../shared/data/real/beer`` at
``--downscale 4`` (180 x 320), the two the issue names, and two the project never fitted before, generated into a
temporary folder: a forward-facing scene (:mod:`nerfmeta.collection.forward`, a layout and camera seed no other
benchmark uses) and a 128 px object of a fresh collection seed (:mod:`nerfmeta.collection.generate`).

Each run's ``summary.json`` gives the test PSNR on all test views, the route (and why) and the iterations; the script
prints every run, the median per arm and the target: the default's median within 0.1 dB of the scratch grid's, or
above it. ``--write`` replaces the ``## Default route against the scratch grid (issue 14)`` section.

Usage::

    .venv/bin/python scripts/bench_default_route.py [--reps 3] [--budget 60] [--scenes lego,beer,forward,object]
        [--write]
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
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

SECTION = "## Default route against the scratch grid (issue 14)"
MACHINE = "2-core CPU (AMD EPYC), no GPU"
SHARED = ROOT.parent / "shared" / "data"
ARMS = {"default": [], "scratch grid": ["--init", "scratch", "--backbone", "grid"]}
"""Arms by name: what a newcomer types, and the best scratch fit."""
TOLERANCE_DB = 0.1
FORWARD_SEEDS = (5, 5)
"""(layout, camera) seeds of the generated forward-facing scene: no other benchmark or test uses them."""
OBJECT = ("table", 2027, 128)
"""(category, collection seed, pixels) of the generated object scene: a seed no collection here was made with."""


def make_scenes(names: list[str], tmp: Path) -> dict[str, tuple[Path, float, str]]:
    """name -> (scene folder, downscale, what it is), generating the unseen scenes into ``tmp``."""
    scenes = {}
    for name in names:
        if name == "lego":
            scenes[name] = (SHARED / "nerf_synthetic" / "lego", 8.0, "lego, `--downscale 8` (100 x 100)")
        elif name == "beer":
            scenes[name] = (SHARED / "real" / "beer", 4.0, "beer, `--downscale 4` (180 x 320)")
        elif name == "forward":
            from nerfmeta.collection.forward import ForwardSceneConfig, make_forward_scene

            config = ForwardSceneConfig(layout_seed=FORWARD_SEEDS[0], seed=FORWARD_SEEDS[1])
            folder = make_forward_scene(tmp / "forward", config)
            scenes[name] = (folder, 1.0, f"generated forward-facing (layout {FORWARD_SEEDS[0]}, cameras {FORWARD_SEEDS[1]}; "
                                         f"{config.width} x {config.height}, unseen)")
        elif name == "object":
            from nerfmeta.collection.generate import CollectionConfig, generate_collection, load_collection

            category, seed, pixels = OBJECT
            config = CollectionConfig(categories=(category,), scenes_per_category=1, views=32, test_views=8, resolution=pixels,
                                      seed=seed, val_fraction=0.0, test_fraction=0.0)
            generate_collection(config, tmp / "object", overwrite=True)
            coll = load_collection(tmp / "object" / "collection.json")
            scenes[name] = (coll.scene_path(coll.scenes[0]), 1.0,
                            f"generated {category} (collection seed {seed}, {pixels} x {pixels}, 32 + 8 views, unseen)")
        else:
            raise SystemExit(f"--scenes: unknown scene {name!r} (lego, beer, forward, object)")
        if not scenes[name][0].exists():
            raise SystemExit(f"{scenes[name][0]}: not found (the shared reference data)")
    return scenes


def load_average() -> str:
    """The 1 / 5 / 15 minute load averages, as the tables print them."""
    return " / ".join(f"{v:.1f}" for v in os.getloadavg())


def fit_once(scene: Path, downscale: float, out: Path, arm: str, budget: float, seed: int) -> dict:
    """One fit in a fresh process: its summary, with the load average before it."""
    load = load_average()
    cmd = [sys.executable, "-m", "nerfmeta", "fit", str(scene), "--out", str(out), "--downscale", f"{downscale:g}",
           "--time-budget", f"{budget:g}", "--eval-every", "0", "--checkpoint-every", "0", "--seed", str(seed), *ARMS[arm]]
    with open(out.with_suffix(".log"), "w") as log:
        proc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT)
    if proc.returncode != 0:
        raise SystemExit(f"bench_default_route: {arm} on {scene} seed {seed} failed (exit {proc.returncode}); "
                         f"see {out.with_suffix('.log')}")
    return {**json.loads((out / "summary.json").read_text()), "load": load}


def route_of(summary: dict) -> str:
    """What the run started from, and why, from its summary."""
    route = summary.get("route")
    if not route:
        return f"{summary.get('init', 'scratch')} (no routing)"
    return f"{route['route']} ({route.get('backbone')}): {route.get('reason', '')}"


def verdict(default: list[float], scratch: list[float]) -> tuple[float, str]:
    """(median difference default - scratch, whether the target is met) (pure)."""
    diff = statistics.median(default) - statistics.median(scratch)
    return diff, "met" if diff >= -TOLERANCE_DB else "**missed**"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--budget", type=float, default=60.0)
    p.add_argument("--scenes", default="lego,beer,forward,object")
    p.add_argument("--write", action="store_true")
    args = p.parse_args(argv)
    rows, runs_lines, routes = [], [], {}
    load_before = load_average()
    with tempfile.TemporaryDirectory(prefix="bench_default_route_") as tmp:
        scenes = make_scenes(args.scenes.split(","), Path(tmp))
        for name, (scene, downscale, label) in scenes.items():
            results: dict[str, list[dict]] = {arm: [] for arm in ARMS}
            for k in range(args.reps):
                for arm in (list(ARMS) if k % 2 == 0 else list(ARMS)[::-1]):
                    r = fit_once(scene, downscale, Path(tmp) / f"{name}_{arm.replace(' ', '_')}{k}", arm, args.budget, k)
                    results[arm].append(r)
                    line = (f"{name} {arm} seed {k}: {r['test_psnr']:.2f} dB, {r['iters']} iterations, "
                            f"route {(r.get('route') or {}).get('route', 'none')}; load before {r['load']}")
                    runs_lines.append(line)
                    print(line, flush=True)
            routes[name] = route_of(results["default"][0])
            psnr = {arm: [float(r["test_psnr"]) for r in rs] for arm, rs in results.items()}
            iters = {arm: statistics.median(int(r["iters"]) for r in rs) for arm, rs in results.items()}
            diff, met = verdict(psnr["default"], psnr["scratch grid"])
            cell = {arm: f"{statistics.median(v):.2f} ({min(v):.2f}-{max(v):.2f})" for arm, v in psnr.items()}
            rows.append(f"| {label} | {results['default'][0].get('route', {}).get('route', 'scratch')} | {cell['default']} | "
                        f"{cell['scratch grid']} | {iters['default']:.0f} / {iters['scratch grid']:.0f} | {diff:+.2f} dB, {met} |")
    lines = [
        SECTION, "",
        "```",
        f".venv/bin/python scripts/bench_default_route.py --reps {args.reps} --budget {args.budget:g} --scenes {args.scenes} --write",
        "```", "",
        f"Machine: {MACHINE}; date {datetime.date.today().isoformat()}; **median of {args.reps} runs** per arm (min-max in "
        f"brackets), seeds 0..{args.reps - 1}, arms interleaved with their order swapped every run; load average before "
        f"{load_before}, after {load_average()}. Default: `nerfmeta fit SCENE --out RUN "
        f"--downscale D --time-budget {args.budget:g} --eval-every 0 --checkpoint-every 0` with the shipped zoo; scratch: the same "
        "with `--init scratch --backbone grid`. Test PSNR on all test views.", "",
        "| scene | default route | test PSNR, default (dB) | test PSNR, scratch grid (dB) | iterations (default / scratch) | "
        f"target (default >= scratch - {TOLERANCE_DB:g} dB, medians) |",
        "|---|---|---|---|---|---|",
        *rows, "",
        "Where the default route is `scratch`, both arms run the same configuration and seed: the differences are how "
        "many iterations each process fitted into the budget (the route itself is decided before the budget starts; "
        "with no prior of the asked backbone it classifies nothing).", "",
        "Routes, as `summary.json[\"route\"]` records them:", "",
        *[f"- {name}: {text}" for name, text in routes.items()], "",
        "<details><summary>every run</summary>", "", *[f"    {line}" for line in runs_lines], "", "</details>", "",
    ]
    print("\n".join(lines))
    if args.write:
        from benchlib.sections import write_section

        write_section(ROOT / "BENCHMARKS.md", SECTION, "\n".join(lines))
        print(f"updated BENCHMARKS.md ({SECTION})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
