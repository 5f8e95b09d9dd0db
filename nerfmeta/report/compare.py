"""Comparing fits of one scene: a routed (or any) fit against a baseline such as the scratch fit.

:func:`compare_logs` computes the numbers from the fits' ``metrics.jsonl`` and ``summary.json``
(rules in :mod:`nerfmeta.report.curves`); :func:`write_comparison` also writes the report files
into a folder (by default the routed run's own ``RUN/``)::

    psnr_vs_iter.png, psnr_vs_time.png       every method on one plot (replacing the single-fit ones); the
                                             time plot is on the wall-clock axis (see below)
    comparison_renders_view_VVV.png          one image per snapshot view: rows are snapshot
                                             iterations, columns ground truth | baseline | method(s)
    report.md                                tables and the images above

and stores the returned dict in ``RUN/summary.json["comparison"]``.

Two time axes: *optimisation time* (``time_s`` of ``metrics.jsonl``, the fit loop's own) and
*wall-clock* (``wall_s``): the optimisation time plus what a fit spent before its first step, its
``start_s`` = the routing of a routed fit (``summary["route"]["classify_s"]``: reading the scene,
classifying it) + building its start (``summary["init_load_s"]``: reading and checking a saved
init). A route pays for its classification and loading on the wall-clock axis; it is the axis the
headline and the ``*_wall`` numbers use.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import imageio.v3 as iio

from nerfmeta.errors import ConfigError
from nerfmeta.io import read_metrics, write_bytes_atomic, write_json
from nerfmeta.report.curves import (Evaluations, Reach, ahead_in_time, ahead_of, evaluations, first_reach, psnr_at_iter, shifted,
                                    speedup)
from nerfmeta.report.plots import plot_image_grid, plot_psnr_curves
from nerfmeta.report.snapshots import SNAPSHOT_DIR, read_snapshots, target_name

log = logging.getLogger(__name__)

REPORT_ITERS = (25, 50, 100, 200, 500, 1000)
"""Iterations at which the comparison tables give the test PSNR."""

RULES = {
    "test_psnr_at_iter": "last evaluation at or before N (no interpolation); null if the fit stopped before N "
                         "or had no evaluation by then",
    "reach": "first evaluation at or above the target, linearly interpolated (iterations and time, same fraction) "
             "with the evaluation before it; the first evaluation itself if it already reaches the target "
             "(before_first_eval, an upper bound); null if never reached",
    "speedup": "baseline's iterations (or seconds) to the target over the method's; null if the method never reaches it",
    "ahead": "strictly higher test PSNR at every iteration where both fits were evaluated; null if none is shared",
    "time": "optimisation time only (evaluation and rendering excluded), as logged in metrics.jsonl",
    "wall": "wall-clock time: optimisation time plus start_s (a routed fit's classification, route.classify_s, plus building "
            "its start, init_load_s); reach_wall_s, speedup_wall and the psnr_vs_time plot use it",
    "ahead_wall": "strictly above the baseline's test-PSNR curve (linear in wall-clock time) at every evaluation of the method "
                  "inside the baseline's evaluated time range; behind_wall_db: the largest gap below it there",
}


@dataclass(frozen=True)
class FitLog:
    """A fit run folder read back: its ``summary.json`` and ``metrics.jsonl`` records."""

    path: Path
    summary: dict[str, Any]
    records: list[dict[str, Any]]

    @property
    def evaluations(self) -> Evaluations:
        return evaluations(self.records)

    @property
    def last_iter(self) -> int:
        """The fit's final iteration (``summary["iters"]``, else the last record's)."""
        if self.summary.get("iters") is not None:
            return int(self.summary["iters"])
        return int(self.records[-1]["iter"]) if self.records else 0

    @property
    def classify_s(self) -> float:
        """Seconds a routed fit spent routing before its fit (0 for a plain fit)."""
        route = self.summary.get("route")
        return float(route.get("classify_s") or 0.0) if isinstance(route, Mapping) else 0.0

    @property
    def init_load_s(self) -> float:
        """Seconds spent building the starting model (0 where not recorded)."""
        return float(self.summary.get("init_load_s") or 0.0)

    @property
    def start_s(self) -> float:
        """Wall seconds before the first step: :attr:`classify_s` + :attr:`init_load_s`."""
        return self.classify_s + self.init_load_s

    @property
    def wall_evaluations(self) -> Evaluations:
        """The evaluations on the wall-clock axis (times shifted by :attr:`start_s`)."""
        return shifted(self.evaluations, self.start_s)

    def wall_records(self) -> list[dict[str, Any]]:
        """The ``metrics.jsonl`` records with ``wall_s`` (``time_s`` + :attr:`start_s`) added."""
        return [{**r, "wall_s": float(r["time_s"]) + self.start_s} for r in self.records]

    @property
    def final_test_psnr(self) -> float | None:
        """``summary["test_psnr"]`` (the final evaluation on all test views), else the last evaluation."""
        if self.summary.get("test_psnr") is not None:
            return float(self.summary["test_psnr"])
        ev = self.evaluations
        return float(ev.psnr[-1]) if len(ev) else None


def load_fit_log(path: str | Path) -> FitLog:
    """Read a fit run folder.

    Raises:
        ConfigError: the folder has no ``metrics.jsonl`` or ``summary.json`` (not a finished fit
            run), or its ``summary.json`` is not a JSON object.
    """
    path = Path(path)
    missing = [name for name in ("metrics.jsonl", "summary.json") if not (path / name).is_file()]
    if missing:
        raise ConfigError(f"{path}: not a finished fit run (no {' and no '.join(missing)}); "
                          "pass run folders written by 'nerfmeta fit'")
    try:
        summary = json.loads((path / "summary.json").read_text())
    except json.JSONDecodeError as err:
        raise ConfigError(f"{path / 'summary.json'}: not valid JSON ({err}); rerun the fit") from None
    if not isinstance(summary, dict):
        raise ConfigError(f"{path / 'summary.json'}: expected a JSON object; rerun the fit")
    return FitLog(path, summary, read_metrics(path / "metrics.jsonl"))


def _r(value: float | None, digits: int) -> float | None:
    return None if value is None else round(float(value), digits)


def _reach_x(reach: Reach | None, key: str) -> float | None:
    return None if reach is None else getattr(reach, key)


def compare_logs(
    logs: Mapping[str, FitLog], *, baseline: str, method: str | None = None, iters: Sequence[int] = REPORT_ITERS
) -> dict[str, Any]:
    """The comparison numbers of several fits of one scene against ``baseline`` (a key of ``logs``).

    Returns a JSON-able dict::

        baseline, target_psnr (the baseline's final test PSNR), iters, rules,
        methods: {name: {run, init, iters, time_s, final_test_psnr,
                         test_psnr_at_iter {N: dB|null}, test_psnr_at_iter_from {N: evaluated iter|null},
                         reach_iter, reach_time_s, reach_before_first_eval, reached,
                         speedup_iters, speedup_time,
                         backbone, classify_s, init_load_s, start_s, wall_s, reach_wall_s, speedup_wall,
                         and for non-baseline methods: ahead_at_every_eval, not_ahead_at, compared_iters,
                         ahead_wall, behind_wall_db}}

    and, when ``method`` names one of them, its ``method``, ``ahead_at_every_eval``,
    ``not_ahead_at``, ``speedup_iters``, ``speedup_time``, ``speedup_wall``, ``ahead_wall`` and
    ``behind_wall_db`` again at the top level. ``axis`` names the time axis of the ``*_wall`` numbers.
    """
    if baseline not in logs:
        raise ConfigError(f"baseline {baseline!r}: not among the compared fits ({', '.join(logs)})")
    if method is not None and method not in logs:
        raise ConfigError(f"method {method!r}: not among the compared fits ({', '.join(logs)})")
    base = logs[baseline]
    base_ev = base.evaluations
    target = base.final_test_psnr
    base_reach = None if target is None else first_reach(base_ev, target)
    base_wall = base.wall_evaluations
    base_reach_wall = None if target is None else first_reach(base_wall, target)
    methods: dict[str, Any] = {}
    for name, fit_log in logs.items():
        ev = fit_log.evaluations
        at = {int(n): psnr_at_iter(ev, int(n), fit_log.last_iter) for n in iters}
        reach = None if target is None else first_reach(ev, target)
        wall = fit_log.wall_evaluations
        reach_wall = None if target is None else first_reach(wall, target)
        time_s = fit_log.summary.get("time_s")
        entry: dict[str, Any] = {
            "run": str(fit_log.path),
            "init": fit_log.summary.get("init"),
            "iters": fit_log.last_iter,
            "time_s": fit_log.summary.get("time_s"),
            "final_test_psnr": _r(fit_log.final_test_psnr, 4),
            "test_psnr_at_iter": {str(n): _r(v, 4) for n, (v, _) in at.items()},
            "test_psnr_at_iter_from": {str(n): k for n, (_, k) in at.items()},
            "reached": reach is not None,
            "reach_iter": None if reach is None else round(reach.iter, 3),
            "reach_time_s": None if reach is None else round(reach.time_s, 4),
            "reach_before_first_eval": reach is not None and reach.before_first_eval,
            "speedup_iters": _r(speedup(_reach_x(base_reach, "iter"), _reach_x(reach, "iter")), 4),
            "speedup_time": _r(speedup(_reach_x(base_reach, "time_s"), _reach_x(reach, "time_s")), 4),
            "backbone": fit_log.summary.get("backbone"),
            "classify_s": _r(fit_log.classify_s, 3),
            "init_load_s": _r(fit_log.init_load_s, 3),
            "start_s": _r(fit_log.start_s, 3),
            "wall_s": None if time_s is None else _r(float(time_s) + fit_log.start_s, 3),
            "reach_wall_s": None if reach_wall is None else round(reach_wall.time_s, 4),
            "speedup_wall": _r(speedup(_reach_x(base_reach_wall, "time_s"), _reach_x(reach_wall, "time_s")), 4),
        }
        if name != baseline:
            ahead = ahead_of(ev, base_ev)
            in_time = ahead_in_time(wall, base_wall)
            entry.update(ahead_at_every_eval=ahead.ahead, not_ahead_at=list(ahead.not_ahead_at),
                         compared_iters=list(ahead.compared_iters), ahead_wall=in_time.ahead,
                         behind_wall_db=_r(in_time.behind_db, 4))
        methods[name] = entry
    out: dict[str, Any] = {"baseline": baseline, "baseline_backbone": base.summary.get("backbone"), "target_psnr": _r(target, 4),
                           "iters": [int(n) for n in iters], "axis": "wall-clock (classification and loading included)",
                           "rules": RULES, "methods": methods}
    if method is not None:
        m = methods[method]
        out.update(method=method, ahead_at_every_eval=m.get("ahead_at_every_eval"), not_ahead_at=m.get("not_ahead_at", []),
                   speedup_iters=m["speedup_iters"], speedup_time=m["speedup_time"], speedup_wall=m["speedup_wall"],
                   ahead_wall=m.get("ahead_wall"), behind_wall_db=m.get("behind_wall_db"))
    return out


def write_comparison(
    run_dir: str | Path,
    methods: Mapping[str, str | Path],
    out_dir: str | Path | None = None,
    *,
    iters: Sequence[int] = REPORT_ITERS,
    baseline: str = "scratch",
    name: str = "routed",
    update_summary: bool = True,
    summary: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Compare the fit in ``run_dir`` with the fits in ``methods`` and write the report files.

    Args:
        run_dir: the main (routed) fit run folder, called ``name`` in the report.
        methods: the other fit run folders by name; must hold ``baseline``,
            e.g. ``{"scratch": RUN / "compare" / "scratch"}``.
        out_dir: where to write (default ``run_dir``; its single-fit PSNR plots are replaced).
        iters: iterations of the test-PSNR table.
        baseline: the name of the baseline fit (the target is its final test PSNR).
        name: the name of ``run_dir``'s fit.
        update_summary: also store the returned dict in ``run_dir/summary.json["comparison"]``.
        summary: ``run_dir``'s summary when its ``summary.json`` is not written yet (the caller then
            writes it, once, with the comparison: pass ``update_summary=False``).

    Returns:
        :func:`compare_logs`'s dict with ``method=name``, each method's ``run`` relative to ``run_dir`` where it
        lies inside it (``"."``, ``"compare/scratch"``: the summary stays true when the folder is moved, or swapped
        in by ``--overwrite``), plus ``renders``: the render image files written (relative to ``out_dir``) and
        ``report``: ``"report.md"``.

    Raises:
        ConfigError: a folder that is not a finished fit run, a name used twice, a missing baseline.
    """
    run_dir = Path(run_dir)
    out_dir = run_dir if out_dir is None else Path(out_dir)
    if name in methods:
        raise ConfigError(f"method name {name!r} is used twice; rename the main fit or the compared one")
    main = load_fit_log(run_dir) if summary is None else FitLog(run_dir, dict(summary), read_metrics(run_dir / "metrics.jsonl"))
    logs = {name: main, **{k: load_fit_log(v) for k, v in methods.items()}}
    result = compare_logs(logs, baseline=baseline, method=name, iters=iters)
    for entry in result["methods"].values():
        entry["run"] = _run_path(Path(entry["run"]), run_dir)
    order = [baseline, *[k for k in logs if k != baseline]]
    labels = {k: _label(k, logs[k]) for k in order}
    title = f"{Path(str(logs[name].summary.get('scene', run_dir))).name}: " + " vs ".join(labels.values())
    plot_psnr_curves({labels[k]: logs[k].records for k in order}, "iter", out_dir / "psnr_vs_iter.png", title=title)
    plot_psnr_curves({labels[k]: logs[k].wall_records() for k in order}, "wall_s", out_dir / "psnr_vs_time.png", title=title)
    result["renders"] = write_render_grids({k: logs[k] for k in order}, out_dir)
    result["report"] = "report.md"
    write_bytes_atomic(out_dir / "report.md", comparison_markdown(result, logs[name].summary, title).encode())
    if update_summary:
        summary = json.loads((run_dir / "summary.json").read_text())
        summary["comparison"] = result
        write_json(run_dir / "summary.json", summary)
    return result


def _run_path(path: Path, run_dir: Path) -> str:
    """``path`` relative to ``run_dir`` when inside it (pure), else as given."""
    try:
        return path.relative_to(run_dir).as_posix() or "."
    except ValueError:
        return str(path)


def _label(name: str, fit_log: FitLog) -> str:
    """``name (backbone)`` for plots and tables."""
    backbone = fit_log.summary.get("backbone")
    return f"{name} ({backbone})" if backbone else name


def write_render_grids(logs: Mapping[str, FitLog], out_dir: Path) -> list[str]:
    """One image per snapshot view shared by every fit: ground truth then one column per fit (in order).

    Rows are the snapshot iterations every fit has, then (if the fits' final iterations differ) a
    ``final`` row with each fit's last snapshot. Returns the file names written (none when a fit
    has no snapshots).
    """
    snaps = {k: read_snapshots(fl.path / SNAPSHOT_DIR) for k, fl in logs.items()}
    views = sorted(set.intersection(*(set(s) for s in snaps.values()))) if snaps else []
    if not views:
        missing = [k for k, s in snaps.items() if not s]
        if missing:
            log.info("no comparison renders: no snapshots in %s", ", ".join(str(logs[k].path) for k in missing))
        return []
    written = []
    for view in views:
        per = {k: s[view] for k, s in snaps.items()}
        shared = sorted(set.intersection(*(set(its) for its in per.values())))
        finals = {k: max(its) for k, its in per.items()}
        rows: list[tuple[str, dict[str, int]]] = [(f"iter {it}", {k: it for k in per}) for it in shared]
        if any(f not in shared for f in finals.values()):
            rows.append(("final", finals))
        target = next((fl.path / SNAPSHOT_DIR / target_name(view) for fl in logs.values()
                       if (fl.path / SNAPSHOT_DIR / target_name(view)).is_file()), None)
        file = f"comparison_renders_view_{view:03d}.png"
        _render_grid(target, per, rows, out_dir / file, view)
        written.append(file)
    return written


def _render_grid(target: Path | None, per: Mapping[str, Mapping[int, Path]], rows: list[tuple[str, dict[str, int]]],
                 path: Path, view: int) -> None:
    names = list(per)
    gt = iio.imread(target)[..., :3] if target is not None else None
    cells, notes = [], []
    for label, its in rows:
        cells.append([gt, *(iio.imread(per[k][its[k]])[..., :3] for k in names)])
        notes.append(["", *(f"iter {its[k]}" if label == "final" else "" for k in names)])
    plot_image_grid(cells, path, col_titles=["ground truth", *names], row_labels=[label for label, _ in rows],
                    cell_notes=notes, title=f"view {view}")


def _fmt(value: Any, digits: int = 2, none: str = "—") -> str:
    if value is None:
        return none
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def _times(value: float | None) -> str:
    return "never" if value is None else f"{value:.2f}x"


def comparison_markdown(result: Mapping[str, Any], summary: Mapping[str, Any], title: str) -> str:
    """``report.md`` of one comparison (``result`` from :func:`compare_logs`, ``summary`` of the main fit)."""
    baseline, methods = result["baseline"], result["methods"]
    names = [baseline, *[k for k in methods if k != baseline]]
    lines = [f"# {title}", ""]
    route = summary.get("route")
    if isinstance(route, Mapping):
        conf = route.get("confidence")
        lines += [f"Route: **{route.get('route', '?')}**" + (f" ({route['category']})" if route.get("category") else "")
                  + ("" if conf is None else f", confidence {conf:.3f}")
                  + (f"; true category: {summary['category']}" if summary.get("category") else ""), ""]
    base = methods[baseline]
    lines += [f"Baseline: **{baseline}**, a {base.get('backbone') or '?'} fit from {base['init']}. Time axis of the "
              "speed-ups and the time plot: **wall-clock**, the optimisation time plus what a fit spent before its first "
              "step (a routed fit's classification and the loading of its start).", "",
              "| method | backbone | init | iterations | classify (s) | load start (s) | optimisation time (s) | wall-clock (s) "
              "| final test PSNR (dB) |", "|---|---|---|---|---|---|---|---|---|"]
    for k in names:
        m = methods[k]
        lines.append(f"| {k} | {m.get('backbone') or '—'} | {m['init']} | {m['iters']} | {_fmt(m.get('classify_s'))} | "
                     f"{_fmt(m.get('init_load_s'))} | {_fmt(m['time_s'])} | {_fmt(m.get('wall_s'))} | {_fmt(m['final_test_psnr'])} |")
    its = result["iters"]
    lines += ["", "## Test PSNR at fixed iterations (dB)", "",
              "Last evaluation at or before N (no interpolation; `@k`: the evaluation was at iteration k < N); "
              "— : the fit stopped before N or had no evaluation by then.", "",
              "| method | " + " | ".join(str(n) for n in its) + " |", "|---|" + "---|" * len(its)]
    for k in names:
        cells = []
        for n in its:
            v, frm = methods[k]["test_psnr_at_iter"][str(n)], methods[k]["test_psnr_at_iter_from"][str(n)]
            cells.append(_fmt(v) + ("" if v is None or frm == n else f" @{frm}"))
        lines.append(f"| {k} | " + " | ".join(cells) + " |")
    lines += ["", f"## Reaching {baseline}'s final test PSNR ({_fmt(result['target_psnr'])} dB)", "",
              "Linear interpolation between the evaluations either side of the first crossing "
              "(`≤`: already reached at the first evaluation, an upper bound); never: not reached. "
              f"Speedup: {baseline}'s iterations (time) over the method's; iterations of fits with other backbones or "
              "ray batches are not comparable, wall-clock is.", "",
              "| method | iterations | optimisation time (s) | wall-clock (s) | speedup (iterations) | speedup (time) "
              "| speedup (wall-clock) |", "|---|---|---|---|---|---|---|"]
    for k in names:
        m = methods[k]
        bound = "≤ " if m["reach_before_first_eval"] else ""
        it = "never" if not m["reached"] else bound + _fmt(m["reach_iter"], 1)
        t = "never" if not m["reached"] else bound + _fmt(m["reach_time_s"], 2)
        w = "never" if not m["reached"] else bound + _fmt(m.get("reach_wall_s"), 2)
        lines.append(f"| {k} | {it} | {t} | {w} | {_times(m['speedup_iters'])} | {_times(m['speedup_time'])} | "
                     f"{_times(m.get('speedup_wall'))} |")
    lines.append("")
    for k in names[1:]:
        m = methods[k]
        if m["ahead_at_every_eval"] is None:
            lines.append(f"- {k} and {baseline} share no evaluated iteration.")
        elif m["ahead_at_every_eval"]:
            lines.append(f"- {k} is ahead of {baseline} at every evaluated iteration ({len(m['compared_iters'])}).")
        else:
            lines.append(f"- {k} is **not** ahead of {baseline} at every evaluated iteration: not at "
                         + ", ".join(str(i) for i in m["not_ahead_at"]) + f" (of {len(m['compared_iters'])}).")
        if m.get("ahead_wall") is True:
            lines.append(f"- wall-clock: {k} is above {baseline}'s curve at every one of its evaluations in {baseline}'s time range.")
        elif m.get("ahead_wall") is False:
            lines.append(f"- wall-clock: {k} is **behind** {baseline}'s curve, by up to {_fmt(m.get('behind_wall_db'))} dB.")
    lines += ["", "## Curves", "", "Thin lines: train PSNR (smoothed); markers: test PSNR at evaluations. "
              "Time is wall-clock: optimisation time plus each fit's classification and loading of its start.", "", "![PSNR vs iteration](psnr_vs_iter.png)", "",
              "![PSNR vs time](psnr_vs_time.png)", ""]
    if result.get("renders"):
        lines += ["## Renders", "", "Columns: ground truth | " + " | ".join(names) + "; rows: iterations "
                  "(iter 0: the starting point, before any step).", ""]
        lines += [f"![{f}]({f})" for f in result["renders"]] + [""]
    return "\n".join(lines)
