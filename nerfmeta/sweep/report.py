"""The report of a sweep, drawn from its study alone (``nerfmeta sweep DIR --report`` redraws it).

``DIR/report.md``: the trials table (mean and spread over repeats), the six Pareto plots of the
source study (PSNR, SSIM and LPIPS each against optimisation time and against peak memory; the
front of each plane highlighted, the default configuration marked), one plot per knob of the
one-at-a-time design (quality, time and memory against the knob's value, with the spread over
repeats), the Pareto-optimal configurations of the study's own objectives
(``study.best_trials``), and the sweep's bookkeeping time against its trials' time.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from nerfmeta.io import atomic_path
from nerfmeta.sweep.spec import SweepSpec
from nerfmeta.sweep.study import LOGS, completed, params_of, slot_of

QUALITY = (("test_psnr", "PSNR (dB)", "max"), ("test_ssim", "SSIM", "max"), ("test_lpips", "LPIPS", "min"))
COSTS = (("time_s", "optimisation time (s)"), ("peak_rss_mb", "peak RSS of the fit process (MB)"))
DEFAULT_SLOT = "p0"
"""The default configuration's slot (enqueued first by every sampler)."""


@dataclass(frozen=True)
class Row:
    """One completed configuration."""

    number: int
    slot: str
    params: dict[str, Any]
    figures: dict[str, Any]
    flags: list[dict[str, Any]]
    optimal: bool


def rows_of(spec: SweepSpec, study) -> list[Row]:
    best = {t.number for t in study.best_trials} if completed(study) else set()
    rows = [Row(t.number, slot_of(t), params_of(spec, t), t.user_attrs.get("figures", {}), t.user_attrs.get("flags", []),
                t.number in best) for t in completed(study)]
    return sorted(rows, key=lambda r: (r.slot[0], int(r.slot[1:]) if r.slot[1:].isdigit() else 0))


def mean_of(row: Row, figure: str) -> float | None:
    entry = row.figures.get(figure)
    return None if entry is None else float(entry["mean"])


def std_of(row: Row, figure: str) -> float:
    entry = row.figures.get(figure)
    return 0.0 if entry is None else float(entry.get("std", 0.0))


def pareto_mask(points: list[tuple[float, float]], *, maximise_y: bool) -> list[bool]:
    """Which (cost, quality) points no other point beats: lower or equal cost and better or equal quality,
    strictly better in one. Points: (n, 2) pairs; returns n flags."""
    def better(a, b):
        qa, qb = (a[1], b[1]) if maximise_y else (-a[1], -b[1])
        return a[0] <= b[0] and qa >= qb and (a[0] < b[0] or qa > qb)

    return [not any(better(q, p) for q in points if q is not p) for p in points]


def _label(params: dict[str, Any], base: dict[str, Any]) -> str:
    diff = {k: v for k, v in params.items() if v != base.get(k)}
    return "default" if not diff else ", ".join(f"{k}={_fmt(v)}" for k, v in diff.items())


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, tuple):
        return "[" + ",".join(_fmt(x) for x in v) + "]"
    return str(v)


def plot_pareto(rows: list[Row], quality: tuple[str, str, str], cost: tuple[str, str], path: Path, base: dict[str, Any]) -> bool:
    """One quality-against-cost plane; False (nothing drawn) when the figures are missing."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    (qkey, qlabel, qdir), (ckey, clabel) = quality, cost
    pts = [(r, mean_of(r, ckey), mean_of(r, qkey)) for r in rows]
    pts = [p for p in pts if p[1] is not None and p[2] is not None]
    if not pts:
        return False
    mask = pareto_mask([(c, q) for _, c, q in pts], maximise_y=qdir == "max")
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=110)
    ax.errorbar([c for _, c, _ in pts], [q for _, _, q in pts], xerr=[std_of(r, ckey) for r, _, _ in pts],
                yerr=[std_of(r, qkey) for r, _, _ in pts], fmt="o", color="0.6", ms=4, lw=0.8, label="configurations")
    front = sorted((c, q) for (_, c, q), m in zip(pts, mask) if m)
    ax.plot([c for c, _ in front], [q for _, q in front], "-o", color="tab:red", ms=6, lw=1.5, label="Pareto front")
    for (r, c, q), m in zip(pts, mask):
        if m or r.slot == DEFAULT_SLOT:
            ax.annotate(_label(r.params, base), (c, q), fontsize=6, xytext=(3, 3), textcoords="offset points")
    default = [(c, q) for r, c, q in pts if r.slot == DEFAULT_SLOT]
    if default:
        ax.plot(*default[0], marker="*", color="tab:blue", ms=14, ls="none", label="default configuration")
    ax.set_xlabel(clabel)
    ax.set_ylabel(qlabel + (" (lower is better)" if qdir == "min" else ""))
    ax.set_title(f"{qlabel.split(' ')[0]} against {clabel.split(' (')[0]}")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return True


def knob_rows(rows: list[Row], knob: str, base: dict[str, Any]) -> list[Row]:
    """The configurations of the one-at-a-time design that vary only ``knob`` (the default included)."""
    return [r for r in rows if all(r.params.get(k) == v for k, v in base.items() if k != knob)]


def plot_knob(rows: list[Row], knob: str, path: Path) -> bool:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if len(rows) < 2:
        return False
    numeric = all(isinstance(r.params[knob], (int, float)) and not isinstance(r.params[knob], bool) for r in rows)
    rows = sorted(rows, key=lambda r: r.params[knob] if numeric else str(r.params[knob]))
    xs = [r.params[knob] if numeric else i for i, r in enumerate(rows)]
    panels = [("test_psnr", "PSNR (dB)"), ("test_lpips", "LPIPS"), ("time_s", "optimisation time (s)"),
              ("peak_rss_mb", "peak RSS (MB)")]
    panels = [p for p in panels if all(mean_of(r, p[0]) is not None for r in rows)]
    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 3.2), dpi=110)
    for ax, (key, label) in zip(list(axes) if len(panels) > 1 else [axes], panels):
        ax.errorbar(xs, [mean_of(r, key) for r in rows], yerr=[std_of(r, key) for r in rows], fmt="-o", ms=4, capsize=3)
        ax.set_xlabel(knob)
        ax.set_ylabel(label)
        if not numeric:
            ax.set_xticks(xs, [_fmt(r.params[knob]) for r in rows], rotation=30, fontsize=7)
        ax.grid(alpha=0.3)
    fig.suptitle(f"{knob}, the other knobs at their defaults (mean and spread over repeats)", fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return True


def _cell(row: Row, figure: str, digits: int) -> str:
    m = mean_of(row, figure)
    if m is None:
        return "-"
    s = std_of(row, figure)
    return f"{m:.{digits}f} ± {s:.{digits}f}" if s else f"{m:.{digits}f}"


def overhead(out: Path) -> dict[str, float] | None:
    """Bookkeeping (ask, tell, storage) against trial time, over the overhead records of the workers."""
    records = [json.loads(p.read_text()) for p in sorted((out / LOGS).glob("overhead-*.json"))] if (out / LOGS).is_dir() else []
    if not records:
        return None
    book = sum(r["bookkeeping_s"] for r in records)
    trial = sum(r["trial_s"] for r in records)
    return {"trials": len(records), "bookkeeping_s": book, "trial_s": trial, "fraction": book / trial if trial else 0.0}


def write_report(spec: SweepSpec, study, out: Path) -> Path:
    """Write ``out/report.md`` and its plots from the study."""
    rows = rows_of(spec, study)
    base = spec.default_params()
    knobs = [k.name for k in spec.knobs]
    lines = [f"# Sweep {spec.study_name()}", "",
             f"Scenes: {', '.join(Path(s).name for s in spec.scenes)}; backbone {spec.backbone}; sampler {spec.sampler}; "
             f"{spec.repeats} repeat(s) per configuration; objectives: "
             + ", ".join(f"{d} {f}" for f, d in spec.objectives) + f"; fixed: {json.dumps(spec.fixed)}.",
             f"Completed configurations: {len(rows)} of {spec.planned_trials()} planned.", "",
             "Figures are means over repeats ± their standard deviation. Time is optimisation time (evaluation "
             "apart); memory is the peak RSS of each fit's own process (wait4). ★: Pareto-optimal for the study's "
             "objectives. Flags: a repeat more than 3 MAD from its repeats' median, re-run once.", "",
             "| slot | " + " | ".join(knobs) + " | PSNR | SSIM | LPIPS | time (s) | peak RSS (MB) | flags | ★ |",
             "|" + "---|" * (len(knobs) + 8)]
    for r in rows:
        flags = "; ".join(f"r{f['repeat']} {f['figure']} {f['value']:.4g}->{f['rerun']:.4g}" for f in r.flags) or ""
        lines.append(f"| {r.slot} | " + " | ".join(_fmt(r.params.get(k)) for k in knobs)
                     + f" | {_cell(r, 'test_psnr', 2)} | {_cell(r, 'test_ssim', 4)} | {_cell(r, 'test_lpips', 4)} "
                     f"| {_cell(r, 'time_s', 1)} | {_cell(r, 'peak_rss_mb', 0)} | {flags} | {'★' if r.optimal else ''} |")
    lines += ["", "## Pareto plots", ""]
    for quality in QUALITY:
        for cost in COSTS:
            name = f"pareto_{quality[0].removeprefix('test_')}_vs_{cost[0].removesuffix('_s').removesuffix('_mb')}.png"
            if plot_pareto(rows, quality, cost, out / name, base):
                lines.append(f"![{quality[1]} against {cost[1]}]({name})")
            else:
                lines.append(f"({quality[1]} against {cost[1]}: no trial reported it)")
    if spec.sampler == "grid":
        lines += ["", "## One knob at a time", ""]
        for knob in knobs:
            name = f"knob_{knob.replace('.', '_')}.png"
            if plot_knob(knob_rows(rows, knob, base), knob, out / name):
                lines.append(f"![{knob}]({name})")
    lines += ["", "## Pareto-optimal configurations", ""]
    for r in (r for r in rows if r.optimal):
        figures = ", ".join(f"{f} {mean_of(r, f):.4g}" for f, _ in spec.objectives if mean_of(r, f) is not None)
        lines.append(f"- {r.slot} ({_label(r.params, base)}): {figures}")
    cost = overhead(out)
    if cost:
        lines += ["", "## Sweep overhead", "",
                  f"Bookkeeping (ask, tell, storage) {cost['bookkeeping_s']:.2f} s against {cost['trial_s']:.1f} s of "
                  f"trials ({100 * cost['fraction']:.2f} %) over the {cost['trials']} trials run by this folder's workers."]
    with atomic_path(out / "report.md") as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return out / "report.md"
