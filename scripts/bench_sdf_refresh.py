"""What an SDF run's occupancy refresh costs: full refreshes against the narrow-band ones between them.

Loads a fitted ``--backbone sdf`` run and times ``--repeats`` refreshes of each kind on its final field: full (every
corner of the occupancy grid) and narrow (only the corners within the band plus ``occupancy_reach`` cells, what most
refreshes of a fit do, :class:`~nerfmeta.fields.sdf.NarrowBand`). Prints JSON: the median seconds of each, the share of
corners a narrow refresh evaluates, and whether its marks equal the full refresh's. BENCHMARKS.md, *Surfaces: carving
concavities*, section 12, has what it measured.

Usage::

    .venv/bin/python scripts/bench_sdf_refresh.py RUN [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import nerfmeta  # noqa: E402,F401 - before torch, which then spins its OpenMP workers briefly (nerfmeta/__init__.py)
import torch  # noqa: E402

from nerfmeta.fields.sdf import SdfField  # noqa: E402
from nerfmeta.geometry.load import load_run_model  # noqa: E402


def timed_refresh(model: SdfField, full: bool) -> tuple[float, int]:
    """Seconds of one refresh (full, or narrow after the band's last values) and the corners it evaluated."""
    band = model.band
    if full:
        band.distance = None
    else:
        band.period, band.since_full = 2, 0  # the next refresh is a narrow one
    before = band.evaluated
    t = time.perf_counter()
    model._refresh_occupancy()
    return time.perf_counter() - t, band.evaluated - before


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", help="a fit run of --backbone sdf")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    model, _ = load_run_model(args.run)
    if not isinstance(model, SdfField) or not model.config.occupancy:
        print(f"error: {args.run} is not an SDF run with an occupancy grid", file=sys.stderr)
        return 2
    full_s, narrow_s, share, same = [], [], 0.0, True
    for _ in range(args.repeats):
        seconds, n = timed_refresh(model, full=True)
        full_s.append(seconds)
        marks = model.occupancy.binaries.clone()
        seconds, m = timed_refresh(model, full=False)
        narrow_s.append(seconds)
        share = m / n
        same &= torch.equal(marks, model.occupancy.binaries)
    print(json.dumps({"run": args.run, "threads": torch.get_num_threads(), "full_s": round(statistics.median(full_s), 3),
                      "narrow_s": round(statistics.median(narrow_s), 3), "narrow_share": round(share, 3),
                      "same_marks": same}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
