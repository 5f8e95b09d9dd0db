"""Classify-and-fit on new scenes with the shipped zoo, against the scratch grid and the scratch MLP; into BENCHMARKS.md.

Workload: 10 scenes of the zoo's known categories (every known category at least once) and 5 of
its unseen categories, generated with ``--seed`` (default 1; the zoo is built from seed 0, so
none of these objects was seen by any zoo model), at the zoo collection's size (64 x 64, 16 + 8
views). For each scene the script records two things:

- the **default route** (``nerfmeta fit SCENE``: ``--backbone grid``), which :func:`nerfmeta.route.route_scene`
  decides without fitting: with a zoo of NeRF-MLP priors it is the scratch grid, so it is the baseline fit itself;
- the **MLP route** (``nerfmeta fit SCENE --backbone nerf --compare scratch,scratch-nerf``, the library call
  behind it): the scene is classified and fitted from its category model or the meta-learned initialisation
  with the zoo's fit settings (its iterations, ray batch, evaluation interval), beside the **scratch grid**
  (the best scratch fit, given the routed fit's wall-clock time) and the **scratch MLP** with the routed
  fit's settings (the source work's baseline).

Then ``nerfmeta report`` gathers all runs against the scratch grid on the wall-clock axis (classification
and loading of the start included). The script prints and (``--write``) records in BENCHMARKS.md:
routing accuracy (right route: a known category to its own category model, an unseen one to the
meta-learned initialisation), final test PSNRs of the three fits, how far the routed fit is behind the
scratch grid at any evaluation time, and the speed-ups to the scratch MLP's final PSNR (the source
work's measure).

Usage::

    .venv/bin/python scripts/bench_routing.py [--out runs/bench_routing] [--seed 1] [--workers 1] [--write]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

SECTION = "## Classify-and-fit with the model zoo"
MACHINE = "2-core CPU, no GPU"
N_KNOWN, N_UNSEEN = 10, 5
BASELINES = ("scratch", "scratch-nerf")
"""The fits beside each routed MLP fit: the scratch grid (the fair baseline) and the scratch MLP (the source work's)."""
ZOO_MARKER = "bench_zoo_sha256.txt"
"""A routed run's record of the zoo manifest it was fitted with: a run is reused only with the same zoo."""


def make_scenes(out: Path, seed: int, zoo) -> list[tuple[str, str, Path]]:
    """(name, category, path) of the benchmark scenes, generated into ``out/scenes``."""
    from nerfmeta.collection.generate import CollectionConfig, generate_collection, load_collection

    recipe = zoo.manifest["recipe"]
    picked = []
    for group, cats, per, n in (("known", zoo.manifest["known_categories"], 2, N_KNOWN), ("unseen", zoo.manifest["unseen_categories"], 3, N_UNSEEN)):
        config = CollectionConfig(categories=tuple(cats), scenes_per_category=per, views=recipe["views"], test_views=recipe["test_views"],
                                  resolution=recipe["resolution"], seed=seed, val_fraction=0.0, test_fraction=0.0)
        index = out / "scenes" / group / "collection.json"
        if not index.is_file():
            generate_collection(config, out / "scenes" / group, overwrite=True)
        coll = load_collection(index)
        records = sorted(coll.scenes, key=lambda r: (r.index, cats.index(r.category)))[:n]
        picked += [(r.name, r.category, coll.scene_path(r)) for r in records]
    return picked


def fit_one(job: tuple[str, str, str, str]) -> dict:
    import torch

    from nerfmeta.fit.loop import FitConfig
    from nerfmeta.fit.run import RunConfig
    from nerfmeta.report.snapshots import SNAPSHOT_ITERS
    from nerfmeta.route import DEFAULT_BACKBONE, classify_and_fit, route_scene
    from nerfmeta.zoo import load_zoo

    from nerfmeta.io import sha256_file

    torch.set_num_threads(1)
    name, scene, zoo_dir, out = job
    zoo_key, marker = sha256_file(Path(zoo_dir) / "manifest.json"), Path(out) / ZOO_MARKER
    zoo = load_zoo(zoo_dir)
    default = route_scene(RunConfig(scene=scene, backbone=DEFAULT_BACKBONE, downscale=2.0), zoo, 0).as_json()
    done = all((Path(out) / "compare" / b / "summary.json").is_file() for b in BASELINES)
    if done and (Path(out) / "summary.json").is_file() and "comparison" in json.loads((Path(out) / "summary.json").read_text()) \
            and marker.is_file() and marker.read_text() == zoo_key:
        return {**json.loads((Path(out) / "summary.json").read_text()), "default_route": default}  # fitted with this very zoo
    fit = zoo.fit
    config = RunConfig(scene=scene, backbone=zoo.backbone, model=dict(fit["model"]), downscale=2.0,
                       fit=FitConfig(iters=fit["iters"], batch_rays=fit["batch_rays"], eval_every=fit["eval_every"], checkpoint_every=0,
                                     eval_views=fit.get("eval_views", 4)),
                       snapshot_iters=tuple(i for i in SNAPSHOT_ITERS if i <= fit["iters"]))
    summary = classify_and_fit(config, out, zoo=zoo, compare=BASELINES, overwrite=True)
    marker.write_text(zoo_key)
    return {**summary, "default_route": default}


def meta_on_known(job: tuple[str, str, str, str]) -> dict:
    """Control: a known-category scene fitted from the meta-initialisation instead, against the same scratch fits."""
    import torch

    from nerfmeta.fit.run import RunConfig, run_fit
    from nerfmeta.io import sha256_file
    from nerfmeta.report.compare import write_comparison

    torch.set_num_threads(1)
    name, scene, zoo_dir, routed_out = job
    out = Path(routed_out).parent.parent / "meta_on_known" / name
    zoo_key, marker = sha256_file(Path(zoo_dir) / "manifest.json"), out.parent / f"{name}.{ZOO_MARKER}"
    if not (out / "summary.json").is_file() or "comparison" not in json.loads((out / "summary.json").read_text()) \
            or not marker.is_file() or marker.read_text() != zoo_key:  # fitted with another zoo's meta-initialisation
        routed = RunConfig.from_json(json.loads((Path(routed_out) / "config.json").read_text()))
        config = RunConfig(**{**{f: getattr(routed, f) for f in routed.__dataclass_fields__}, "init": f"meta:{Path(zoo_dir) / 'meta'}",
                              "freeze": 0})
        run_fit(config, out, overwrite=True)
        write_comparison(out, {b: Path(routed_out) / "compare" / b for b in BASELINES}, out, name="meta")
        marker.write_text(zoo_key)
    return json.loads((out / "summary.json").read_text())


def main(argv: list[str] | None = None) -> int:
    from nerfmeta.zoo import load_zoo, resolve_zoo_path

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "bench_routing")
    p.add_argument("--zoo", default=None)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--write", action="store_true")
    p.add_argument("--meta-on-known", action="store_true",
                   help="control: also fit the known-category scenes from the meta-initialisation (against the same scratch fits)")
    args = p.parse_args(argv)
    zoo_dir = resolve_zoo_path(args.zoo)
    if zoo_dir is None:
        raise SystemExit("no model zoo: build one with scripts/build_model_zoo")
    zoo = load_zoo(zoo_dir)
    load_before = os.getloadavg()
    t0 = time.perf_counter()
    scenes = make_scenes(args.out, args.seed, zoo)
    jobs = [(name, str(path), str(zoo_dir), str(args.out / "runs" / name)) for name, _, path in scenes]
    if args.workers > 1:
        with ProcessPoolExecutor(args.workers) as pool:
            summaries = list(pool.map(fit_one, jobs))
    else:
        summaries = [fit_one(j) for j in jobs]
    wall = time.perf_counter() - t0
    load_after = os.getloadavg()
    timing = args.out / "timing.json"
    if wall < 60 and timing.is_file():  # every fit was reused: report the run that made them
        saved = json.loads(timing.read_text())
        wall, load_before, load_after = saved["wall_s"], saved["load_before"], saved["load_after"]
    else:
        timing.write_text(json.dumps({"wall_s": wall, "load_before": load_before, "load_after": load_after}))

    controls = [meta_on_known(j) for j, (_, cat, _) in zip(jobs, scenes) if cat in zoo.manifest["known_categories"]] \
        if args.meta_on_known else []
    from nerfmeta.cli import main as cli

    report_dir = args.out / "report"
    code = cli(["report", *[j[3] for j in jobs], "--out", str(report_dir)])
    if code != 0:
        raise SystemExit(f"nerfmeta report failed with exit code {code}")
    report = json.loads((report_dir / "report.json").read_text())
    lines = render_section(scenes, summaries, report, zoo, args, wall, load_before, load_after)
    if controls:
        lines += control_table(scenes, summaries, controls, args.out / "runs")
    print("\n".join(lines))
    if args.write:
        from benchlib.sections import write_section as write_benchmark_section
        write_benchmark_section(ROOT / "BENCHMARKS.md", SECTION, "\n".join(lines))
        print(f"updated BENCHMARKS.md ({SECTION})")
    return 0


def mlp_comparison(run: str | Path, name: str, scratch_nerf: str | Path) -> dict:
    """``run``'s fit against the scratch MLP with the same settings (the source work's measure), by iterations."""
    from nerfmeta.report.compare import compare_logs, load_fit_log

    return compare_logs({name: load_fit_log(run), "scratch-nerf": load_fit_log(scratch_nerf)}, baseline="scratch-nerf", method=name)


def render_section(scenes, summaries, report, zoo, args, wall, load_before, load_after) -> list[str]:
    known = set(zoo.manifest["known_categories"])
    rows, right, behind, default_scratch = [], 0, [], 0
    for (name, category, _), s in zip(scenes, summaries):
        r = s["route"]
        ok = (r["route"] == "category" and r["category"] == category) if category in known else r["route"] == "meta"
        right += ok
        default_scratch += s["default_route"]["route"] == "scratch"
        comp = s.get("comparison") or {}
        methods = comp.get("methods", {})
        final = {k: (methods.get(k) or {}).get("final_test_psnr") for k in ("scratch", "scratch-nerf", "routed")}
        run = args.out / "runs" / name
        mlp = mlp_comparison(run, "routed", run / "compare" / "scratch-nerf")
        behind.append(comp.get("behind_wall_db") or 0.0)
        rows.append(f"| {name} | {'known' if category in known else 'unseen'} | {s['default_route']['route']} | {r['route']}"
                    f"{' (' + r['category'] + ')' if r['route'] == 'category' else ''} | {'yes' if ok else '**no**'} | "
                    f"{r['confidence']:.2f} | {_fmt(final, 'scratch')} | {_fmt(final, 'scratch-nerf')} | {_fmt(final, 'routed')} | "
                    f"{_fmt(comp, 'behind_wall_db')} | {_speed(mlp, 'speedup_iters')} | {_speed(mlp, 'speedup_time')} |")
    date = datetime.date.today().isoformat()
    flag = " --meta-on-known" if args.meta_on_known else ""
    fit = zoo.fit
    out = [
        SECTION, "",
        f"```\n.venv/bin/python scripts/bench_routing.py --seed {args.seed} --workers {args.workers}{flag} --write\n```", "",
        f"Machine: {MACHINE}; date {date}; wall time {wall / 60:.1f} min for {len(scenes)} scenes x 3 fits "
        f"({args.workers} at a time, one torch thread each); load average before {_load(load_before)}, after {_load(load_after)}.",
        f"Zoo: `{zoo.root.name}/` built {zoo.manifest.get('date')} from seed {zoo.manifest.get('seed')}; scenes generated from seed "
        f"{args.seed} (never seen by any zoo model). The MLP route and the scratch MLP: {fit['backbone']} {json.dumps(fit['model'])}, "
        f"Adam, {fit['batch_rays']} rays/iteration, {fit['iters']} iterations, test PSNR every {fit['eval_every']} on all 8 test "
        "views (32 x 32), seed 0 (they differ only in the starting point and frozen layers). The scratch grid: its tuned "
        "defaults, given the routed fit's wall-clock time (classification and loading included), test PSNR at the same "
        "interval.", "",
        f"**Default route** (`nerfmeta fit SCENE`, the grid): **scratch on {default_scratch}/{len(scenes)} scenes** (the zoo holds "
        "no grid prior), i.e. the scratch grid itself: never behind it, by construction. **MLP route** (`--backbone nerf`, the "
        f"source work's system): classification **{right}/{len(scenes)} right** ({100 * right / len(scenes):.0f} %); behind the "
        f"scratch grid on the wall-clock axis on {sum(b > 0.1 for b in behind)}/{len(scenes)} scenes by more than 0.1 dB "
        f"(median worst gap {statistics.median(behind):.2f} dB).", "",
        "| scene | group | default route | MLP route | right | p | scratch grid final (dB) | scratch MLP final (dB) | "
        "MLP route final (dB) | MLP route behind the grid, worst (dB, wall clock) | MLP route speed-up over scratch MLP (iters) | (time) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
        *rows, "",
        "Speed-ups over the scratch MLP are the iterations (optimisation time) the scratch MLP needs to reach its own final "
        "PSNR over what the MLP route needs. The tables below are `nerfmeta report`'s, against the **scratch grid** on the "
        "wall-clock axis.", "",
    ]
    out += report_tables(args.out / "report" / "report.md")
    docs = ROOT / "docs" / "bench"
    docs.mkdir(parents=True, exist_ok=True)
    for name in ("psnr_vs_iter.png", "psnr_vs_time.png"):
        shutil.copyfile(args.out / "report" / name, docs / f"routing_{name}")
    out += ["", "![routed vs scratch, PSNR against iterations](docs/bench/routing_psnr_vs_iter.png)",
            "![routed vs scratch, PSNR against time](docs/bench/routing_psnr_vs_time.png)", ""]
    return out


def control_table(scenes, summaries, controls, runs: Path) -> list[str]:
    """Known-category scenes: the category route against the meta-initialisation, both against the same scratch MLP fit."""
    out = ["### Control: known categories from the meta-initialisation", "",
           "The 10 known-category scenes fitted again from the meta-learned initialisation (same settings, same scratch fits); "
           "speed-ups over the scratch MLP:", "",
           "| scene | routed | routed final (dB) | meta final (dB) | routed speed-up (iters) | meta speed-up (iters) |", "|---|---|---|---|---|---|"]
    known = [(n, s) for (n, _, _), s in zip(scenes, summaries) if s["route"]["known_categories"] and n.split("_")[0] in s["route"]["known_categories"]]
    ratios = {"routed": [], "meta": []}
    for (name, s), c in zip(known, controls):
        methods, run = s["comparison"]["methods"], runs / name
        rc = mlp_comparison(run, "routed", run / "compare" / "scratch-nerf")
        mc = mlp_comparison(runs.parent / "meta_on_known" / name, "meta", run / "compare" / "scratch-nerf")
        rf = methods["routed"]["final_test_psnr"]
        mf = c["comparison"]["methods"]["meta"]["final_test_psnr"]
        out.append(f"| {name} | {s['route']['route']} | {_fmt({'v': rf}, 'v')} | {_fmt({'v': mf}, 'v')} | "
                   f"{_speed(rc, 'speedup_iters')} | {_speed(mc, 'speedup_iters')} |")
        for key, comp in (("routed", rc), ("meta", mc)):
            if comp.get("speedup_iters"):
                ratios[key].append(comp["speedup_iters"])
    out += ["", "Geometric-mean speed-up (iterations) over the scenes that reach the scratch MLP's final PSNR: " + "; ".join(
        f"{k} {statistics.geometric_mean(v):.2f}x ({len(v)}/{len(known)})" for k, v in ratios.items() if v), ""]
    return out


def report_tables(path: Path) -> list[str]:
    """The speed-up and final-PSNR tables of ``nerfmeta report``'s report.md, headings demoted."""
    lines = path.read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("## Speedup"))
    end = next(i for i, line in enumerate(lines) if line.startswith("## Curves"))
    return ["#" + line if line.startswith("## ") else line for line in lines[start:end]]


def _fmt(d: dict, key: str) -> str:
    v = d.get(key)
    return "n/a" if v is None else f"{v:.2f}"


def _speed(comp: dict, key: str) -> str:
    v = comp.get(key)
    return "never" if v is None else f"{v:.1f}x"


def _load(load) -> str:
    return " / ".join(f"{v:.1f}" for v in load)




if __name__ == "__main__":
    sys.exit(main())
