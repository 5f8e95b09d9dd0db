"""Reports over many fit runs (``nerfmeta report``): mean curves, speedups per route, routing accuracy.

Each RUN is a fit run folder. Its own fit is the *main* fit, named ``routed`` when its
``summary.json`` has a ``route`` (a classify-and-fit run), else by its ``init`` (``scratch``,
``category``, ``meta``); every ``RUN/compare/NAME/`` fit run folder beside it is a compared fit
named ``NAME`` (e.g. ``compare/scratch``, the voxel grid from scratch given the same wall-clock time, and
``compare/scratch-nerf``, the MLP from scratch with the routed fit's settings).

``summary.json`` keys read (all optional except what a fit always writes):

- ``category``: the scene's true category (written by every fit from the scene; None if unknown).
- ``route``: written by the classify-and-fit code, an object with
    - ``route``: the decision, ``"category"``, ``"meta"`` or ``"scratch"``;
    - ``category``: the category whose model was used (the classifier's prediction; None unless
      ``route == "category"``);
    - ``known_categories``: the categories the classifier knows (has a category model for);
    - ``unknown``: the classifier's unknown decision (absent or None when no classifier answered);
    - ``confidence`` (float) and ``probabilities`` ({category: p}): shown, not scored.

Where the classifier answered (``unknown`` is true or false), the *classifier's answer* is scored:
a known true category (in ``known_categories``) is right when classified as itself and not
flagged unknown, an unknown one when flagged unknown; the route may still be scratch or the meta
initialisation when a prior does not apply to the scene (``route.checks``), which is not a
routing error. Without ``unknown`` (older runs) the route is scored: right when a known true
category is routed to ``category`` with that category, or an unknown one to ``meta``. Runs
without ``route``, with empty ``route.known_categories`` (no classifier asked, e.g. a zoo of
another backbone) or without a true ``category`` are not scored.

Runs are grouped by ``route.route`` (``no route`` for plain fits). Curves are test PSNR, mean +-
sd over the runs of a group (see :func:`nerfmeta.report.curves.mean_band`), against iterations,
optimisation time (``time_s``) and wall-clock time (``wall_s``: optimisation time plus the fit's
classification and loading of its start, the axis ``psnr_vs_time.png`` plots); speedups are the
main fit's against the ``baseline`` compared fit (rules in :mod:`nerfmeta.report.curves`).
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from nerfmeta.errors import ConfigError
from nerfmeta.io import write_bytes_atomic, write_json
from nerfmeta.report.compare import REPORT_ITERS, RULES, FitLog, compare_logs, load_fit_log
from nerfmeta.report.curves import X_KEYS, Band, mean_band
from nerfmeta.report.plots import plot_psnr_bands

log = logging.getLogger(__name__)

WALL = "wall_s"
"""Curve key of the wall-clock axis: a fit's ``time_s`` plus what it spent before its first step (the fair axis)."""

COMPARE_DIR = "compare"
NO_ROUTE = "no route"
ALL = "all"

ROUTING_RULE = ("right: a known true category classified as itself and not flagged unknown, or an unknown one "
                "(not in route.known_categories) flagged unknown (runs without route.unknown: routed to 'category' with "
                "that category, or to 'meta'); runs without route, known_categories or a true category are not scored")


@dataclass(frozen=True)
class ReportRun:
    """One RUN of a report: its main fit and the fits in ``RUN/compare/``.

    Attributes:
        path: the RUN folder.
        main: its own fit.
        name: the main fit's method name (``routed``, or its ``init``).
        compared: compared fits by name (``RUN/compare/NAME/``).
    """

    path: Path
    main: FitLog
    name: str
    compared: dict[str, FitLog]

    @property
    def route(self) -> dict[str, Any] | None:
        route = self.main.summary.get("route")
        return route if isinstance(route, dict) else None

    @property
    def group(self) -> str:
        route = self.route
        return str(route["route"]) if route and route.get("route") else NO_ROUTE

    @property
    def fits(self) -> dict[str, FitLog]:
        return {self.name: self.main, **self.compared}


def load_report_run(path: str | Path) -> ReportRun:
    """Read a RUN folder and its ``compare/*`` fits.

    Raises:
        ConfigError: the RUN (or a ``compare/NAME`` folder in it) is not a finished fit run, or a
            compared fit has the main fit's name.
    """
    path = Path(path)
    if not path.is_dir():
        raise ConfigError(f"{path}: no such run folder; pass folders written by 'nerfmeta fit'")
    main = load_fit_log(path)
    name = "routed" if "route" in main.summary else str(main.summary.get("init") or "fit")
    compared = {}
    if (path / COMPARE_DIR).is_dir():
        for sub in sorted(p for p in (path / COMPARE_DIR).iterdir() if p.is_dir()):
            if sub.name == name:
                raise ConfigError(f"{sub}: has the main fit's name {name!r}; rename the compared fit")
            compared[sub.name] = load_fit_log(sub)
    return ReportRun(path, main, name, compared)


def route_correct(summary: Mapping[str, Any]) -> bool | None:
    """Whether the run's route is right (see the module rule); None when it cannot be scored."""
    route, true = summary.get("route"), summary.get("category")
    if not isinstance(route, Mapping) or true is None or not route.get("route") or not route.get("known_categories"):
        return None
    if route.get("unknown") is not None:
        if true in route["known_categories"]:
            return not route["unknown"] and route.get("category") == true
        return bool(route["unknown"])
    if true in route["known_categories"]:
        return route["route"] == "category" and route.get("category") == true
    return route["route"] == "meta"


def _ratio(n: int, d: int) -> float | None:
    return None if d == 0 else round(n / d, 4)


def routing_accuracy(runs: Sequence[ReportRun]) -> dict[str, Any]:
    """Routing accuracy over the scorable runs, overall and for known / unknown true categories."""
    scored = [(r, route_correct(r.main.summary)) for r in runs]
    scored = [(r, ok) for r, ok in scored if ok is not None]
    known = [ok for r, ok in scored if r.main.summary["category"] in r.route["known_categories"]]
    unknown = [ok for r, ok in scored if r.main.summary["category"] not in r.route["known_categories"]]
    n_correct = sum(ok for _, ok in scored)
    return {
        "n_scored": len(scored), "n_correct": n_correct, "accuracy": _ratio(n_correct, len(scored)),
        "known": {"n": len(known), "n_correct": sum(known), "accuracy": _ratio(sum(known), len(known))},
        "unknown": {"n": len(unknown), "n_correct": sum(unknown), "accuracy": _ratio(sum(unknown), len(unknown))},
        "n_unscored": len(runs) - len(scored),
        "rule": ROUTING_RULE,
    }


def _mean_sd(values: Sequence[float]) -> tuple[float | None, float | None]:
    if not values:
        return None, None
    arr = np.asarray(values, dtype=float)
    sd = float(arr.std(ddof=1)) if len(arr) > 1 else 0.0
    return round(float(arr.mean()), 4), round(sd, 4)


def _speedup_stats(values: Sequence[float | None]) -> dict[str, Any]:
    reached = [v for v in values if v is not None]
    return {
        "n_reached": len(reached),
        "mean": None if not reached else round(sum(reached) / len(reached), 4),
        "geomean": None if not reached else round(math.exp(sum(math.log(v) for v in reached) / len(reached)), 4),
        "min": None if not reached else round(min(reached), 4),
        "max": None if not reached else round(max(reached), 4),
    }


def run_comparison(run: ReportRun, baseline: str, iters: Sequence[int]) -> dict[str, Any] | None:
    """:func:`~nerfmeta.report.compare.compare_logs` of the run's main fit against its ``baseline``
    compared fit (rules left out), or None when the run has no such fit."""
    if baseline not in run.compared:
        return None
    out = compare_logs(run.fits, baseline=baseline, method=run.name, iters=iters)
    out.pop("rules")
    return out


def summarize_group(runs: Sequence[ReportRun], comparisons: Sequence[dict | None], methods: Sequence[str]) -> dict[str, Any]:
    """The numbers of one group of runs: per-method finals and mean curves, and the main fits' speedups."""
    out: dict[str, Any] = {"n_runs": len(runs), "methods": {}, "speedup": None}
    for m in methods:
        fits = [r.fits[m] for r in runs if m in r.fits]
        if not fits:
            continue
        psnr_mean, psnr_sd = _mean_sd([f.final_test_psnr for f in fits if f.final_test_psnr is not None])
        time_mean, time_sd = _mean_sd([float(f.summary["time_s"]) for f in fits if f.summary.get("time_s") is not None])
        iters_mean, _ = _mean_sd([f.last_iter for f in fits])
        bands = {key: mean_band([f.evaluations for f in fits], key) for key in X_KEYS}
        bands[WALL] = mean_band([f.wall_evaluations for f in fits], "time_s")
        out["methods"][m] = {
            "n_runs": len(fits), "final_test_psnr_mean": psnr_mean, "final_test_psnr_sd": psnr_sd,
            "time_s_mean": time_mean, "time_s_sd": time_sd, "iters_mean": iters_mean,
            "curves": {key: None if b is None else b.as_json() for key, b in bands.items()},
        }
    comps = [c for c in comparisons if c is not None]
    if comps:
        out["speedup"] = {
            "n_compared": len(comps),
            "iters": _speedup_stats([c["speedup_iters"] for c in comps]),
            "time": _speedup_stats([c["speedup_time"] for c in comps]),
            "wall": _speedup_stats([c.get("speedup_wall") for c in comps]),
            "n_ahead_at_every_eval": sum(1 for c in comps if c["ahead_at_every_eval"]),
            "n_ahead_wall": sum(1 for c in comps if c.get("ahead_wall")),
            "behind_wall_db_max": max((c["behind_wall_db"] for c in comps if c.get("behind_wall_db") is not None), default=None),
        }
    return out


def build_report(runs: Sequence[ReportRun], *, baseline: str = "scratch", iters: Sequence[int] = REPORT_ITERS) -> dict[str, Any]:
    """All the numbers of a report (``report.json`` without the plot file names)."""
    methods: list[str] = []
    for r in runs:
        methods += [m for m in r.fits if m not in methods]
    comparisons = [run_comparison(r, baseline, iters) for r in runs]
    groups = sorted({r.group for r in runs})
    per_group = {ALL: summarize_group(runs, comparisons, methods)}
    if groups != [NO_ROUTE]:
        for g in groups:
            idx = [i for i, r in enumerate(runs) if r.group == g]
            per_group[g] = summarize_group([runs[i] for i in idx], [comparisons[i] for i in idx], methods)
    run_entries = []
    for r, comp in zip(runs, comparisons):
        route = r.route or {}
        run_entries.append({
            "run": str(r.path), "scene": r.main.summary.get("scene"), "category": r.main.summary.get("category"),
            "group": r.group, "main": r.name,
            "route": {k: route.get(k) for k in ("route", "category", "confidence")} if route else None,
            "route_correct": route_correct(r.main.summary),
            "final_test_psnr": {m: f.final_test_psnr for m, f in r.fits.items()},
            "comparison": comp,
        })
    return {"n_runs": len(runs), "baseline": baseline, "methods": methods, "groups": per_group,
            "routing": routing_accuracy(runs), "runs": run_entries, "rules": {**RULES, "routing": ROUTING_RULE,
            "curves": "test PSNR interpolated onto a grid inside every run's evaluated range; mean +- sample sd (ddof=1)"}}


def _backbones(report: Mapping[str, Any], baseline: str) -> str:
    """The baseline's backbone(s) over the runs' comparisons, e.g. ``grid``."""
    names = sorted({str(r["comparison"].get("baseline_backbone")) for r in report["runs"] if r.get("comparison")})
    return "/".join(names) if names else "?"


def _slug(group: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in group)


def write_report(
    run_dirs: Sequence[str | Path], out_dir: str | Path, *, baseline: str = "scratch", iters: Sequence[int] = REPORT_ITERS
) -> dict[str, Any]:
    """Read the runs, write the plots, ``report.md`` and ``report.json`` into ``out_dir``; return the numbers.

    Plots: ``psnr_vs_iter.png`` / ``psnr_vs_time.png`` over all runs and, when the runs have
    more than one group, ``psnr_vs_iter_GROUP.png`` / ``psnr_vs_time_GROUP.png`` per group.

    Raises:
        ConfigError: no runs, or a run folder that is not a finished fit run (named).
    """
    if not run_dirs:
        raise ConfigError("no runs given; pass one or more fit run folders")
    runs = [load_report_run(p) for p in run_dirs]
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ConfigError(f"--out {out_dir}: exists and is not a folder")
    report = build_report(runs, baseline=baseline, iters=iters)
    for g, numbers in report["groups"].items():
        suffix = "" if g == ALL else f"_{_slug(g)}"
        numbers["plots"] = []
        label = "all runs" if g == ALL else f"route {g}"
        for key, stem in (("iter", "psnr_vs_iter"), (WALL, "psnr_vs_time")):
            bands = {m: _band(v["curves"][key]) for m, v in numbers["methods"].items()}
            file = f"{stem}{suffix}.png"
            plot_psnr_bands(bands, key, out_dir / file, title=f"{label} ({numbers['n_runs']} runs): test PSNR, mean ± sd")
            numbers["plots"].append(file)
    write_json(out_dir / "report.json", report)
    write_bytes_atomic(out_dir / "report.md", report_markdown(report, base=out_dir).encode())
    return report


def _band(data: Mapping[str, Any] | None) -> Band | None:
    """A :class:`Band` back from its JSON form."""
    if data is None:
        return None
    return Band(np.asarray(data["x"]), np.asarray(data["mean"]), np.asarray(data["sd"]), int(data["n_runs"]))


def _f(value: Any, digits: int = 2) -> str:
    if value is None:
        return "—"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def _x(value: float | None) -> str:
    return "never" if value is None else f"{value:.2f}x"


def report_markdown(report: Mapping[str, Any], *, base: Path | None = None) -> str:
    """``report.md`` of :func:`build_report`'s numbers (with the plot names filled in).

    With ``base`` (the report's folder) each run is named by its path relative to it, so the file stays true when the
    tree holding runs and report moves (the demo builds its folder aside and swaps it in after the report is written).
    """
    methods, baseline = report["methods"], report["baseline"]
    lines = [f"# Fit report: {report['n_runs']} runs", ""]
    routing = report["routing"]
    lines += ["## Routing", ""]
    if routing["n_scored"]:
        lines += [f"Routing accuracy: **{routing['n_correct']}/{routing['n_scored']}** ({_f(routing['accuracy'], 3)}); "
                  f"known categories {routing['known']['n_correct']}/{routing['known']['n']}, "
                  f"unknown categories {routing['unknown']['n_correct']}/{routing['unknown']['n']}; "
                  f"{routing['n_unscored']} runs not scored.", "", f"Rule: {routing['rule']}.", ""]
    else:
        lines += ["No run carries a route, its known categories and a true category: routing not scored.", ""]
    lines += [f"## Speedup over {baseline}", "",
              f"Baseline: **{baseline}** ({_backbones(report, baseline)} from scratch). Iterations (time) {baseline} needs to "
              "reach its own final test PSNR, over what the main fit needs (interpolated between evaluations). Mean and "
              "geometric mean over the runs that reach it. Wall-clock: optimisation time plus the routed fit's "
              "classification and loading of its start, the fair axis (iterations of fits with other backbones or ray "
              "batches are not comparable).", "",
              "| group | runs | compared | reached | speedup wall-clock mean | geomean | speedup iters mean | geomean | "
              "speedup time mean | geomean | ahead on wall-clock | most behind (dB) |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for g, numbers in report["groups"].items():
        s = numbers["speedup"]
        if s is None:
            lines.append(f"| {g} | {numbers['n_runs']} | 0 |" + " — |" * 9)
            continue
        wall = s.get("wall") or {}
        lines.append(f"| {g} | {numbers['n_runs']} | {s['n_compared']} | {s['iters']['n_reached']} | {_x(wall.get('mean'))} | "
                     f"{_x(wall.get('geomean'))} | {_x(s['iters']['mean'])} | "
                     f"{_x(s['iters']['geomean'])} | {_x(s['time']['mean'])} | {_x(s['time']['geomean'])} | "
                     f"{s.get('n_ahead_wall', 0)}/{s['n_compared']} | {_f(s.get('behind_wall_db_max'))} |")
    lines += ["", "## Final test PSNR (dB), mean ± sd over runs", "",
              "| group | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    for g, numbers in report["groups"].items():
        cells = []
        for m in methods:
            v = numbers["methods"].get(m)
            if v is None or v["final_test_psnr_mean"] is None:
                cells.append("—")
            elif v["n_runs"] == 1:
                cells.append(f"{v['final_test_psnr_mean']:.2f} (n=1)")
            else:
                cells.append(f"{v['final_test_psnr_mean']:.2f} ± {v['final_test_psnr_sd']:.2f} (n={v['n_runs']})")
        lines.append(f"| {g} | " + " | ".join(cells) + " |")
    lines += ["", "## Curves", "", f"Rule: {report['rules']['curves']}. Time is wall-clock: each fit's optimisation time "
              "plus its classification and loading of its start (report.json keeps the optimisation-time curves too, "
              "`time_s`).", ""]
    for g, numbers in report["groups"].items():
        lines += [f"### {g}", ""] + [f"![{p}]({p})" for p in numbers.get("plots", [])] + [""]
    lines += ["## Runs", "", "| run | scene | true category | route | right | " + " | ".join(methods)
              + " | speedup wall-clock | speedup iters | speedup time | ahead at every eval |",
              "|---|---|---|---|---|" + "---|" * (len(methods) + 4)]
    for r in report["runs"]:
        route = r["route"] or {}
        routed = route.get("route") or "—"
        if route.get("category"):
            routed += f" ({route['category']})"
        right = {True: "yes", False: "no", None: "—"}[r["route_correct"]]
        psnrs = [_f(r["final_test_psnr"].get(m)) for m in methods]
        c = r["comparison"]
        tail = ["—", "—", "—", "—"] if c is None else [_x(c.get("speedup_wall")), _x(c["speedup_iters"]), _x(c["speedup_time"]),
                                                  {True: "yes", False: "no", None: "—"}[c["ahead_at_every_eval"]]]
        run = r["run"] if base is None else os.path.relpath(r["run"], base)
        lines.append(f"| {run} | {Path(str(r['scene'])).name} | {r['category'] or '—'} | {routed} | {right} | "
                     + " | ".join(psnrs + tail) + " |")
    lines += ["", "Rules: " + "; ".join(f"{k}: {v}" for k, v in report["rules"].items() if k != "routing"), ""]
    return "\n".join(lines)
