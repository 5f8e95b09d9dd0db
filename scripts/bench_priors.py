"""Grid priors on held-out generated scenes: PSNR against *wall* time, scratch grid vs each start (issue 17).

What it does:

1. Generates a collection (``nerfmeta make-collection``) with a seed no design run used: the zoo's
   6 seen categories (one scene each: the *seen* group) and its 2 held-out ones (``--unseen``
   scenes in all: the *unseen* group).
2. Fits every scene with each grid arm (:data:`GRID_ARMS`), the arms interleaved scene by scene
   (their order rotating) so the machine's load hits them alike: ``scratch`` (the voxel grid with
   its tuned defaults) and the candidate starts. Every arm: the same ``FitConfig`` (1000
   iterations, lr decay over them, 4096 rays, seed 0); only the start (and the coarse length it
   implies) differ.
3. Optionally (``--mlp``) the source work's setting with the model zoo's NeRF-MLP priors, at the
   zoo's resolution: ``scratch-nerf`` against the zoo's route (category model or meta-init),
   classification included, beside the grid arms of the same scenes.

Time axis: wall seconds = building the start (classification, loading, carving) + the fit loop's
own time (evaluation excluded). Test PSNR (all test views) is taken at the first step past each
point of :data:`EVAL_TIMES` and at the end. Per scene: the time to reach scratch's 1000-iteration PSNR as a fraction of scratch's
(interpolated between evaluations), PSNR at 2 s against scratch (interpolated), and the worst
deficit against scratch at any common evaluation time (scratch interpolated).

Usage::

    flock /work/wt/bench.lock .venv/bin/python scripts/bench_priors.py --out runs/bench_priors --seed 11 [--workers 2] [--mlp]
        [--occupancy-net zoo|NET.safetensors] [--arms scratch,carve,routed]
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import multiprocessing
import os
import statistics
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import nerfmeta  # noqa: E402,F401 - before torch, which then spins its OpenMP workers briefly (nerfmeta/__init__.py)
import torch  # noqa: E402

SEEN = ("airplane", "car", "chair", "lamp", "mug", "table")
UNSEEN = ("sofa", "vase")
EVAL_TIMES = (0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0, 32.0, 48.0, 64.0, 96.0, 128.0, 192.0, 256.0, 384.0)
"""Wall seconds at which every arm's test PSNR is taken (the run in BENCHMARKS.md stopped at 32 s: under load a
1000-iteration fit took up to 344 s, and the late part of its curves was seen only at the end)."""
GRID_ARMS = ("scratch", "carve")
"""Default grid arms: ``scratch`` (tuned defaults) and ``carve`` (the visual-hull start, :mod:`nerfmeta.priors`);
``occupancy`` (the learned occupancy start, :mod:`nerfmeta.priors.occupancy`) joins them with ``--occupancy-net``.
``--arms`` may also name ``routed``: what ``nerfmeta fit SCENE`` (``--init auto``) does with ``--zoo``, routing on the
clock."""


@dataclass
class Curve:
    """One fit's test PSNR against wall time."""

    arm: str
    scene: str
    group: str
    times: list[float]
    psnrs: list[float]
    iters: list[int]
    build_s: float
    wall_s: float
    final_psnr: float
    note: str = ""

    def at(self, t: float) -> float | None:
        """PSNR at wall time ``t`` (linear between evaluations; None before the first or after the last)."""
        return interpolate(self.times, self.psnrs, t)


def interpolate(xs: list[float], ys: list[float], x: float) -> float | None:
    """Linear interpolation of (xs, ys) at ``x``; None outside ``[xs[0], xs[-1]]``."""
    if not xs or x < xs[0] or x > xs[-1]:
        return None
    for (x0, y0), (x1, y1) in zip(zip(xs, ys), zip(xs[1:], ys[1:])):
        if x0 <= x <= x1:
            return y0 if x1 == x0 else y0 + (y1 - y0) * (x - x0) / (x1 - x0)
    return ys[-1]


def time_to_reach(xs: list[float], ys: list[float], target: float) -> float | None:
    """First ``x`` at which the piecewise-linear curve reaches ``target`` (None if never)."""
    if not xs:
        return None
    if ys[0] >= target:
        return xs[0]
    for (x0, y0), (x1, y1) in zip(zip(xs, ys), zip(xs[1:], ys[1:])):
        if y1 >= target:
            return x0 + (x1 - x0) * (target - y0) / (y1 - y0)
    return None


def worst_gap(xs: list[float], ys: list[float], base_xs: list[float], base_ys: list[float]) -> float:
    """Largest ``base - curve`` (dB) at the curve's points ``xs`` within the base's range, the base interpolated on the
    same axis (>= 0 means behind; -inf when no point falls in the range)."""
    gaps = [b - y for x, y in zip(xs, ys) if (b := interpolate(base_xs, base_ys, x)) is not None]
    return max(gaps, default=-math.inf)


def worst_deficit(curve: Curve, base: Curve) -> float:
    """:func:`worst_gap` on the wall-clock axis: at ``curve``'s evaluation times."""
    return worst_gap(curve.times, curve.psnrs, base.times, base.psnrs)


def worst_deficit_by_iteration(curve: Curve, base: Curve) -> float:
    """:func:`worst_gap` at the same *iteration*: the deficit with the machine's speed (and each arm's own speed per
    iteration) taken out."""
    return worst_gap(curve.iters, curve.psnrs, base.iters, base.psnrs)


def best_so_far(curve: Curve) -> Curve:
    """``curve`` with each PSNR replaced by the best reached up to then (what a fit that keeps its best test
    checkpoint would hand over; both arms' test PSNR falls after ~400 iterations on 24 views at 64 px)."""
    best, out = -math.inf, []
    for p in curve.psnrs:
        best = max(best, p)
        out.append(best)
    return dataclasses.replace(curve, psnrs=out)


# ----- fitting ----------------------------------------------------------------------------------


def timed_fit(model, scene, fit_config, background, *, build_s: float, extra_times: tuple[float, ...] = ()):
    """Fit ``model``, evaluating all test views at :data:`EVAL_TIMES` (+ ``extra_times``) of wall time and at the end."""
    from nerfmeta.fit.evaluate import evaluate_views
    from nerfmeta.fit.loop import fit

    views = list(scene.splits["test"])
    marks = sorted(set(EVAL_TIMES) | set(extra_times))
    times, psnrs, iters = [], [], []

    def evaluate(wall: float, step: int) -> None:
        times.append(round(wall, 4))
        psnrs.append(round(evaluate_views(model, scene, views, background, with_ssim=False).psnr, 4))
        iters.append(step)
        model.train()

    evaluate(build_s, 0)

    def callback(record, model_, state) -> None:
        wall = build_s + record.time_s
        if marks and wall >= marks[0]:
            while marks and wall >= marks[0]:
                marks.pop(0)
            evaluate(wall, record.iter)

    result = fit(model, scene, fit_config, background=background, callbacks=[callback])
    wall = build_s + result.state.time_s
    if iters[-1] != result.state.step:
        times.append(round(wall, 4))
        psnrs.append(round(result.final.psnr, 4))
        iters.append(result.state.step)
    return times, psnrs, iters, wall, result.final.psnr


def grid_arm(arm: str, scene_path: Path, iters: int, extra_times: tuple[float, ...] = (),
             occupancy_net: Path | None = None, start_coarse_iters: int | None = None, zoo_dir: Path | None = None,
             overrides: dict[str, Any] | None = None) -> Curve:
    """Fit the grid arm ``arm`` on a scene; the wall clock starts before the scene's model is built (and, for
    ``occupancy``, before the network ``occupancy_net`` is read). The starts keep ``start_coarse_iters`` coarse steps
    (None: what ``nerfmeta fit`` gives them, :data:`~nerfmeta.priors.start.CARVE_COARSE_ITERS` for the carve and
    :data:`~nerfmeta.priors.occupancy.COARSE_ITERS` for a learned start). ``routed``: the route ``nerfmeta fit SCENE``
    takes with the zoo ``zoo_dir`` (:func:`nerfmeta.route.route_scene`, its time on the clock), then that arm.
    ``overrides``: grid settings (``--set``) given to every arm alike, last, over the arm's own."""
    from nerfmeta.data import load_scene
    from nerfmeta.fields.registry import build_model
    from nerfmeta.fields.voxel_grid import VoxelGridConfig
    from nerfmeta.fit.loop import FitConfig
    from nerfmeta.fit.run import RunConfig
    from nerfmeta.priors.occupancy import boxed_start, hull_inputs, learned_start, learned_start_config, load_occupancy_net
    from nerfmeta.priors.start import CARVE_COARSE_ITERS, carve_grid_start
    from nerfmeta.route import route_scene
    from nerfmeta.zoo import load_zoo

    # Imported above, off the clock: a process's imports are no arm's work (nerfmeta fit imports them at start-up).
    scene = load_scene(scene_path)
    background = torch.tensor(scene.background, dtype=torch.float32)
    fit_config = FitConfig(iters=iters, eval_every=0, checkpoint_every=0, final_ssim=False)
    t0 = time.perf_counter()
    overrides = overrides or {}

    def settled(config: VoxelGridConfig) -> VoxelGridConfig:
        return dataclasses.replace(config, **overrides)

    config = VoxelGridConfig().for_scene(scene)
    note = ""
    if arm == "routed":
        route = route_scene(RunConfig(scene=str(scene_path), backbone="grid"), load_zoo(zoo_dir), 0)
        if route.route not in ("scratch", "occupancy", "carve"):
            raise ValueError(f"{scene_path}: routed to {route.init}, which this bench does not fit")
        arm, note = route.route, f"route {route.route}; "
        if arm == "occupancy":
            occupancy_net = Path(route.init.partition(":")[2])
    if arm not in ("carve", "occupancy"):
        model = build_model("grid", settled(config), scene.bounds, seed=0)
    else:  # as --init carve / --init occupancy do: in the silhouettes' box
        if start_coarse_iters is not None:  # 0 too: no coarse stage at all
            config = dataclasses.replace(config, coarse_iters=start_coarse_iters)
        else:  # as the fit does: the carve keeps scratch's coarse stage, a learned start its own
            config = dataclasses.replace(config, coarse_iters=CARVE_COARSE_ITERS) if arm == "carve" else learned_start_config(config)
        config = settled(config)

        def build(box: torch.Tensor):
            return build_model("grid", config, box, seed=0)

        if arm == "carve":
            model, report = boxed_start(build, scene, hull_inputs, lambda m, _: carve_grid_start(m, scene, background))
        else:
            model, report = learned_start(build, scene, background, load_occupancy_net(occupancy_net))
        note += report.reason
        if not report.applied:  # the route's rule: no start, the scratch defaults
            model = build_model("grid", settled(VoxelGridConfig().for_scene(scene)), scene.bounds, seed=0)
    build_s = time.perf_counter() - t0
    times, psnrs, its, wall, final = timed_fit(model, scene, fit_config, background, build_s=build_s, extra_times=extra_times)
    return Curve(arm, scene_path.name, "", times, psnrs, its, round(build_s, 4), round(wall, 3), round(final, 4), note)


def mlp_arm(arm: str, scene_path: Path, zoo_dir: Path) -> Curve:
    """The zoo's MLP setting (its resolution, model and iterations): ``scratch-nerf`` or ``routed-nerf`` (classified)."""
    from nerfmeta.data import load_scene
    from nerfmeta.fit.loop import FitConfig
    from nerfmeta.fit.run import RunConfig, build_initial_model
    from nerfmeta.route import decide_route, prior_facts, scene_facts, classify_scene
    from nerfmeta.zoo import load_zoo

    zoo = load_zoo(zoo_dir)
    fit = zoo.fit
    config = RunConfig(scene=str(scene_path), backbone="nerf", model=dict(fit["model"]), downscale=2.0,
                       fit=FitConfig(iters=fit["iters"], batch_rays=fit["batch_rays"], eval_every=0, checkpoint_every=0,
                                     final_ssim=False))
    scene = load_scene(scene_path, downscale=2.0)
    background = torch.tensor(scene.background, dtype=torch.float32)
    t0 = time.perf_counter()
    note = "scratch"
    if arm == "routed-nerf":
        priors = {e.name: prior_facts(zoo, e) for e in zoo.entries if e.kind in ("category", "meta")}
        prediction = classify_scene(scene_path, zoo, config.background)
        route = decide_route(prediction, zoo, 0, backbone="nerf", scene=scene_facts(config), priors=priors)
        config = dataclasses.replace(config, init=route.init, freeze=route.freeze)
        note = route.route
    model, _, _ = build_initial_model(config, scene, torch.device("cpu"))
    build_s = time.perf_counter() - t0
    times, psnrs, its, wall, final = timed_fit(model, scene, config.fit, background, build_s=build_s)
    return Curve(arm, scene_path.name, "", times, psnrs, its, round(build_s, 4), round(wall, 3), round(final, 4), note)


# ----- the benchmark ----------------------------------------------------------------------------


def make_collection(out: Path, seed: int, resolution: int, seen: int, unseen: int) -> list[tuple[str, str, Path]]:
    """(name, group, path) of the benchmark's scenes, generating the collection when absent."""
    coll = out / f"collection_{resolution}px_seed{seed}"
    per = max(1, math.ceil(unseen / len(UNSEEN)))
    if not (coll / "collection.json").is_file():
        subprocess.run([str(ROOT / ".venv" / "bin" / "nerfmeta"), "make-collection", str(coll), "--categories",
                        ",".join(SEEN + UNSEEN), "--scenes-per-category", str(per), "--views", "24", "--test-views", "8",
                        "--resolution", str(resolution), "--seed", str(seed), "--workers", "1"], check=True)
    scenes = [(f"{c}_000", "seen", coll / c / f"{c}_000") for c in SEEN[:seen]]
    held = [(f"{c}_{i:03d}", "unseen", coll / c / f"{c}_{i:03d}") for i in range(per) for c in UNSEEN][:unseen]
    return scenes + held


def scene_figures(curves: dict[str, Curve], base: str = "scratch") -> dict[str, dict[str, Any]]:
    """Per arm: time to scratch's final PSNR as a fraction of scratch's wall time, PSNR at 2 s against scratch, worst deficit."""
    b = curves[base]
    target, out = b.final_psnr, {}
    for arm, c in curves.items():
        reach = time_to_reach(c.times, c.psnrs, target)
        at2, b2 = c.at(2.0), b.at(2.0)
        out[arm] = {
            "final_psnr": c.final_psnr, "wall_s": c.wall_s, "build_s": c.build_s, "target_psnr": target,
            "reach_fraction": None if reach is None else round(reach / b.wall_s, 4),
            "psnr_2s": at2, "gain_2s_db": None if at2 is None or b2 is None else round(at2 - b2, 3),
            "worst_deficit_db": round(worst_deficit(c, b), 3),
            "worst_deficit_best_db": round(worst_deficit(best_so_far(c), best_so_far(b)), 3),
            "worst_deficit_iters_db": round(worst_deficit_by_iteration(c, b), 3), "note": c.note,
        }
    return out


def mean_sd(values: list[float]) -> str:
    vals = [v for v in values if v is not None]
    if not vals:
        return "n/a"
    sd = statistics.stdev(vals) if len(vals) > 1 else 0.0
    return f"{statistics.mean(vals):.2f} +- {sd:.2f}"


def table(results: dict[str, Any], arms: tuple[str, ...], base: str) -> list[str]:
    """Markdown rows: per scene and per group (mean +- sd) against ``base``."""
    lines = [f"| scene | group | arm | final PSNR (dB) | {base} final | time to {base}'s final / {base}'s time | ({base} itself) | "
             f"PSNR at 2 s | {base} at 2 s | worst deficit (dB) | worst deficit, best so far (dB) | worst deficit, equal iterations (dB) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    groups: dict[tuple[str, str], list[dict]] = {}
    for name, res in results.items():
        figs = res["figures"]
        for arm in arms:
            if arm == base or arm not in figs:
                continue
            f = figs[arm]
            groups.setdefault((res["group"], arm), []).append(f)
            frac = "never" if f["reach_fraction"] is None else f"{f['reach_fraction']:.2f}"
            at2 = "n/a" if f["psnr_2s"] is None else f"{f['psnr_2s']:.2f}"
            b2 = figs[base]["psnr_2s"]
            own = figs[base]["reach_fraction"]
            lines.append(f"| {name} | {res['group']} | {arm} | {f['final_psnr']:.2f} | {f['target_psnr']:.2f} | {frac} | {own:.2f} | {at2} | "
                         f"{'n/a' if b2 is None else f'{b2:.2f}'} | {f['worst_deficit_db']:+.2f} | {f['worst_deficit_best_db']:+.2f} | "
                         f"{f.get('worst_deficit_iters_db', math.nan):+.2f} |")
    lines += ["", "| group | arm | n | reached | time fraction (reached) | gain at 2 s (dB) | worst deficit (dB) | "
              "within 0.1 dB (best so far; equal iterations) |", "|---|---|---|---|---|---|---|---|"]
    for (group, arm), fs in groups.items():
        reached = [f["reach_fraction"] for f in fs if f["reach_fraction"] is not None]
        lines.append(f"| {group} | {arm} | {len(fs)} | {len(reached)}/{len(fs)} | {mean_sd(reached)} | "
                     f"{mean_sd([f['gain_2s_db'] for f in fs])} | {mean_sd([f['worst_deficit_db'] for f in fs])} | "
                     f"{sum(f['worst_deficit_db'] <= 0.1 for f in fs)}/{len(fs)} "
                     f"({sum(f['worst_deficit_best_db'] <= 0.1 for f in fs)}/{len(fs)}; "
                     f"{sum(f.get('worst_deficit_iters_db', math.inf) <= 0.1 for f in fs)}/{len(fs)}) |")
    return lines


def fit_scene(job: tuple) -> tuple[str, dict[str, Any]]:
    """Every arm on one scene, interleaved (the first arm rotating with the scene's index), one torch thread."""
    k, name, group, path, arms, iters, zoo, occupancy_net, start_coarse_iters, zoo_dir, overrides = job
    torch.set_num_threads(1)
    from nerfmeta.fields.voxel_grid import VoxelGrid

    VoxelGrid.warm_up()  # the worker's once-per-process cost (compiled lookups), on neither arm's clock
    order = arms[k % len(arms):] + arms[: k % len(arms)]
    curves = {arm: dataclasses.replace(grid_arm(arm, path, iters, occupancy_net=occupancy_net, start_coarse_iters=start_coarse_iters,
                                                zoo_dir=zoo_dir, overrides=overrides), arm=arm)
              for arm in order}
    mlp: dict[str, Curve] = {}
    if zoo is not None:
        for arm in (("scratch-nerf", "routed-nerf") if k % 2 == 0 else ("routed-nerf", "scratch-nerf")):
            mlp[arm] = mlp_arm(arm, path, zoo)
    res = {"group": group, "curves": {a: dataclasses.asdict(c) for a, c in {**curves, **mlp}.items()},
           "figures": scene_figures(curves)}
    if mlp:
        res["mlp_figures"] = scene_figures(mlp, base="scratch-nerf")
    return name, res


def tables(results: dict[str, Any], arms: tuple[str, ...], mlp: bool) -> list[str]:
    """The grid table against scratch, then (``mlp``) the MLP table against scratch-nerf."""
    lines = table(results, arms, "scratch")
    if mlp:
        mlp_results = {n: {**r, "figures": r["mlp_figures"]} for n, r in results.items()}
        lines += [""] + table(mlp_results, ("scratch-nerf", "routed-nerf"), "scratch-nerf")
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "bench_priors")
    p.add_argument("--seed", type=int, default=11, help="collection seed (not one used while designing: 7)")
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--seen", type=int, default=6, help="seen-category scenes (one per category, up to 6)")
    p.add_argument("--unseen", type=int, default=5, help="held-out-category scenes")
    p.add_argument("--iters", type=int, default=1000)
    p.add_argument("--arms", default=",".join(GRID_ARMS))
    p.add_argument("--mlp", action="store_true", help="also the zoo's NeRF-MLP setting: scratch-nerf vs routed-nerf")
    p.add_argument("--zoo", type=Path, default=ROOT / "model_zoo")
    p.add_argument("--only", default="", help="comma-separated scene names (default: all)")
    p.add_argument("--workers", type=int, default=2, help="scenes fitted at once (one torch thread each)")
    p.add_argument("--report", action="store_true", help="only print the tables of OUT/results.json")
    p.add_argument("--occupancy-net", default=None, metavar="NET.safetensors|zoo",
                   help="add the learned occupancy start as an arm: 'zoo' for --zoo's network (what --init occupancy "
                   "uses), or a file from scripts/probe_occupancy_start.py train")
    p.add_argument("--start-coarse-iters", type=int, default=None, metavar="N",
                   help="coarse steps the carve and occupancy arms keep (default: as nerfmeta fit gives them, 100 for the "
                   "carve and 200 for a learned start)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a grid setting, as `nerfmeta fit --set` takes it, given to every grid arm alike (scratch "
                   "included, so the comparison stays fair); repeatable")
    args = p.parse_args(argv)
    if args.report:
        doc = json.loads((args.out / "results.json").read_text())
        for res in doc["results"].values():  # figures again from the curves (columns added since the run)
            res["figures"] = scene_figures({a: Curve(**c) for a, c in res["curves"].items() if a in doc["arms"]})
        print("\n".join(tables(doc["results"], tuple(doc["arms"]), any("mlp_figures" in r for r in doc["results"].values()))))
        return 0
    torch.set_num_threads(1)
    from nerfmeta.config import parse_overrides
    from nerfmeta.errors import ConfigError
    from nerfmeta.fields.voxel_grid import VoxelGridConfig

    try:  # a bad setting named before any scene is made
        overrides = parse_overrides(args.set, VoxelGridConfig)
    except ConfigError as err:
        p.error(str(err))
    if args.occupancy_net is not None:  # a bad file named before any fit starts
        from nerfmeta.priors.occupancy import load_occupancy_net
        from nerfmeta.zoo import load_zoo

        try:
            if args.occupancy_net == "zoo":
                entry = load_zoo(args.zoo).occupancy
                if entry is None:
                    raise ConfigError(f"{args.zoo}: the zoo has no occupancy network")
                args.occupancy_net = entry.path / "model.safetensors"
            args.occupancy_net = Path(args.occupancy_net)
            load_occupancy_net(args.occupancy_net)
        except ConfigError as err:
            p.error(str(err))
    arms = tuple(dict.fromkeys(tuple(a for a in args.arms.split(",") if a) + (("occupancy",) if args.occupancy_net else ())))
    unknown = sorted(set(arms) - {"scratch", "carve", "occupancy", "routed"})
    if unknown or ("occupancy" in arms and args.occupancy_net is None):
        p.error(f"--arms: {', '.join(unknown) or 'occupancy'}: the grid arms are scratch, carve, routed and (with "
                "--occupancy-net) occupancy")
    load_before = os.getloadavg()
    t_start = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    scenes = make_collection(args.out, args.seed, args.resolution, args.seen, args.unseen)
    if args.only:
        scenes = [s for s in scenes if s[0] in args.only.split(",")]
    results: dict[str, Any] = {}
    jobs = [(k, name, group, path, arms, args.iters, args.zoo if args.mlp else None, args.occupancy_net,
             args.start_coarse_iters, args.zoo, overrides)
            for k, (name, group, path) in enumerate(scenes)]
    with ProcessPoolExecutor(args.workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        for name, res in pool.map(fit_scene, jobs):
            results[name] = res
            figs = res["figures"]
            print(name, {a: (f["final_psnr"], f["reach_fraction"], f["gain_2s_db"], f["worst_deficit_db"]) for a, f in figs.items()},
                  flush=True)
            (args.out / "results.json").write_text(json.dumps(results, indent=1))
    doc = {"date": datetime.date.today().isoformat(), "load_before": load_before, "load_after": os.getloadavg(),
           "minutes": round((time.perf_counter() - t_start) / 60, 2), "seed": args.seed, "resolution": args.resolution,
           "iters": args.iters, "arms": arms, "start_coarse_iters": args.start_coarse_iters, "set": args.set,
           "results": results}
    (args.out / "results.json").write_text(json.dumps(doc, indent=1))
    lines = tables(results, arms, args.mlp)
    (args.out / "table.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"load {load_before} -> {doc['load_after']}, {doc['minutes']} min")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
