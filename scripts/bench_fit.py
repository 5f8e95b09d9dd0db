"""Time-budgeted fits on NeRF-synthetic lego at 100 x 100, recorded in BENCHMARKS.md.

Workload: ``nerfmeta fit LEGO --init scratch --downscale 8 --time-budget BUDGET`` (100 views of 800 x 800 read at
100 x 100; the loader holds out every 8th view, 0, 8, ..., 96, as the 13 test views and trains on
the other 87), ``--eval-every 0 --checkpoint-every 0`` so that only the final evaluation on all
13 test views runs. Each run is a fresh ``python -m nerfmeta fit`` process (so ``peak_rss_mb`` is
its own) writing into a temporary folder, with seed ``k`` for run ``k``; the script reads each
run's ``summary.json`` (test_psnr, time_s, iters, samples_per_ray, peak_rss_mb), prints every
run, the median and the spread (min..max), and with ``--write`` replaces the subsection of its
backbone in the ``## Fit on lego`` section of BENCHMARKS.md (the other subsection is kept).

Targets: grid, median test PSNR >= 28 dB in 60 s and <= 40 samples evaluated per ray; nerf,
test PSNR after 600 s (issue 13: >= 26 dB with the occupancy estimator).

Usage::

    .venv/bin/python scripts/bench_fit.py [--lego PATH] [--reps 3] [--budget 60] [--backbone grid|nerf]
        [--batch-rays N] [--set KEY=VALUE ...] [--write]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_LEGO = ROOT.parent / "shared" / "data" / "nerf_synthetic" / "lego"
SECTION = "## Fit on lego"
MACHINE = "2-core CPU, no GPU"
FIGURES = (("test_psnr", "test PSNR (dB)", 2), ("time_s", "optimisation time (s)", 1), ("iters", "iterations", 0),
           ("samples_per_ray", "samples per ray (test)", 1), ("peak_rss_mb", "peak RSS (MB)", 0),
           ("wall_s", "wall time incl. loading and evaluation (s)", 1))
TARGETS = {"grid": (("test_psnr", ">=", 28.0), ("samples_per_ray", "<=", 40.0)), "nerf": (("test_psnr", ">=", 26.0),)}
INTRO = [
    SECTION,
    "",
    "NeRF-synthetic lego read at 100 x 100 (`--downscale 8`); the loader holds out every 8th view",
    "(0, 8, ..., 96) as 13 test views and trains on the other 87. Test PSNR is the mean over the 13",
    "test views of the per-view PSNR, after the time budget (optimisation time only: loading and",
    "evaluation are not counted). Measured with `scripts/bench_fit.py`.",
    "",
]


def fit_command(lego: Path, out: Path, args: argparse.Namespace, seed: int) -> list[str]:
    cmd = [str(lego), "--out", str(out), "--init", "scratch", "--backbone", args.backbone, "--downscale", "8", "--time-budget", f"{args.budget:g}",
           "--eval-every", "0", "--checkpoint-every", "0", "--seed", str(seed)]
    if args.batch_rays:
        cmd += ["--batch-rays", str(args.batch_rays)]
    if getattr(args, "iters", None):
        cmd += ["--iters", str(args.iters)]
    for item in args.set:
        cmd += ["--set", item]
    return cmd


def run_once(lego: Path, workdir: Path, args: argparse.Namespace, k: int, tree: Path = ROOT) -> dict:
    """One fit in a fresh process of checkout ``tree`` (its ``.venv``, else this interpreter); its summary plus the
    wall time and the load average before it."""
    out = workdir / f"run{k}"
    load = " / ".join(f"{v:.1f}" for v in os.getloadavg())
    start = time.perf_counter()
    with open(workdir / f"run{k}.log", "w") as log:
        python = tree / ".venv" / "bin" / "python" if tree != ROOT else Path(sys.executable)
        proc = subprocess.run([str(python), "-m", "nerfmeta", "fit", *fit_command(lego, out, args, k)], cwd=tree,
                              stdout=log, stderr=subprocess.STDOUT)
    if proc.returncode != 0:
        tail = (workdir / f"run{k}.log").read_text().strip().splitlines()[-1:]
        raise SystemExit(f"bench_fit: {tree} run {k + 1} failed (exit {proc.returncode}): {tail[0] if tail else 'no output'}")
    summary = json.loads((out / "summary.json").read_text())
    summary["wall_s"] = time.perf_counter() - start
    summary["load"] = load
    return summary


def stats(runs: list[dict], key: str) -> tuple[float, float, float]:
    values = [float(r[key]) for r in runs]
    return statistics.median(values), min(values), max(values)


def verdicts(runs: list[dict], backbone: str) -> list[str]:
    out = []
    for key, op, target in TARGETS[backbone]:
        median = stats(runs, key)[0]
        met = median >= target if op == ">=" else median <= target
        out.append(f"median {key} {median:.2f} {op} {target:g}: {'met' if met else 'NOT met'}")
    return out


def subsection_text(runs: list[dict], args: argparse.Namespace) -> str:
    cmd = "nerfmeta fit LEGO " + " ".join(fit_command(Path("LEGO"), Path("RUN"), args, 0)[1:]).replace("--seed 0", "--seed K")
    rows = []
    for key, label, digits in FIGURES:
        med, lo, hi = stats(runs, key)
        rows.append(f"| {label} | {med:.{digits}f} | {lo:.{digits}f} | {hi:.{digits}f} |")
    per_run = "; ".join(f"seed {k}: {r['test_psnr']:.2f} dB, {r['iters']} iters, load before {r['load']}" for k, r in enumerate(runs))
    lines = [
        f"### {args.backbone} backbone, {args.budget:g} s budget",
        "",
        "```",
        cmd.replace("LEGO", "../shared/data/nerf_synthetic/lego").replace("RUN", "RUN_K"),
        "```",
        "",
        f"Machine: {MACHINE} (torch {torch_version()}, {torch_threads()} intra-op threads); date "
        f"{datetime.date.today().isoformat()}; {len(runs)} run{'s' if len(runs) != 1 else ''} "
        f"({'seed K = 0' if len(runs) == 1 else f'seeds K = 0..{len(runs) - 1}'}, one fresh process each).",
        "",
        "| figure | median | min | max |",
        "|---|---|---|---|",
        *rows,
        "",
        "Targets: " + "; ".join(verdicts(runs, args.backbone)) + ".",
        "",
        f"Per run: {per_run}. The machine is shared with other engineers' jobs; the 1/5/15-minute load averages "
        "before each run say how contended it was (2.0 = both cores busy), and a contended run does fewer iterations "
        "in its budget.",
        "",
    ]
    return "\n".join(lines)


def torch_version() -> str:
    out = subprocess.run([sys.executable, "-c", "import torch; print(torch.__version__)"], capture_output=True, text=True)
    return out.stdout.strip() or "unknown"


def torch_threads() -> str:
    out = subprocess.run([sys.executable, "-c", "import torch; print(torch.get_num_threads())"], capture_output=True, text=True)
    return out.stdout.strip() or "?"


def write_subsection(path: Path, backbone: str, text: str) -> None:
    """Replace this backbone's ``### `` subsection of our ``## `` section (creating either as needed)."""
    doc = path.read_text() if path.exists() else "# Benchmarks\n"
    section = re.compile(rf"^{re.escape(SECTION)}\n.*?(?=^## |\Z)", re.S | re.M)
    found = section.search(doc)
    body = found.group(0) if found else "\n".join(INTRO)
    sub = re.compile(rf"^### {re.escape(backbone)} backbone.*?(?=^### |^## |\Z)", re.S | re.M)
    body = sub.sub(lambda _: text + "\n", body, count=1) if sub.search(body) else body.rstrip("\n") + "\n\n" + text + "\n"
    doc = doc[:found.start()] + body + doc[found.end():] if found else doc.rstrip("\n") + "\n\n" + body
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(doc.rstrip("\n") + "\n")
    os.replace(tmp, path)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lego", type=Path, default=DEFAULT_LEGO, help=f"lego folder (default {DEFAULT_LEGO})")
    parser.add_argument("--reps", type=int, default=3, help="number of runs (default 3)")
    parser.add_argument("--budget", type=float, default=60.0, help="time budget per run in seconds (default 60)")
    parser.add_argument("--backbone", choices=("grid", "nerf"), default="grid", help="backbone (default grid)")
    parser.add_argument("--batch-rays", type=int, default=None, metavar="N", help="rays per iteration (default: the CLI's)")
    parser.add_argument("--iters", type=int, default=None, metavar="N",
                        help="iteration cap (default: the CLI's, 3000); raise it so that the time budget ends the fit")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="backbone config override, passed to nerfmeta fit")
    parser.add_argument("--write", action="store_true", help="replace this backbone's results in BENCHMARKS.md")
    args = parser.parse_args()
    if not (args.lego / "transforms_train.json").is_file():
        print(f"bench_fit: lego not found at {args.lego} (no transforms_train.json); pass --lego PATH", file=sys.stderr)
        return 2
    if args.reps < 1 or args.budget <= 0:
        print("bench_fit: --reps must be >= 1 and --budget > 0", file=sys.stderr)
        return 2
    runs = []
    with tempfile.TemporaryDirectory(prefix="bench_fit_") as tmp:
        for k in range(args.reps):
            runs.append(run_once(args.lego, Path(tmp), args, k))
            r = runs[-1]
            print(f"run {k + 1}/{args.reps}: test PSNR {r['test_psnr']:.2f} dB, {r['iters']} iters in {r['time_s']:.1f} s, "
                  f"{r['samples_per_ray']} samples/ray, peak RSS {r['peak_rss_mb']:.0f} MB, wall {r['wall_s']:.0f} s, "
                  f"load before {r['load']}", flush=True)
    for key, label, digits in FIGURES:
        med, lo, hi = stats(runs, key)
        print(f"{label}: median {med:.{digits}f} (min {lo:.{digits}f} .. max {hi:.{digits}f})")
    for line in verdicts(runs, args.backbone):
        print(line)
    if args.write:
        write_subsection(ROOT / "BENCHMARKS.md", args.backbone, subsection_text(runs, args))
        print(f"updated {ROOT / 'BENCHMARKS.md'} ({SECTION}, {args.backbone})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
