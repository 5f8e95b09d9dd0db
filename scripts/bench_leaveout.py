"""Leaving out what a scene does not need (issue #8): every switch measured on and off, into BENCHMARKS.md.

Scenes: NeRF-synthetic lego at 100 x 100 (``--downscale 8``) and two generated scenes at 64 x 64,
the test scenes of chair and car in a collection from ``nerfmeta make-collection --categories
chair,car --scenes-per-category 5 --views 40 --test-views 10 --resolution 64 --val-fraction 0
--test-fraction 0.2`` (made in ``--work`` unless ``--collection`` is given; diffuse shading).

Parts (each fit is a fresh ``python -m nerfmeta fit`` process, seed ``k`` for repetition ``k``,
``--init scratch`` unless said otherwise, ``--checkpoint-every 0``):

* ``grid``: fits of a fixed number of iterations (``ITERS``: 750 on lego, 600 on the generated scenes) with
  test PSNR on the first 4 test views every ``--eval-every`` 50 iterations (outside the timed
  optimisation): the defaults, then one switch at a time: ``--set empty_space_skipping=false``,
  ``--set tighten_box=false``, ``--set view_dependent=true``/``false`` (against the default
  ``auto``, a trial decided 100 fine steps in; ``true`` was the default until session 43). Reported: final test PSNR (all test views), optimisation time to a fixed PSNR
  (``FIXED_PSNR``, on the 4 evaluation views), iterations, samples per ray, the decision.
* ``stage``: ``--target-psnr`` (``STAGE_TARGET``, below what the coarse stage reaches) with the
  default ``--eval-every 500``, with the stage-end evaluation and with ``--no-stage-end-eval``:
  optimisation time and iterations until the fit stops, wall time, final PSNR.
* ``frozen``: transfer fits of the generated chair from category models (``nerfmeta pretrain
  category`` on the collection's 4 training chairs; grid with ``view_dependent=true`` so the colour
  MLP exists, nerf with the small preset) with ``--freeze K`` against ``--freeze 0``: ms per
  iteration, peak RSS, and (in this process, exact and load-independent) the bytes autograd keeps
  for the backward pass of one 4096-ray step, also for "frozen by bookkeeping only" (the same
  layers kept out of the optimiser but still requiring gradients).
* ``eval``: 200-iteration fits with the final evaluation's SSIM and 4 renders against
  ``--no-eval-ssim --renders 0``: evaluation time and wall time.

Every run records the 1/5/15-minute load average before it (the machine is shared). ``--write``
replaces the ``## Leaving out what a scene does not need`` section of BENCHMARKS.md; results are
also kept in ``WORK/results.json`` (``--reuse`` takes finished runs from ``WORK``).

Usage::

    .venv/bin/python scripts/bench_leaveout.py [--work runs/bench_leaveout] [--reps 2] [--parts grid,stage,frozen,eval]
        [--scenes lego,chair,car] [--reuse] [--write]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # the pretrain/ package, when the checkout is not installed
    sys.path.insert(0, str(ROOT))

DEFAULT_LEGO = ROOT.parent / "shared" / "data" / "nerf_synthetic" / "lego"
SECTION = "## Leaving out what a scene does not need"
MACHINE = "2-core CPU, no GPU"
COLLECTION_ARGS = ["--categories", "chair,car", "--scenes-per-category", "5", "--views", "40", "--test-views", "10",
                   "--resolution", "64", "--val-fraction", "0", "--test-fraction", "0.2", "--seed", "0"]
ITERS = {"lego": 750, "chair": 600, "car": 600}
"""Iterations per fit of the ``grid`` part (lego: what the 60 s budget of ``## Fit on lego`` gives on an idle machine)."""
FIXED_PSNR = {"lego": 28.0, "chair": 30.0, "car": 30.0}
"""The PSNR (dB, first 4 test views) whose optimisation time the ``grid`` part reports."""
STAGE_TARGET = {"lego": 18.0, "chair": 20.0, "car": 20.0}
"""``--target-psnr`` of the ``stage`` part: below what the 100-step coarse stage reaches."""
BUDGET = {"lego": 60.0, "chair": 20.0, "car": 20.0}
"""Optimisation seconds of the ``budget`` part."""
BUDGET_VARIANTS = (("default", []), ("view_dependent=true", ["--set", "view_dependent=true"]),
                   ("view_dependent=false", ["--set", "view_dependent=false"]))
VARIANTS = (
    ("default", []),
    ("empty_space_skipping=false", ["--set", "empty_space_skipping=false"]),
    ("tighten_box=false", ["--set", "tighten_box=false"]),
    ("view_dependent=true", ["--set", "view_dependent=true"]),
    ("view_dependent=false", ["--set", "view_dependent=false"]),
)
NERF_MODEL = []  # the small preset (4 x 128, 48 samples)
FREEZE = {"grid": (0, 1, 2), "nerf": (0, 2, 4)}
PRETRAIN = {"grid": ["--iters", "500", "--batch-rays", "4096", "--set", "view_dependent=true"],
            "nerf": ["--iters", "300", "--batch-rays", "1024"]}
TRANSFER = {"grid": ["--iters", "150", "--batch-rays", "4096"], "nerf": ["--iters", "40", "--batch-rays", "1024"]}


def load() -> str:
    return " / ".join(f"{v:.1f}" for v in os.getloadavg())


THREADS = 1
"""Torch (OpenMP) threads per run. With other jobs on the 2 cores, two threads ran about 10x slower than one
(a 150-iteration grid fit of the generated chair: 130.8 s against 12.6 s, load average 4.7): each parallel
region waits for a thread the scheduler has parked."""


def run_cli(args: list[str], log: Path) -> float:
    """``python -m nerfmeta ARGS`` in a fresh process; its wall time. Exits with the log's last line on failure."""
    start = time.perf_counter()
    env = {**os.environ, "OMP_NUM_THREADS": str(THREADS)}
    with open(log, "w") as f:
        proc = subprocess.run([sys.executable, "-m", "nerfmeta", *args], cwd=ROOT, stdout=f, stderr=subprocess.STDOUT,
                              env=env)
    if proc.returncode != 0:
        tail = log.read_text().strip().splitlines()[-1:]
        raise SystemExit(f"bench_leaveout: nerfmeta {' '.join(args[:2])} failed (exit {proc.returncode}): "
                         f"{tail[0] if tail else 'no output'}; see {log}")
    return time.perf_counter() - start


def fit_run(out: Path, scene: str, extra: list[str], reuse: bool) -> dict[str, Any]:
    """One fit into ``out`` (or its earlier result with ``reuse``): summary, metrics, wall time and load before."""
    done = out / "bench.json"
    if reuse and done.is_file():
        return json.loads(done.read_text())
    before = load()
    out.parent.mkdir(parents=True, exist_ok=True)
    wall = run_cli(["fit", scene, "--out", str(out), "--overwrite", *extra], out.with_suffix(".log"))
    summary = json.loads((out / "summary.json").read_text())
    metrics = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines() if line.strip()]
    result = {"summary": summary, "curve": [(r["iter"], r["time_s"], r["test_psnr"]) for r in metrics if "test_psnr" in r],
              "wall_s": wall, "load": before, "load_after": load()}
    done.write_text(json.dumps(result))
    return result


def time_to(run: dict, psnr: float) -> float | None:
    """Optimisation seconds at the first intermediate evaluation (first 4 test views) reaching ``psnr`` (None: never).

    The last iteration's figure is the final evaluation on all test views, a different measure: left out.
    """
    return next((t for i, t, p in run["curve"] if p >= psnr and i != run["summary"]["iters"]), None)


def med(values: list) -> float | None:
    values = [v for v in values if v is not None]
    return statistics.median(values) if values else None


def fmt(value: float | None, digits: int = 1, unit: str = "") -> str:
    return "-" if value is None else f"{value:.{digits}f}{unit}"


# ----- scenes -----------------------------------------------------------------------------------------


def scenes(args: argparse.Namespace) -> dict[str, dict[str, Any]]:
    from nerfmeta.collection.generate import load_collection

    col_dir = args.collection or args.work / "collection"
    if not (Path(col_dir) / "collection.json").is_file():
        print(f"generating the collection in {col_dir} (load {load()})", flush=True)
        args.work.mkdir(parents=True, exist_ok=True)
        run_cli(["make-collection", str(col_dir), *COLLECTION_ARGS], args.work / "make_collection.log")
    col = load_collection(col_dir)
    out = {"lego": {"path": str(args.lego), "cli": ["--downscale", "8"], "label": "lego 100x100"}}
    for category in ("chair", "car"):
        record = next(r for r in col.scenes if r.category == category and r.split == "test")
        out[category] = {"path": str(col.scene_path(record)), "cli": [], "label": f"{record.name} 64x64"}
    out["_collection"] = {"path": str(col_dir)}
    return out


# ----- parts ------------------------------------------------------------------------------------------


def seeded_fits(args, sc, part: str, variants, settings, describe) -> list[dict]:
    """Per scene and variant, ``args.reps`` scratch grid fits (seeds 0, 1, ...) into ``WORK/PART/SCENE/STEM_SEED``.

    Args:
        part: the part's name (folder and progress prefix).
        variants: (label, folder stem, extra CLI flags) per variant.
        settings: scene name -> the part's own CLI flags (iterations or budget, evaluation, renders).
        describe: (scene name, run) -> the progress line's figures.

    Returns:
        one row per scene and variant: ``{"scene", "variant", "runs"}``.
    """
    rows = []
    for name in args.scenes:
        s = sc[name]
        for variant, stem, extra in variants:
            runs = []
            for k in range(args.reps):
                cli = [*s["cli"], "--init", "scratch", "--backbone", "grid", *settings(name), "--checkpoint-every", "0",
                       "--seed", str(k), *extra]
                r = fit_run(args.work / part / name / f"{stem}_{k}", s["path"], cli, args.reuse)
                runs.append(r)
                print(f"[{part}] {name} {variant} seed {k}: {describe(name, r)}, load {r['load']}", flush=True)
            rows.append({"scene": name, "variant": variant, "runs": runs})
    return rows


def _view_decision(summary: dict) -> Any:
    return summary["decisions"].get("view_dependent", {}).get("value")


def part_grid(args, sc) -> list[dict]:
    variants = [(v, v, extra) for v, extra in VARIANTS if not args.variants or v in args.variants]
    return seeded_fits(
        args, sc, "grid", variants,
        lambda name: ["--iters", str(ITERS[name]), "--eval-every", "50", "--renders", "0"],
        lambda name, r: (f"{r['summary']['test_psnr']:.2f} dB, {r['summary']['iters']} iters, to {FIXED_PSNR[name]:g} dB "
                         f"{fmt(time_to(r, FIXED_PSNR[name]))} s, vd={_view_decision(r['summary'])}"))


def part_budget(args, sc) -> list[dict]:
    return seeded_fits(
        args, sc, "budget", [(v, v, extra) for v, extra in BUDGET_VARIANTS],
        lambda name: ["--time-budget", f"{BUDGET[name]:g}", "--eval-every", "0", "--renders", "0"],
        lambda name, r: (f"{r['summary']['test_psnr']:.2f} dB, {r['summary']['iters']} iters in {r['summary']['time_s']:.1f} s, "
                         f"vd={_view_decision(r['summary'])}"))


def part_stage(args, sc) -> list[dict]:
    return seeded_fits(
        args, sc, "stage",
        [("stage-end evaluation", "stage-end evaluation", []), ("--no-stage-end-eval", "no-stage-end-eval", ["--no-stage-end-eval"])],
        lambda name: ["--target-psnr", f"{STAGE_TARGET[name]:g}", "--iters", "3000", "--eval-every", "500"],
        lambda name, r: (f"stopped after {r['summary']['iters']} iters, {r['summary']['time_s']:.1f} s "
                         f"({r['summary']['stop_reason']}), {r['summary']['test_psnr']:.2f} dB, wall {r['wall_s']:.1f} s"))


def part_eval(args, sc) -> list[dict]:
    return seeded_fits(
        args, sc, "eval",
        [("SSIM + 4 renders", "full", []), ("--no-eval-ssim --renders 0", "lean", ["--no-eval-ssim", "--renders", "0"])],
        lambda name: ["--iters", "200", "--eval-every", "0"],
        lambda name, r: (f"eval {r['summary']['eval_time_s']:.2f} s, wall {r['wall_s']:.1f} s, "
                         f"SSIM {r['summary']['test_ssim']}"))


def graph_bytes(init_dir: Path, scene_path: str, freeze: int, bookkeeping_only: bool, batch: int) -> tuple[int, float]:
    """Bytes autograd saves for backward in one training step of ``batch`` rays, and that step's seconds (median of 5)."""
    import torch

    from nerfmeta.data import load_scene
    from nerfmeta.fit.sampler import RaySampler
    from nerfmeta.init import load_init

    scene = load_scene(scene_path)
    model = load_init(init_dir).build()
    frozen = model.freeze_first(freeze)
    if bookkeeping_only:  # frozen in name only: out of the optimiser, but autograd still differentiates them
        params = dict(model.named_parameters())
        for name in frozen:
            params[name].requires_grad_(True)
    background = torch.ones(3)
    sampler = RaySampler(scene, "train", "cpu")
    gen = torch.Generator().manual_seed(0)
    saved = [0]

    def pack(t):
        saved[0] += t.numel() * t.element_size()
        return t

    times = []
    for step in range(6):
        rays = sampler.sample(batch, gen)
        saved[0] = 0
        start = time.perf_counter()
        with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
            out = model(rays, background=background, train=True, generator=gen)
            loss = ((out.rgb - rays.target) ** 2).mean()
        loss.backward()
        if step:  # the first step warms up
            times.append(time.perf_counter() - start)
        model.zero_grad(set_to_none=True)
    return saved[0], statistics.median(times)


def part_frozen(args, sc) -> list[dict]:
    col, scene = sc["_collection"]["path"], sc["chair"]["path"]
    rows = []
    for backbone in ("grid", "nerf"):
        init_dir = args.work / "frozen" / f"chair_{backbone}"
        if not (args.reuse and (init_dir / "init.json").is_file()):
            print(f"[frozen] pretraining the {backbone} chair model (load {load()})", flush=True)
            init_dir.parent.mkdir(parents=True, exist_ok=True)
            run_cli(["pretrain", "category", col, "--category", "chair", "--out", str(init_dir), "--overwrite",
                     "--backbone", backbone, *PRETRAIN[backbone]], init_dir.with_suffix(".log"))
        for k in FREEZE[backbone]:
            runs = []
            for rep in range(args.reps):
                cli = ["--init", f"category:{init_dir}", "--freeze", str(k), *TRANSFER[backbone], "--eval-every", "0",
                       "--checkpoint-every", "0", "--seed", str(rep), "--renders", "0", "--no-eval-ssim"]
                r = fit_run(args.work / "frozen" / backbone / f"freeze{k}_{rep}", scene, cli, args.reuse)
                runs.append(r)
                sm = r["summary"]
                print(f"[frozen] {backbone} --freeze {k} seed {rep}: {1000 * sm['time_s'] / sm['iters']:.1f} ms/iter, "
                      f"peak RSS {sm['peak_rss_mb']:.0f} MB, {sm['test_psnr']:.2f} dB, load {r['load']}", flush=True)
            batch = int(TRANSFER[backbone][TRANSFER[backbone].index("--batch-rays") + 1])
            graph = {mode: graph_bytes(init_dir, scene, k, mode == "bookkeeping", batch) for mode in ("no graph", "bookkeeping")}
            rows.append({"backbone": backbone, "freeze": k, "runs": runs, "frozen_layers": runs[0]["summary"]["frozen_layers"],
                         "graph_mb": {m: v[0] / 2**20 for m, v in graph.items()},
                         "step_ms": {m: 1000 * v[1] for m, v in graph.items()}, "graph_load": load()})
    return rows


# ----- report -----------------------------------------------------------------------------------------


def section(results: dict, args: argparse.Namespace) -> str:
    sc = results["scenes"]
    lines = [
        SECTION,
        "",
        "Issue #8: each thing a scene may not need is a per-scene decision, recorded in `summary.json` under",
        "`decisions` (and as an `event` in `metrics.jsonl`), with a switch to turn it off. Measured with",
        "`scripts/bench_leaveout.py` (one fresh `nerfmeta fit` process per run; seeds 0..R-1; medians over the",
        "runs). Scenes: " + ", ".join(f"{n} ({sc[n]['label']})" for n in results["scene_names"]) + "; the generated",
        "ones are the test scenes of `nerfmeta make-collection COL " + " ".join(COLLECTION_ARGS) + "` (diffuse).",
        "",
        f"Machine: {MACHINE} (torch {results['torch']}), shared with other engineers' jobs; date {results['date']}.",
        f"Every run uses {results['threads']} torch thread (`OMP_NUM_THREADS={results['threads']}`): with the other jobs on",
        "the two cores, two threads ran a 150-iteration grid fit 10x slower (130.8 s against 12.6 s at load 4.7).",
        "Load averages (1 / 5 / 15 min) before each run are listed per row: 2.0 means both cores were busy with",
        "other work, so absolute times are inflated and noisy; compare rows run at similar load.",
        "",
    ]
    if "grid" in results:
        lines += [
            "### Grid fits: each switch off in turn",
            "",
            "```",
            "nerfmeta fit SCENE --init scratch --backbone grid --iters N --eval-every 50 --checkpoint-every 0 "
            "--seed K --renders 0 [--downscale 8] [--set SWITCH=VALUE]",
            "```",
            "",
            "N = " + ", ".join(f"{ITERS[n]} ({n})" for n in results["scene_names"]) + " iterations (a fixed count, not a "
            "time budget, so that every variant follows the same learning-rate schedule and the PSNR does not depend on "
            "how busy the machine was). Final PSNR: all test views after N iterations; time to P: optimisation seconds "
            "until the first 4 test views (evaluated every 50 "
            "iterations) reach P = " + ", ".join(f"{FIXED_PSNR[n]:g} dB ({n})" for n in results["scene_names"]) + ". "
            "Runs that compute the same thing (the default and `tighten_box=false` where the box stays the scene box; "
            "the default and `view_dependent=true` where the trial keeps the MLP) give the same PSNR to the last digit, "
            "and their times show the run-to-run noise of the shared machine.",
            "",
            "| scene | variant | final PSNR (dB) | vs default | time to P (s) | optimisation time (s) | "
            "samples/ray (train) | decided | load before runs |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        base = {}
        for row in results["grid"]:
            runs = row["runs"]
            psnr = med([r["summary"]["test_psnr"] for r in runs])
            if row["variant"] == "default":
                base[row["scene"]] = psnr
            delta = psnr - base.get(row["scene"], psnr)
            times = [time_to(r, FIXED_PSNR[row["scene"]]) for r in runs]
            reached = sum(t is not None for t in times)
            ttp = fmt(med(times)) + ("" if reached == len(runs) else f" ({reached}/{len(runs)} reached)")
            vd = [r["summary"]["decisions"].get("view_dependent", {}).get("value") for r in runs]
            vd_text = "view-dep. " + "/".join("yes" if v else "no" for v in vd)
            lines.append(f"| {row['scene']} | {row['variant']} | {psnr:.2f} | {delta:+.2f} | {ttp} | "
                         f"{med([r['summary']['time_s'] for r in runs]):.1f} | "
                         f"{med([r['summary']['train_samples_per_ray'] for r in runs]):.1f} | {vd_text} | "
                         f"{'; '.join(r['load'] for r in runs)} |")
        evidence = []
        for row in results["grid"]:
            for k, r in enumerate(row["runs"]):
                d = r["summary"]["decisions"]
                if row["variant"] == "default":
                    box, ess = d.get("tighten_box", {}).get("evidence", {}), d.get("empty_space_skipping", {}).get("evidence", {})
                    evidence.append(f"{row['scene']} seed {k}: fine box {box.get('volume_fraction')} of the scene box's "
                                    f"volume, occupancy cache {ess.get('occupied_fraction')} of the fine voxels")
                    vd = d.get("view_dependent", {})  # the default is the trial (``auto``) since session 43
                    evidence.append(f"{row['scene']} seed {k}: view input gain {vd.get('evidence', {}).get('gain_db')} dB "
                                    f"(threshold {vd.get('evidence', {}).get('threshold_db')}), MLP "
                                    f"{'kept' if vd.get('value') else 'folded and dropped'}")
        lines += ["", "Decisions and their evidence (`summary.json` `decisions`): " + "; ".join(evidence) + ".", ""]
    if "budget" in results:
        lines += [
            "### The view-dependence decision under a time budget",
            "",
            "```",
            "nerfmeta fit SCENE --init scratch --backbone grid --time-budget B --eval-every 0 --checkpoint-every 0 --seed K "
            "--renders 0 [--downscale 8] [--set view_dependent=true|false]",
            "```",
            "",
            "B = " + ", ".join(f"{BUDGET[n]:g} s ({n})" for n in results["scene_names"]) + ": the learning rates decay "
            "over the budget, so each variant spends it with its own number of iterations (which the load changes: see "
            "the load column).",
            "",
            "| scene | variant | final PSNR (dB) | vs default | iterations | decided | load before runs |",
            "|---|---|---|---|---|---|---|",
        ]
        base = {}
        for row in results["budget"]:
            runs = row["runs"]
            psnr = med([r["summary"]["test_psnr"] for r in runs])
            if row["variant"] == "default":
                base[row["scene"]] = psnr
            vd = [r["summary"]["decisions"].get("view_dependent", {}).get("value") for r in runs]
            lines.append(f"| {row['scene']} | {row['variant']} | {psnr:.2f} | {psnr - base.get(row['scene'], psnr):+.2f} | "
                         f"{med([r['summary']['iters'] for r in runs]):.0f} | "
                         f"view-dep. {'/'.join('yes' if v else 'no' for v in vd)} | {'; '.join(r['load'] for r in runs)} |")
        lines.append("")
    if "stage" in results:
        lines += [
            "### Fine stage skipped when the coarse stage meets the target",
            "",
            "```",
            "nerfmeta fit SCENE --init scratch --backbone grid --target-psnr T --iters 3000 --eval-every 500 "
            "--checkpoint-every 0 --seed K [--downscale 8] [--no-stage-end-eval]",
            "```",
            "",
            "T = " + ", ".join(f"{STAGE_TARGET[n]:g} dB ({n})" for n in results["scene_names"]) + ", which the "
            "100-step coarse stage reaches. Without the stage-end evaluation the target is only seen at the "
            "scheduled evaluation (iteration 500).",
            "",
            "| scene | variant | stopped after (iterations) | optimisation time (s) | wall time (s) | final PSNR (dB) | load before runs |",
            "|---|---|---|---|---|---|---|",
        ]
        for row in results["stage"]:
            runs = row["runs"]
            lines.append(f"| {row['scene']} | {row['variant']} | {med([r['summary']['iters'] for r in runs]):.0f} | "
                         f"{med([r['summary']['time_s'] for r in runs]):.1f} | {med([r['wall_s'] for r in runs]):.1f} | "
                         f"{med([r['summary']['test_psnr'] for r in runs]):.2f} | {'; '.join(r['load'] for r in runs)} |")
        lines.append("")
    if "frozen" in results:
        lines += [
            "### No gradients through frozen layers (transfer fits)",
            "",
            "```",
            "nerfmeta pretrain category COL --category chair --out CHAIR_B --backbone B " + " / ".join(
                f"({b}) {' '.join(v)}" for b, v in PRETRAIN.items()),
            "nerfmeta fit CHAIR_TEST --init category:CHAIR_B --freeze K --eval-every 0 --checkpoint-every 0 --seed K "
            "--renders 0 --no-eval-ssim " + " / ".join(f"({b}) {' '.join(v)}" for b, v in TRANSFER.items()),
            "```",
            "",
            "ms/iteration and peak RSS from the fits (whole process, images included); autograd memory: the bytes "
            "saved for the backward pass of one step (exact, from `torch.autograd.graph.saved_tensors_hooks`), and "
            "that step's forward + backward time (median of 5, in the benchmark process), for the frozen layers "
            "with `requires_grad=False` (what `--freeze` does) and for 'bookkeeping only' (the same layers out of "
            "the optimiser but still requiring gradients).",
            "",
            "| backbone | --freeze | frozen layers | ms/iteration (fit) | peak RSS (MB) | final PSNR (dB) | autograd MB/step: frozen / bookkeeping only | step ms: frozen / bookkeeping only | load before runs |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for row in results["frozen"]:
            runs = row["runs"]
            ms = med([1000 * r["summary"]["time_s"] / r["summary"]["iters"] for r in runs])
            lines.append(f"| {row['backbone']} | {row['freeze']} | {', '.join(row['frozen_layers']) or 'none'} | {ms:.1f} | "
                         f"{med([r['summary']['peak_rss_mb'] for r in runs]):.0f} | "
                         f"{med([r['summary']['test_psnr'] for r in runs]):.2f} | "
                         f"{row['graph_mb']['no graph']:.1f} / {row['graph_mb']['bookkeeping']:.1f} | "
                         f"{row['step_ms']['no graph']:.0f} / {row['step_ms']['bookkeeping']:.0f} | "
                         f"{'; '.join(r['load'] for r in runs)} |")
        lines.append("")
    if "eval" in results:
        lines += [
            "### Evaluation work only when asked for",
            "",
            "```",
            "nerfmeta fit SCENE --init scratch --backbone grid --iters 200 --eval-every 0 --checkpoint-every 0 --seed K "
            "[--downscale 8] [--no-eval-ssim --renders 0]",
            "```",
            "",
            "LPIPS is never computed (nerfmeta has no LPIPS yet). The final evaluation renders every test view either way "
            "(test PSNR needs them); the switches drop SSIM and the PNG strips.",
            "",
            "| scene | variant | evaluation time (s) | wall time (s) | test SSIM | load before runs |",
            "|---|---|---|---|---|---|",
        ]
        for row in results["eval"]:
            runs = row["runs"]
            ssim = runs[0]["summary"]["test_ssim"]
            lines.append(f"| {row['scene']} | {row['variant']} | {med([r['summary']['eval_time_s'] for r in runs]):.2f} | "
                         f"{med([r['wall_s'] for r in runs]):.1f} | {'-' if ssim is None else f'{ssim:.4f}'} | "
                         f"{'; '.join(r['load'] for r in runs)} |")
        lines.append("")
    lines += results.get("conclusions", [])
    return "\n".join(lines).rstrip("\n") + "\n"




CONCLUSIONS = "conclusions.md"
"""Optional hand-written paragraph in WORK appended to the section (what is kept on by default, and why)."""


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lego", type=Path, default=DEFAULT_LEGO, help=f"lego folder (default {DEFAULT_LEGO})")
    parser.add_argument("--collection", type=Path, default=None, help="a collection made with the arguments above (default: made in WORK)")
    parser.add_argument("--work", type=Path, default=ROOT / "runs" / "bench_leaveout", help="run folders and results.json")
    parser.add_argument("--reps", type=int, default=2, help="runs per variant (default 2)")
    parser.add_argument("--parts", default="grid,budget,stage,frozen,eval", help="which parts to run (default all)")
    parser.add_argument("--scenes", default="lego,chair,car", help="scenes of the grid, stage and eval parts (default all)")
    parser.add_argument("--variants", default="", help="grid part: only these variants, comma-separated (default all)")
    parser.add_argument("--reuse", action="store_true", help="take finished runs from WORK instead of running them again")
    parser.add_argument("--write", action="store_true", help="replace the section in BENCHMARKS.md")
    args = parser.parse_args()
    args.scenes = [s for s in args.scenes.split(",") if s]
    args.variants = [v for v in args.variants.split(",") if v]
    parts = [p for p in args.parts.split(",") if p]
    if not (args.lego / "transforms_train.json").is_file() and "lego" in args.scenes:
        print(f"bench_leaveout: lego not found at {args.lego}; pass --lego PATH", file=sys.stderr)
        return 2
    import torch

    torch.set_num_threads(THREADS)  # the in-process measurements of the frozen part
    sc = scenes(args)
    results: dict[str, Any] = {"scenes": sc, "scene_names": args.scenes, "date": datetime.date.today().isoformat(),
                               "torch": torch.__version__, "threads": torch.get_num_threads(), "load_start": load()}
    for part, fn in (("grid", part_grid), ("budget", part_budget), ("stage", part_stage), ("frozen", part_frozen),
                     ("eval", part_eval)):
        if part in parts:
            results[part] = fn(args, sc)
    results["load_end"] = load()
    conclusions = args.work / CONCLUSIONS
    if conclusions.is_file():
        results["conclusions"] = conclusions.read_text().splitlines()
    (args.work / "results.json").write_text(json.dumps(results, indent=1))
    text = section(results, args)
    print(text)
    if args.write:
        from benchlib.sections import write_section as write_benchmark_section
        write_benchmark_section(ROOT / "BENCHMARKS.md", SECTION, text)
        print(f"updated {ROOT / 'BENCHMARKS.md'} ({SECTION})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
