"""Stiff and extreme cases (issue #8): run the stress table and record it in BENCHMARKS.md.

Every case of :data:`benchlib.stress.CASES` writes its scene into a temporary folder, runs the
real fit (``run_fit``; ``meta_train`` for the meta-learning rows) with each backbone it applies
to, and checks for NaN (training loss, parameters, test PSNR) and a sane test PSNR (finite, above
the case's floor, and within 0.5 dB of the original for the scaled and translated scenes). The
table (case, backbone, what happened, test PSNR, difference to the reference, guard events, NaN
seen, time) is printed, and with ``--write`` replaces the ``## Stress cases`` section of
BENCHMARKS.md (the rest of the file is kept). The exit status is 1 when any case is not ``ok``.

Forms: ``--quick`` is the reduced table that ``tests/test_stress.py`` runs in CI (16 px scenes,
60 iterations, tiny networks); the default is the full one (32 px, 300 iterations of 512 rays,
the grid's defaults and a 4 x 64 MLP, plus rows with the load-time normalisation switched off).

Usage::

    .venv/bin/python scripts/stress.py [--quick] [--case NAME ...] [--write]
"""

from __future__ import annotations

import argparse
import datetime
import logging
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchlib.sections import write_section as write_benchmark_section  # noqa: E402
from benchlib.stress import CASES, FULL, MAX_CHAMFER_GAP, MAX_PSNR_GAP, QUICK, format_table, run_table  # noqa: E402

SECTION = "## Stress cases"
MACHINE = "2-core CPU, no GPU"


def section_text(results, args: argparse.Namespace, wall_s: float, load: str) -> str:
    settings = QUICK if args.quick else FULL
    failed = [r for r in results if not r.ok]
    cmd = "python scripts/stress.py" + (" --quick" if args.quick else "") + "".join(f" --case '{c}'" for c in args.case) + " --write"
    fit = settings.fit
    lines = [
        SECTION,
        "",
        "Extreme inputs from issue #8, each a real fit (`run_fit`; `meta_train` for the meta-learning rows) on a scene",
        "written for the case (variants of the tiny analytic spheres scene, `scripts/benchlib/stress.py`). A row is `ok` when no",
        "NaN was seen (training loss and parameters every iteration, saved parameters, test PSNR) and the final test PSNR",
        f"is finite and above the case's sane floor; the scaled and translated scenes must also fit to within {MAX_PSNR_GAP:g} dB",
        "of the original (\"vs reference\"; the `no normalisation` rows show the same scenes loaded with `normalize=False`,",
        "compared with their normalised twin, for information); the scaled surface rows (a generated chair, whose exact SDF",
        f"is known) must also keep their Chamfer distance within {MAX_CHAMFER_GAP:g} points (% of the diagonal) of the unscaled fit's.",
        "Guard events: `summary.json[\"guard_events\"]` of the fit",
        "(n/a: the fit loop wrote no such key).",
        "",
        "```",
        cmd,
        "```",
        "",
        f"Machine: {MACHINE} ({args.threads} torch thread{'s' if args.threads != 1 else ''}); date "
        f"{datetime.date.today().isoformat()}; load average before the run {load}; wall time "
        f"{wall_s:.0f} s for the table. Form: {settings.name} ({settings.size} px scenes, {settings.n_train} training + "
        f"{settings.n_test} test views, {fit.iters} iterations of {fit.batch_rays} rays; backbone overrides "
        + "; ".join(f"{b}: {dict(m) if m else 'defaults'}" for b, m in settings.models.items()) + ").",
        "",
        *format_table(results),
        "",
        *normalisation_summary(results),
        (f"{len(results) - len(failed)} of {len(results)} rows ok." if not failed else
         f"{len(results) - len(failed)} of {len(results)} rows ok; not ok: " + "; ".join(f"{r.case} ({r.backbone})" for r in failed) + "."),
        "",
    ]
    return "\n".join(lines)


def normalisation_summary(results) -> list[str]:
    """One paragraph on what the load-time normalisation changed (empty when no such rows ran)."""
    moved = [r for r in results if r.psnr_gap is not None and "no normalisation" not in r.case]
    raw = [r for r in results if r.psnr_gap is not None and "no normalisation" in r.case]
    if not moved:
        return []
    worst = max(moved, key=lambda r: abs(r.psnr_gap))
    text = (f"Scaled and translated scenes, normalised at load time: at most {abs(worst.psnr_gap):.2f} dB from the original "
            f"({worst.case}, {worst.backbone}).")
    if raw:
        worst_raw = max(raw, key=lambda r: abs(r.psnr_gap))
        text += (f" The same scenes without normalisation: up to {abs(worst_raw.psnr_gap):.2f} dB from the normalised fit "
                 f"({worst_raw.case}, {worst_raw.backbone}).")
    return [text, ""]




def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the reduced (CI) form: small scenes, few iterations")
    parser.add_argument("--case", action="append", default=[], metavar="NAME",
                        help="run only this case (repeatable; a reference case is added when a case needs it)")
    parser.add_argument("--threads", type=int, default=1, metavar="N",
                        help="torch intra-op threads (default 1: the machine is shared, and two threads on two busy cores "
                        "ran the full table several times slower)")
    parser.add_argument("--write", action="store_true", help="replace the '## Stress cases' section of BENCHMARKS.md")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    settings = QUICK if args.quick else FULL
    cases = [c for c in CASES if c.quick or not args.quick]
    if args.case:
        known = {c.name for c in cases}
        unknown = [n for n in args.case if n not in known]
        if unknown:
            print(f"stress: unknown case(s) {unknown}; known: {sorted(known)}", file=sys.stderr)
            return 2
        wanted = set(args.case) | {c.reference for c in cases if c.name in args.case and c.reference}
        cases = [c for c in cases if c.name in wanted]
    import torch

    torch.set_num_threads(max(1, args.threads))
    load = " / ".join(f"{v:.1f}" for v in os.getloadavg())
    start = time.perf_counter()

    def progress(r) -> None:
        psnr = "-" if r.test_psnr is None else f"{r.test_psnr:.2f} dB"
        print(f"{r.case} ({r.backbone}): {r.outcome}; test PSNR {psnr}; {r.time_s:.1f} s", flush=True)

    with tempfile.TemporaryDirectory(prefix="stress_") as tmp:
        results = run_table(settings, tmp, cases=cases, progress=progress)
    wall_s = time.perf_counter() - start
    print()
    print("\n".join(format_table(results)))
    print(f"\nwall time {wall_s:.0f} s; {sum(r.ok for r in results)} of {len(results)} rows ok")
    if args.write:
        write_benchmark_section(ROOT / "BENCHMARKS.md", SECTION, section_text(results, args, wall_s, load))
        print(f"updated {ROOT / 'BENCHMARKS.md'} ({SECTION})")
    return 0 if all(r.ok for r in results) else 1


if __name__ == "__main__":
    raise SystemExit(main())
