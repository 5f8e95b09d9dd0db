"""``nerfmeta report``: aggregate many fit runs into mean curves, speedups per route and routing accuracy."""

from __future__ import annotations

import argparse

from nerfmeta.errors import ConfigError
from nerfmeta.report.compare import REPORT_ITERS


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "report",
        help="aggregate fit runs: mean PSNR curves per method and route, speedups, routing accuracy",
        description="Read each RUN (a fit run folder, with the fits in RUN/compare/NAME/ if any, e.g. the "
        "from-scratch baseline of a classify-and-fit run) and write into DIR: psnr_vs_iter.png and "
        "psnr_vs_time.png (test PSNR, mean ± sd per method; per route too when the runs were routed), "
        "report.md and report.json (speedups over the baseline per route, routing accuracy when the "
        "summaries carry the true category and the route, every run's numbers).",
    )
    p.add_argument("runs", nargs="+", metavar="RUN", help="fit run folders")
    p.add_argument("--out", required=True, metavar="DIR", help="folder to write the report into (created)")
    p.add_argument("--baseline", default="scratch", metavar="NAME",
                   help="the compared fit (RUN/compare/NAME) speedups are measured against (default scratch)")
    p.add_argument("--iters", default=",".join(str(n) for n in REPORT_ITERS), metavar="N,N,...",
                   help=f"iterations of the test-PSNR tables (default {','.join(str(n) for n in REPORT_ITERS)})")
    p.set_defaults(func=run)


def parse_iters(text: str) -> tuple[int, ...]:
    try:
        iters = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise ConfigError(f"--iters {text!r}: expected comma-separated whole numbers, e.g. 25,50,100") from None
    if not iters or any(n < 1 for n in iters):
        raise ConfigError(f"--iters {text!r}: expected one or more iterations >= 1")
    return iters


def run(args: argparse.Namespace) -> int:
    from nerfmeta.report.aggregate import write_report

    report = write_report(args.runs, args.out, baseline=args.baseline, iters=parse_iters(args.iters))
    routing = report["routing"]
    if routing["n_scored"]:
        print(f"routing accuracy {routing['n_correct']}/{routing['n_scored']} ({routing['accuracy']:.3f})")
    speedup = report["groups"]["all"]["speedup"]
    if speedup is not None and speedup["iters"]["geomean"] is not None:
        print(f"speedup over {args.baseline}: {speedup['iters']['geomean']:.2f}x iterations, "
              f"{speedup['time']['geomean']:.2f}x time (geometric means over {speedup['iters']['n_reached']} of "
              f"{speedup['n_compared']} runs)")
    print(f"report of {report['n_runs']} runs in {args.out}/ (report.md, report.json, psnr_vs_iter*.png, psnr_vs_time*.png)")
    return 0
