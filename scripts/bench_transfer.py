"""Scratch vs category transfer vs meta-init fits on a generated collection; results into BENCHMARKS.md.

What it does (every fit through ``nerfmeta.fit.run.run_fit``, the code behind ``nerfmeta fit``):

1. Generates a collection (or reuses ``--collection``): 8 categories, 6 seen and 2 held out
   entirely (``--held-out``), ``SCENES`` scenes per category, each seen category with one test
   scene and the rest training scenes.
2. Pretrains one category model per seen category and backbone (``pretrain_category``).
3. Fits, per backbone, the *seen* group (the test scene of every seen category) from scratch and
   from its category model (first ``--freeze`` layers frozen), and the *unseen* group (the first
   scenes of the held-out categories) from scratch; with ``--meta DIR`` (a ``nerfmeta meta-train``
   folder, one per backbone) both groups also from the meta-initialisation. Controls on the first
   seen scenes: transfer from another category's model (``category-other``), scratch in the
   category models' canonical box instead of the scene's own box (``scratch-canonical``, the same
   files with ``aabb`` replaced), and transfer onto a black background from the white-background
   model (``category-black``, with scratch on black, ``scratch-black``, as its reference).
4. Optionally (``--freeze-sweep nerf,grid``) fits two seen scenes with every sensible ``--freeze K``.

Every fit of a scene uses the same backbone config, optimiser (Adam, the backbone's learning-rate
groups, exponential decay to 0.1x over the iterations), ray batch and seed; only the starting
point (and frozen layers) differ. The test PSNR (all test views) is taken at a dense schedule of
iterations by a callback outside the timed optimisation. The target of a scene is the test PSNR
scratch reaches at ``--iters`` (1000); each method's iterations and optimisation time to reach it
are the first scheduled evaluation at or above it.

Results: ``OUT/results.json``, plots in ``docs/bench/transfer_*.png`` and the
``## Transfer and meta-learning`` section of BENCHMARKS.md. Finished fits and category models are
cached in ``OUT``: a rerun with the same ``--out`` and settings reuses them (after a change to a
backbone's code, delete ``OUT/models/BACKBONE`` and ``OUT/fits/BACKBONE``).

Usage::

    .venv/bin/python scripts/bench_transfer.py --out runs/bench_transfer [--meta DIR ...] [--freeze-sweep nerf,grid]
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import multiprocessing
import os
import shutil
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # the pretrain/ package, when the checkout is not installed
    sys.path.insert(0, str(ROOT))

import nerfmeta  # noqa: E402,F401 - before torch, which then spins its OpenMP workers briefly (nerfmeta/__init__.py)
import torch  # noqa: E402

from benchlib.sections import write_section as write_benchmark_section  # noqa: E402
from nerfmeta.collection.generate import CollectionConfig, generate_collection, load_collection  # noqa: E402
from nerfmeta.data import load_scene  # noqa: E402
from nerfmeta.fit.evaluate import evaluate_views  # noqa: E402
from nerfmeta.fit.loop import FitConfig  # noqa: E402
from nerfmeta.fit.run import RunConfig, build_initial_model, run_fit  # noqa: E402
from nerfmeta.init import load_init  # noqa: E402
from pretrain.category import CANONICAL_BOX, CategoryPretrainConfig, pretrain_category  # noqa: E402

SECTION = "## Transfer and meta-learning"
MACHINE = "2-core CPU, no GPU"
CATEGORIES = ("airplane", "car", "chair", "lamp", "mug", "sofa", "table", "vase")
HELD_OUT = ("mug", "vase")
REPORT_ITERS = (25, 50, 100, 200, 500, 1000)
SCHEDULE = (1, 2, 3, 5, 8, 10, 15, 20, 25, 30, 40, 50, 60, 80, 100, 125, 150, 200, 250, 300, 400, 500, 600, 800, 1000)
"""Iterations at which the test PSNR is taken (and the final iteration)."""
EARLY_TARGET = 200
"""A second, earlier target: the PSNR scratch reaches at this iteration (how much faster the first phase is)."""

COLLECTION = CollectionConfig(categories=CATEGORIES, scenes_per_category=7, views=20, test_views=4, resolution=32,
                              seed=0, val_fraction=0.0, test_fraction=0.15)
"""7 scenes per category (1 test + 6 training for a seen category), 20 + 4 views at 32 x 32."""

BACKBONES: dict[str, dict[str, Any]] = {
    # NeRF MLP: 4 x 64 trunk, 32 samples, 6 position octaves; lr 1e-2, the best of 5e-4 / 2e-3 / 5e-3 / 1e-2 for
    # *scratch* on 400-iteration sweeps, so the baseline is not handicapped (at the paper's 5e-4 scratch stays near
    # the empty-white-image PSNR for hundreds of iterations). alpha_init 1e-3 instead of 1e-2: with the default
    # initial haze, scratch fits of thin objects (airplanes) collapse to the empty scene at any lr >= 3e-3.
    "nerf": {"model": {"depth": 4, "width": 64, "skips": [2], "n_samples": 32, "pos_freqs": 6, "alpha_init": 1e-3,
                       "lr": 1e-2},
             "batch_rays": 256, "pretrain_iters": 800, "freeze": 0, "sweep": (0, 2, 4, 5, 7)},
    # Voxel grid: 32^3 fine grid (a voxel is about a pixel footprint at 32 px), 100 coarse steps on 20^3, growth at
    # 50/100 fine steps. Category models use the same recipe (coarse stage included) on the merged scenes.
    "grid": {"model": {"num_voxels": 32**3, "coarse_iters": 100, "coarse_num_voxels": 20**3, "growth_steps": [50, 100],
                       "mlp_width": 32, "mlp_depth": 3},
             "batch_rays": 512, "pretrain_iters": 500, "freeze": 0, "sweep": (0, 1, 2)},
}


@dataclass(frozen=True)
class FitJob:
    """One fit of the benchmark."""

    backbone: str
    group: str
    method: str
    scene_name: str
    category: str
    scene: str
    init: str
    freeze: int
    model: dict[str, Any]
    batch_rays: int
    iters: int
    background: tuple[float, float, float]
    out: str


@dataclass(frozen=True)
class PretrainJob:
    backbone: str
    category: str
    collection: str
    model: dict[str, Any]
    batch_rays: int
    iters: int
    out: str


@dataclass
class Plan:
    pretrain: list[PretrainJob] = field(default_factory=list)
    fits: list[FitJob] = field(default_factory=list)


# ---------------------------------------------------------------------------------------------
# Workers (one torch thread each)


def _worker_init() -> None:
    torch.set_num_threads(1)


CACHED = "cached"


def run_pretrain(job: PretrainJob) -> dict[str, Any]:
    config = CategoryPretrainConfig(collection=job.collection, category=job.category, backbone=job.backbone,
                                    model=job.model, fit=FitConfig(iters=job.iters, batch_rays=job.batch_rays,
                                                                   eval_every=0, checkpoint_every=0))
    done, saved_config = Path(job.out) / "init.json", Path(job.out) / "config.json"
    if done.exists() and json.loads(saved_config.read_text())["fit"] == json.loads(json.dumps(dataclasses.asdict(config.fit))) \
            and {k: v for k, v in json.loads(saved_config.read_text())["model"].items() if k in job.model} == job.model:
        return {**json.loads(done.read_text())["meta"], CACHED: True}  # same recipe
    return pretrain_category(config, job.out, overwrite=True)


class ScheduledEval:
    """Callback: test PSNR on all test views at the scheduled iterations (outside the timed optimisation)."""

    def __init__(self, scene, background: torch.Tensor):
        self.scene, self.background = scene, background
        self.views = list(scene.splits["test"])
        self.points: list[dict[str, float]] = []

    def __call__(self, record, model, state) -> None:
        if record.iter not in SCHEDULE:
            return
        psnr = record.test_psnr  # the loop's own final evaluation (all test views) at the last iteration
        if psnr is None:
            psnr = evaluate_views(model, self.scene, self.views, self.background, with_ssim=False).psnr
        self.points.append({"iter": record.iter, "time_s": record.time_s, "psnr": psnr, "train_psnr": record.train_psnr})


def run_fit_job(job: FitJob) -> dict[str, Any]:
    result_path = Path(job.out) / "bench.json"
    init_sha = None if job.init == "scratch" else json.loads((Path(job.init.partition(":")[2]) / "init.json").read_text())["sha256"]
    if result_path.exists():
        cached = json.loads(result_path.read_text())
        if cached["job"] == json.loads(json.dumps(dataclasses.asdict(job))) and cached.get("init_sha256") == init_sha:
            return {**cached, CACHED: True}
    scene = load_scene(job.scene, background=job.background)
    background = torch.tensor(job.background, dtype=torch.float32)
    evaluator = ScheduledEval(scene, background)
    config = RunConfig(scene=job.scene, backbone=job.backbone, model=job.model, init=job.init, freeze=job.freeze,
                       background=job.background,
                       fit=FitConfig(iters=job.iters, batch_rays=job.batch_rays, seed=0, eval_every=0,
                                     checkpoint_every=0))
    start, _, _ = build_initial_model(config, scene, torch.device("cpu"))  # the same start run_fit builds
    initial = evaluate_views(start, scene, evaluator.views, background, with_ssim=False).psnr
    summary = run_fit(config, job.out, overwrite=True, callbacks=[evaluator])
    out = {"job": dataclasses.asdict(job), "init_sha256": summary["init_sha256"], "initial_psnr": initial, "points": evaluator.points,
           "final_psnr": summary["test_psnr"], "time_s": summary["time_s"], "frozen_layers": summary["frozen_layers"],
           "optimizer": summary["optimizer"], "samples_per_ray": summary["train_samples_per_ray"]}
    tmp = result_path.with_suffix(".tmp")
    tmp.write_text(json.dumps(out, indent=1))
    os.replace(tmp, result_path)
    return out


def run_all(fn, jobs: list, workers: int, label: str) -> list:
    """Run ``jobs`` on ``workers`` processes (spawned, one thread each); results in job order."""
    results: list = [None] * len(jobs)
    t0 = time.time()
    if workers <= 1:
        _worker_init()
        for i, job in enumerate(jobs):
            results[i] = fn(job)
            print(f"[{label} {i + 1}/{len(jobs)} {time.time() - t0:.0f}s] {_describe(job)}", flush=True)
        return results
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_worker_init) as pool:
        futures = {pool.submit(fn, job): i for i, job in enumerate(jobs)}
        for n, fut in enumerate(as_completed(futures), 1):
            i = futures[fut]
            results[i] = fut.result()
            print(f"[{label} {n}/{len(jobs)} {time.time() - t0:.0f}s] {_describe(jobs[i])}", flush=True)
    return results


def _describe(job) -> str:
    if isinstance(job, PretrainJob):
        return f"pretrain {job.backbone} {job.category}"
    return f"{job.backbone} {job.group} {job.method} {job.scene_name}"


# ---------------------------------------------------------------------------------------------
# Planning


def plan(args, collection_dir: Path, out: Path, metas: dict[str, Path]) -> Plan:
    col = load_collection(collection_dir)
    held_out = tuple(args.held_out)
    seen = tuple(c for c in sorted({s.category for s in col.scenes}) if c not in held_out)
    if len(seen) < 6 or len(held_out) < 2:
        raise SystemExit(f"need >= 6 seen and 2 held-out categories, got {seen} / {held_out}")
    seen_scenes = [s for s in col.scenes if s.category in seen and s.split == "test"]
    per_held = math.ceil(args.unseen / len(held_out))
    unseen_scenes = [s for c in held_out for s in col.by_category(c)[:per_held]][: args.unseen]
    white, black = (1.0, 1.0, 1.0), (0.0, 0.0, 0.0)
    p = Plan()
    for backbone in args.backbones:
        b = BACKBONES[backbone]
        iters = args.pretrain_iters or b["pretrain_iters"]
        for c in seen:
            p.pretrain.append(PretrainJob(backbone, c, str(collection_dir), b["model"], b["batch_rays"], iters,
                                          str(out / "models" / backbone / c)))

        def fit(group, method, record, init, freeze=0, background=white, scene=None):
            model = b["model"] if init == "scratch" else {}  # a saved init keeps its own config
            scene = scene or col.scene_path(record)
            p.fits.append(FitJob(backbone, group, method, record.name, record.category, str(scene),
                                 init, freeze, model, b["batch_rays"], args.iters, background,
                                 str(out / "fits" / backbone / (method if init == "scratch" else f"{method}-k{freeze}")
                                     / record.name)))

        k = b["freeze"] if args.freeze is None else args.freeze
        for i, r in enumerate(seen_scenes):
            model_dir = out / "models" / backbone / r.category
            other = out / "models" / backbone / seen[(seen.index(r.category) + 1) % len(seen)]
            fit("seen", "scratch", r, "scratch")
            fit("seen", "category", r, f"category:{model_dir}", k)
            if backbone in metas:
                fit("seen", "meta", r, f"meta:{metas[backbone]}")
            if i < args.controls:
                fit("seen", "category-other", r, f"category:{other}", k)
                if backbone == "nerf":  # the grid's coarse stage tightens its box anyway
                    fit("seen", "scratch-canonical", r, "scratch", 0, white, canonical_copy(r, col, out))
            if i < args.black:
                fit("seen", "scratch-black", r, "scratch", 0, black)
                fit("seen", "category-black", r, f"category:{model_dir}", k, black)
            if backbone in args.freeze_sweep and i < 2:
                for kk in b["sweep"]:  # K = the default too, so the sweep's scenes are compared with themselves
                    fit("sweep", f"freeze-{kk}", r, f"category:{model_dir}", kk)
        for r in unseen_scenes:
            fit("unseen", "scratch", r, "scratch")
            if backbone in metas:
                fit("unseen", "meta", r, f"meta:{metas[backbone]}")
    return p


def canonical_copy(record, col, out: Path) -> Path:
    """The scene's files with its ``aabb`` set to the canonical box, so a scratch fit uses the category models' box."""
    src, dst = col.scene_path(record), out / "canonical_scenes" / record.name
    if not (dst / "transforms_test.json").exists():
        shutil.copytree(src, dst, dirs_exist_ok=True)
        for name in ("transforms_train.json", "transforms_test.json"):
            doc = json.loads((src / name).read_text())
            if "aabb" in doc:
                doc["aabb"] = [list(CANONICAL_BOX[0]), list(CANONICAL_BOX[1])]
            (dst / name).write_text(json.dumps(doc, indent=1))
    return dst


# ---------------------------------------------------------------------------------------------
# Aggregation


def psnr_at(points: list[dict], it: int) -> float | None:
    for p in points:
        if p["iter"] == it:
            return p["psnr"]
    return None


def reach(points: list[dict], target: float) -> tuple[int | None, float | None]:
    for p in points:
        if p["psnr"] >= target - 1e-9:
            return p["iter"], p["time_s"]
    return None, None


def mean_sd(values: list[float]) -> tuple[float, float]:
    if not values:
        return float("nan"), float("nan")
    return statistics.fmean(values), (statistics.stdev(values) if len(values) > 1 else 0.0)


def aggregate(results: list[dict], iters: int) -> dict[str, Any]:
    """Per backbone, group and method: PSNR at the report iterations and iterations/time to the scratch target."""
    by_key: dict[tuple, dict[str, dict]] = {}
    for r in results:
        j = r["job"]
        group = j["group"]
        by_key.setdefault((j["backbone"], group, j["method"]), {})[j["scene_name"]] = r
    out: dict[str, Any] = {}
    for (backbone, group, method), runs in sorted(by_key.items()):
        if group == "sweep":
            scratch_runs = by_key.get((backbone, "seen", "scratch"), {})
        elif method.endswith("-black"):
            scratch_runs = by_key.get((backbone, group, "scratch-black"), {})
        else:
            scratch_runs = by_key.get((backbone, group, "scratch"), {})
        row: dict[str, Any] = {"n": len(runs), "psnr": {}}
        for it in (0, *REPORT_ITERS):
            vals = [r["initial_psnr"] if it == 0 else psnr_at(r["points"], it) for r in runs.values()]
            vals = [v for v in vals if v is not None]
            row["psnr"][it] = mean_sd(vals)
        for label, at in (("", iters), ("_early", EARLY_TARGET)):
            reached_iters, reached_time, speed_iter, speed_time, scenes = [], [], [], [], {}
            for name, r in runs.items():
                base = scratch_runs.get(name)
                target = None if base is None else psnr_at(base["points"], at)  # unrounded evaluations
                if target is None:
                    continue
                base_iter, base_time = reach(base["points"], target)
                it, ts = reach(r["points"], target)
                scenes[name] = {"target": target, "iters": it, "time_s": ts, "scratch_iters": base_iter,
                                "scratch_time_s": base_time, "final": r["final_psnr"]}
                if it is not None:
                    reached_iters.append(it)
                    reached_time.append(ts)
                    speed_iter.append(base_iter / it)
                    speed_time.append(base_time / ts if ts else float("inf"))
            row["scenes" + label] = scenes
            row["reached" + label] = len(reached_iters)
            row["with_target" + label] = len(scenes)
            row["iters_to_target" + label] = _spread(reached_iters)
            row["time_to_target" + label] = _spread(reached_time)
            row["speedup_iters" + label] = _spread(speed_iter, geometric=True)
            row["speedup_time" + label] = _spread(speed_time, geometric=True)
        row["time_per_iter_ms"] = statistics.fmean(1000 * r["time_s"] / iters for r in runs.values())
        out.setdefault(backbone, {}).setdefault(group, {})[method] = row
    return out


def _spread(values: list[float], geometric: bool = False) -> dict[str, float] | None:
    if not values:
        return None
    if geometric:
        centre = math.exp(statistics.fmean(math.log(v) for v in values))
    else:
        centre = statistics.median(values)
    return {"centre": centre, "min": min(values), "max": max(values)}


# ---------------------------------------------------------------------------------------------
# Plots and report


METHOD_ORDER = ("scratch", "category", "meta", "category-other", "scratch-canonical", "scratch-black", "category-black")
CONTROLS = ("category-other", "scratch-canonical", "scratch-black", "category-black")


def _order(method: str) -> tuple[int, str]:
    return (METHOD_ORDER.index(method) if method in METHOD_ORDER else len(METHOD_ORDER), method)


def plot(results: list[dict], backbone: str, x_key: str, path: Path) -> None:
    """PSNR against iterations (or time), mean +- sd over scenes per method; one panel per group."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from nerfmeta.report.plots import save_figure

    mine = [r for r in results if r["job"]["backbone"] == backbone]
    panels = {
        "seen categories": lambda j: j["group"] == "seen" and j["method"] not in CONTROLS,
        "unseen (held-out) categories": lambda j: j["group"] == "unseen",
        "controls (seen scenes)": lambda j: j["group"] == "seen" and j["method"] in CONTROLS,
        "freeze sweep (2 seen scenes)": lambda j: j["group"] == "sweep",  # K = the default is a sweep job too
    }
    panels = {k: f for k, f in panels.items() if any(f(r["job"]) for r in mine)}
    colours: dict[str, str] = {}
    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 4), dpi=110, sharey=True, squeeze=False)
    for ax, (title, keep) in zip(axes[0], panels.items()):
        methods: dict[str, list[dict]] = {}
        for r in mine:
            if keep(r["job"]):
                name = r["job"]["method"] if r["job"]["group"] != "sweep" and "sweep" not in title else \
                    f"freeze-{r['job']['freeze']}"
                methods.setdefault(name, []).append(r)
        for method, runs in sorted(methods.items(), key=lambda kv: _order(kv[0])):
            colour = colours.setdefault(method, f"C{len(colours) % 10}")
            its = [p["iter"] for p in runs[0]["points"]]
            runs = [r for r in runs if [p["iter"] for p in r["points"]] == its]
            ys = np.array([[p["psnr"] for p in r["points"]] for r in runs])
            if x_key == "iter":
                xs = np.array(its, dtype=float)
            else:
                xs = np.array([[p["time_s"] for p in r["points"]] for r in runs]).mean(0)
            mean, sd = ys.mean(0), ys.std(0)
            ax.plot(xs, mean, color=colour, label=f"{method} (n={len(ys)})")
            ax.fill_between(xs, mean - sd, mean + sd, color=colour, alpha=0.15)
        ax.set_xscale("log")
        ax.set_xlabel("iteration" if x_key == "iter" else "optimisation time (s), mean over scenes")
        ax.set_title(f"{backbone}: {title}", fontsize=10)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8, loc="lower right")
    axes[0][0].set_ylabel("test PSNR (dB), mean +- sd over scenes")
    save_figure(fig, path)


def _fmt(ms: tuple[float, float]) -> str:
    m, s = ms
    return "-" if math.isnan(m) else f"{m:.2f} +- {s:.2f}"


def _fmt_spread(d: dict | None, unit: str = "", digits: int = 0) -> str:
    if d is None:
        return "never"
    return f"{d['centre']:.{digits}f}{unit} ({d['min']:.{digits}f}-{d['max']:.{digits}f})"


def section_text(agg: dict, meta: dict) -> str:
    lines = [SECTION, "", meta["intro"], "", "```", meta["command"], "```", ""]
    lines += [f"Machine: {MACHINE}. Date: {meta['date']}. This invocation: {meta['wall_min']:.1f} min ({meta['jobs']}). "
              "The fits were measured in these invocations (load average 1 / 5 / 15 min at start and end; fits "
              "at a time, one torch thread each):", ""]
    lines += [f"- {r['date']}: {r['new_fits']} fits, {r['workers']} at a time, {r['wall_min']:.1f} min, load "
              f"{r['load_start']} -> {r['load_end']}" for r in meta["invocations"]]
    lines += [""]
    lines += meta["setup"] + [""]
    for backbone, groups in agg.items():
        lines += [f"### {backbone}", ""]
        lines += ["Test PSNR (dB, mean +- sd over scenes) after N iterations (0 = the starting point):", ""]
        lines += ["| group | method | n | " + " | ".join(str(i) for i in (0, *REPORT_ITERS)) + " | ms/iter |",
                  "|---|---|---|" + "---|" * (len(REPORT_ITERS) + 2)]
        for group in ("seen", "unseen", "sweep"):
            for method, row in sorted(groups.get(group, {}).items(), key=lambda kv: _order(kv[0])):
                cells = [_fmt(tuple(row["psnr"][i])) for i in (0, *REPORT_ITERS)]
                lines.append(f"| {group} | {method} | {row['n']} | " + " | ".join(cells) + f" | {row['time_per_iter_ms']:.0f} |")
        lines += ["", "To reach the PSNR scratch reaches at 1000 iterations, per scene (first scheduled evaluation at or "
                  "above it; median (min-max) iterations and optimisation seconds over the scenes that reach it; speed-ups "
                  "are geometric means (min-max) of scratch's iterations/seconds to that PSNR over the method's); the "
                  f"last four columns the same for the PSNR scratch reaches at {EARLY_TARGET} iterations:", ""]
        lines += ["| group | method | reached | iterations | seconds | speed-up (iterations) | speed-up (time) | "
                  f"reached scratch@{EARLY_TARGET} | iterations | speed-up (iterations) | speed-up (time) |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for group in ("seen", "unseen", "sweep"):
            for method, row in sorted(groups.get(group, {}).items(), key=lambda kv: _order(kv[0])):
                if method in ("scratch", "scratch-black"):
                    continue
                lines.append(f"| {group} | {method} | {row['reached']}/{row['with_target']} | "
                             f"{_fmt_spread(row['iters_to_target'])} | {_fmt_spread(row['time_to_target'], ' s', 1)} | "
                             f"{_fmt_spread(row['speedup_iters'], 'x', 1)} | {_fmt_spread(row['speedup_time'], 'x', 1)} | "
                             f"{row['reached_early']}/{row['with_target_early']} | {_fmt_spread(row['iters_to_target_early'])} | "
                             f"{_fmt_spread(row['speedup_iters_early'], 'x', 1)} | {_fmt_spread(row['speedup_time_early'], 'x', 1)} |")
        lines += ["", f"![{backbone} PSNR vs iteration](docs/bench/transfer_{backbone}.png)",
                  f"![{backbone} PSNR vs time](docs/bench/transfer_{backbone}_time.png)", ""]
    lines += meta["findings"]
    return "\n".join(lines).rstrip("\n") + "\n"




INVOCATIONS = "invocations.json"
"""Per work folder: each invocation that ran fits, with its load and the fits it ran (the report cites those
that produced the fits it shows, so a rerun that reuses every fit does not pass off its own quiet load)."""


def record_invocation(out: Path, jobs: list, results: list[dict], facts: dict[str, Any]) -> list[dict]:
    """Append this invocation to ``OUT/invocations.json`` when it ran fits; return the invocations behind ``jobs``."""
    path = out / INVOCATIONS
    log_ = json.loads(path.read_text()) if path.is_file() else []
    ran = [job.out for job, r in zip(jobs, results) if not r.get(CACHED)]
    if ran:
        log_.append({**facts, "new_fits": len(ran), "fits": ran})
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(log_, indent=1))
        os.replace(tmp, path)
    wanted = {job.out for job in jobs}
    return [{k: v for k, v in r.items() if k != "fits"} for r in log_ if wanted & set(r["fits"])]


def _load() -> str:
    return " / ".join(f"{v:.2f}" for v in os.getloadavg())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="runs/bench_transfer", help="work folder (cached fits; default runs/bench_transfer)")
    parser.add_argument("--collection", default=None, help="reuse this collection instead of generating OUT/collection")
    parser.add_argument("--held-out", default=",".join(HELD_OUT), type=lambda s: tuple(s.split(",")), help="held-out categories")
    parser.add_argument("--meta", action="append", default=[], metavar="DIR", help="a meta-initialisation folder (repeat per backbone)")
    parser.add_argument("--backbones", default="nerf,grid", type=lambda s: tuple(s.split(",")), help="default nerf,grid")
    parser.add_argument("--iters", type=int, default=1000, help="iterations per fit (default 1000)")
    parser.add_argument("--pretrain-iters", type=int, default=None, help="category-model iterations (default per backbone)")
    parser.add_argument("--unseen", type=int, default=5, help="scenes of the held-out categories (default 5)")
    parser.add_argument("--freeze", type=int, default=None, help="--freeze K of the category fits (default per backbone)")
    parser.add_argument("--freeze-sweep", default="", type=lambda s: tuple(filter(None, s.split(","))), metavar="BACKBONES",
                        help="also fit 2 seen scenes with every freeze K of the sweep, for these backbones (e.g. nerf,grid)")
    parser.add_argument("--controls", type=int, default=2, help="seen scenes also fitted from another category's model (default 2)")
    parser.add_argument("--black", type=int, default=2, help="seen scenes also fitted on a black background, scratch and "
                        "from the white-background category model (default 2)")
    parser.add_argument("--workers", type=int, default=2, help="fits run in parallel (default 2)")
    parser.add_argument("--no-write", action="store_true", help="leave BENCHMARKS.md and docs/bench alone")
    parser.add_argument("--benchmarks", default=str(ROOT / "BENCHMARKS.md"), help="the file whose section is written")
    parser.add_argument("--plots", default=str(ROOT / "docs" / "bench"), help="folder for the plots (default docs/bench)")
    args = parser.parse_args()
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    start, load_start = time.time(), _load()
    metas: dict[str, Path] = {}
    for folder in args.meta:
        saved = load_init(folder, expect_kind="meta")
        used = {str(c) for c in saved.meta.get("categories", [])} | {str(s).split("_")[0] for s in saved.meta.get("scenes", [])}
        if used & set(args.held_out):
            raise SystemExit(f"{folder}: the meta-initialisation was trained on held-out categories {sorted(used & set(args.held_out))}")
        metas[saved.backbone] = Path(folder).resolve()
    if args.collection:
        collection_dir = Path(args.collection).resolve()
    else:
        collection_dir = out / "collection"
        if not (collection_dir / "collection.json").exists():
            print(f"generating {collection_dir}", flush=True)
            generate_collection(COLLECTION, collection_dir, workers=args.workers)
    p = plan(args, collection_dir, out, metas)
    for backbone, folder in metas.items():
        seen_by_meta = set(load_init(folder).meta.get("scenes", []))
        overlap = sorted(seen_by_meta & {f.scene_name for f in p.fits})
        if overlap:
            raise SystemExit(f"{folder}: the meta-initialisation was trained on benchmark scenes {overlap[:5]}")
    print(f"{len(p.pretrain)} category models, {len(p.fits)} fits; load {load_start}", flush=True)
    models = run_all(run_pretrain, p.pretrain, args.workers, "pretrain")
    results = run_all(run_fit_job, p.fits, args.workers, "fit")
    reused = sum(bool(r.get(CACHED)) for r in [*models, *results])
    agg = aggregate(results, args.iters)
    wall = (time.time() - start) / 60
    load_end = _load()
    invocations = record_invocation(out, p.fits, results, {
        "date": datetime.date.today().isoformat(), "workers": args.workers, "wall_min": round(wall, 1),
        "load_start": load_start, "load_end": load_end})
    (out / "results.json").write_text(json.dumps({"aggregate": agg, "runs": results}, indent=1, default=str))
    for backbone, groups in agg.items():
        for group, methods in groups.items():
            for method, row in methods.items():
                print(f"{backbone:5s} {group:7s} {method:15s} psnr@1000 {_fmt(tuple(row['psnr'][1000]))} "
                      f"reached {row['reached']}/{row['with_target']} iters {_fmt_spread(row['iters_to_target'])} "
                      f"speed-up {_fmt_spread(row['speedup_iters'], 'x', 1)} / time {_fmt_spread(row['speedup_time'], 'x', 1)}")
    print(f"wall {wall:.1f} min, load {load_start} -> {load_end}")
    if args.no_write:
        return 0
    plots = Path(args.plots)
    for backbone in args.backbones:
        plot(results, backbone, "iter", plots / f"transfer_{backbone}.png")
        plot(results, backbone, "time_s", plots / f"transfer_{backbone}_time.png")
    notes = plots / "transfer_findings.md"
    meta = {
        "intro": "Scratch vs category-transfer vs meta-init fits of held-out scenes (`scripts/bench_transfer.py`).",
        "command": "python " + " ".join([Path(sys.argv[0]).as_posix(), *sys.argv[1:]]),
        "date": datetime.date.today().isoformat(), "load_start": load_start, "load_end": load_end,
        "workers": args.workers, "wall_min": wall, "setup": setup_lines(args, metas, models),
        "jobs": f"{len(p.pretrain)} category models and {len(p.fits)} fits, {reused} of them reused from an earlier run",
        "invocations": invocations,
        "findings": notes.read_text().splitlines() if notes.exists() else [],
    }
    write_benchmark_section(Path(args.benchmarks), SECTION, section_text(agg, meta))
    print(f"updated {args.benchmarks} ({SECTION}) and {plots}/transfer_*.png")
    return 0


def setup_lines(args, metas: dict[str, Path], models: list[dict]) -> list[str]:
    c = COLLECTION
    lines = [
        f"Collection: {len(c.categories)} categories x {c.scenes_per_category} scenes, {c.views} train + {c.test_views} test "
        f"views at {c.resolution} x {c.resolution} (white background); held out entirely: {', '.join(args.held_out)}. "
        "Seen group: the test scene of each of the 6 seen categories (its category model never saw it); unseen group: "
        f"{args.unseen} scenes of the held-out categories.",
        "Every fit: Adam with the backbone's learning-rate groups, exponential decay to 0.1x over the "
        f"{args.iters} iterations, seed 0, the same ray batch; only the start (and frozen layers) differ. "
        f"Test PSNR on all test views at {len(SCHEDULE)} scheduled iterations, outside the timed optimisation.",
    ]
    for backbone in args.backbones:
        b = BACKBONES[backbone]
        k = b["freeze"] if args.freeze is None else args.freeze
        mine = [m for m in models if m["backbone"] == backbone]
        if mine:
            lines.append(f"{backbone} category models: test PSNR on their own scenes' held-out views "
                         f"{statistics.fmean(m['final_psnr'] for m in mine):.2f} dB on average "
                         f"({min(m['final_psnr'] for m in mine):.2f}-{max(m['final_psnr'] for m in mine):.2f}), "
                         f"{statistics.fmean(m['time_s'] for m in mine):.0f} s of training each (one-off, not counted below).")
        lines.append(f"{backbone}: `{json.dumps(b['model'])}` for scratch fits and category models, "
                     f"{b['batch_rays']} rays/iteration; category models: {args.pretrain_iters or b['pretrain_iters']} "
                     f"iterations on all training rays of the category; transfer with --freeze {k}"
                     + (f"; meta-init from {metas[backbone]}" if backbone in metas else "; no meta-initialisation given") + ".")
        if backbone in metas:
            lines.append(meta_training_line(backbone, metas[backbone]))
    return lines


def meta_training_line(backbone: str, folder: Path) -> str:
    """What the meta-initialisation of ``backbone`` cost to train (from its ``summary.json``), one line."""
    summary_path = folder / "summary.json"
    if not summary_path.is_file():
        return f"{backbone} meta-initialisation: no summary.json in {folder} (training time unknown)."
    s = json.loads(summary_path.read_text())
    held = s.get("held_out") or {}
    lr = s.get("inner_lr")
    lr_text = ", ".join(f"{k} {v:g}" for k, v in lr.items()) if isinstance(lr, dict) else f"{lr}"
    return (f"{backbone} meta-initialisation: {s.get('algo')} ({s.get('engine')}), {s.get('meta_steps')} meta-steps of "
            f"{s.get('meta_batch')} tasks x {s.get('inner_steps')} inner steps (inner lr {lr_text}), "
            f"{len(s.get('scenes', []))} training scenes of {len(s.get('categories', []))} categories: "
            f"**{s.get('time_s', 0) / 60:.1f} min of meta-training on this machine** ({s.get('world_size', 1)} process, one torch thread); "
            f"query PSNR on the seen categories' held-out scenes after {held.get('inner_steps', '?')} inner steps "
            f"{held.get('query_psnr_before', float('nan')):.2f} -> {held.get('query_psnr_after', float('nan')):.2f} dB.")


if __name__ == "__main__":
    raise SystemExit(main())
