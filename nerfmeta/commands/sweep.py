"""``nerfmeta sweep``: a hyperparameter study of fits (Optuna), with Pareto fronts of quality against time and memory.

``nerfmeta sweep SPEC --out DIR`` runs or continues the study of SPEC (see
:mod:`nerfmeta.sweep.spec`); ``nerfmeta sweep DIR --report`` redraws DIR's report from its storage.
"""

from __future__ import annotations

import argparse
import textwrap
from pathlib import Path

from tqdm import tqdm

from nerfmeta.errors import ConfigError


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "sweep",
        help="hyperparameter study of fits (Optuna): trials table, Pareto plots of quality against time and memory",
        description=textwrap.fill(
            "Run the study that SPEC (YAML or JSON) describes: each trial is a configuration, fitted once per repeat in "
            "its own process into DIR/trials/; the study lives in DIR/study.journal (or --storage), so running the same "
            "command again continues it. Writes DIR/report.md with the trials table and the Pareto plots.", width=100),
        epilog="SPEC fields: scenes, backbone, fixed, search, objectives, sampler (grid|random|tpe|nsga2), repeats, "
               "n_trials, combinations, seed, name; see nerfmeta/sweep/spec.py.",
    )
    p.add_argument("spec", metavar="SPEC", help="the sweep's SPEC file, or with --report the sweep's DIR")
    p.add_argument("--out", metavar="DIR", help="sweep folder (new, or one of the same SPEC to continue)")
    p.add_argument("--storage", default=None, metavar="URL",
                   help="Optuna storage URL (e.g. postgresql://user@host/db) shared by several machines; default: "
                   "a journal file in DIR")
    p.add_argument("--workers", type=int, default=1, metavar="N", help="trial processes to run at once on this machine")
    p.add_argument("--report", action="store_true", help="only redraw DIR/report.md from the storage")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from nerfmeta.sweep.spec import load_spec
    from nerfmeta.sweep.run import redraw_report, run_sweep

    if args.report:
        out = redraw_report(args.out or args.spec, args.storage)
        print(f"report in {out}/report.md")
        return 0
    if not args.out:
        raise ConfigError("--out DIR is required (the sweep folder)")
    if args.workers < 1:
        raise ConfigError(f"--workers {args.workers}: must be 1 or more")
    spec = load_spec(args.spec)
    bar = tqdm(total=spec.planned_trials(), unit="trial", dynamic_ncols=True)

    def on_trial(done) -> None:
        figures = ", ".join(f"{name} {done.figures[name]['mean']:.4g}" for name, _ in spec.objectives
                            if done.figures.get(name))
        config = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in done.params.items())
        eta = "" if done.eta_s is None else f", ETA {done.eta_s / 60:.1f} min"
        bar.write(f"trial {done.number} [{done.slot}] {config}: {figures} ({done.done}/{done.total}{eta})")
        bar.n = done.done
        bar.refresh()

    try:
        out = run_sweep(spec, args.out, storage=args.storage, workers=args.workers, on_trial=on_trial)
    finally:
        bar.close()
    print(f"report in {Path(out) / 'report.md'}")
    return 0
