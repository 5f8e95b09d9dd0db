"""A/B fits on lego: the same ``bench_fit`` workload run by two checkouts, interleaved, on one machine.

A before/after figure is only fair when both sides ran under the same load. This script runs
``scripts/bench_fit.py``'s workload (``nerfmeta fit LEGO --init scratch --downscale 8 --time-budget
BUDGET --eval-every 0 --checkpoint-every 0 --seed K``) with seed ``k`` for run ``k``, alternating
between checkout A (``--before``: its own ``.venv``) and checkout B (this one), so any drift of the
machine's load falls on both. It prints one line per run, then the median and range of each figure
for A and B, as a Markdown table ready for BENCHMARKS.md.

Usage::

    .venv/bin/python scripts/bench_ab.py --before ../base [--reps 3] [--budget 60] [--backbone grid]
        [--batch-rays N] [--set KEY=VALUE ...] [--lego PATH]

``--before`` is a checkout of the older commit with its set-up done (``git worktree add ../base
COMMIT && (cd ../base && bash scripts/setup.sh)``).
"""

from __future__ import annotations

import argparse
import datetime
import subprocess
import tempfile
from pathlib import Path

from bench_fit import DEFAULT_LEGO, FIGURES, ROOT, fit_command, run_once, stats


def commit_of(tree: Path) -> str:
    return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=tree, capture_output=True, text=True).stdout.strip()


def table(sides: dict[str, list[dict]]) -> list[str]:
    names = list(sides)
    rows = ["| figure | " + " | ".join(f"{n} median (min-max)" for n in names) + " |", "|---|" + "---|" * len(names)]
    for key, label, digits in FIGURES:
        cells = []
        for runs in sides.values():
            med, lo, hi = stats(runs, key)
            cells.append(f"{med:.{digits}f} ({lo:.{digits}f}-{hi:.{digits}f})")
        rows.append(f"| {label} | " + " | ".join(cells) + " |")
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", type=Path, required=True, help="checkout A (the older commit), with its .venv")
    parser.add_argument("--lego", type=Path, default=DEFAULT_LEGO)
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--budget", type=float, default=60.0)
    parser.add_argument("--backbone", default="grid")
    parser.add_argument("--batch-rays", type=int, default=None)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    before = args.before.resolve()
    if not (before / ".venv" / "bin" / "python").exists():
        parser.error(f"--before {before}: no .venv there (run scripts/setup.sh in it first)")
    trees = {f"A {commit_of(before)}": before, f"B {commit_of(ROOT)}": ROOT}
    sides: dict[str, list[dict]] = {name: [] for name in trees}
    with tempfile.TemporaryDirectory(prefix="bench_ab_") as tmp:
        for k in range(args.reps):
            for name, tree in trees.items():
                workdir = Path(tmp) / name.split()[0]
                workdir.mkdir(exist_ok=True)
                r = run_once(args.lego, workdir, args, k, tree=tree)
                sides[name].append(r)
                print(f"{name} seed {k}: {r['test_psnr']:.2f} dB, {r['iters']} iters, {r['samples_per_ray']:.1f} samples/ray, "
                      f"load before {r['load']}", flush=True)
    cmd = "nerfmeta fit LEGO " + " ".join(fit_command(Path("LEGO"), Path("RUN"), args, 0)[1:]).replace("--seed 0", "--seed K")
    print(f"\n`{cmd}`, {args.reps} runs per side, interleaved A, B, A, B, ...; {datetime.date.today().isoformat()}\n")
    print("\n".join(table(sides)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
