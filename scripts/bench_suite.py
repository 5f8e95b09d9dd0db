"""Test-suite time before and after a change, on the tests both versions share.

    python scripts/bench_suite.py --before ../base [--reps 2]

``--before`` is another checkout of nerfmeta with its own ``.venv`` (``bash scripts/setup.sh``
there). The test files of the *before* checkout are run in both checkouts, alternately, ``--reps``
times, with ``OMP_NUM_THREADS=1`` and the plugin :mod:`benchlib.testtime`; the report compares the
tests present in both (same node id) by CPU time (robust to other load) and wall time, and lists
apart what the change added to those files. Whole-suite wall times of both checkouts are printed
last (new test files included).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def run_tests(checkout: Path, files: list[str], out: Path) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(HERE), "NERFMETA_TESTTIME_OUT": str(out)}
    cmd = [str(checkout / ".venv/bin/python"), "-m", "pytest", "-q", "-p", "benchlib.testtime", "-p", "no:cacheprovider", *files]
    done = subprocess.run(cmd, cwd=checkout, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        sys.exit(f"bench_suite: tests failed in {checkout}:\n{done.stdout[-2000:]}")


def totals(times: dict[str, float], ids: set[str]) -> float:
    return sum(times[i] for i in ids)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", type=Path, required=True, help="checkout of the earlier version, with .venv")
    parser.add_argument("--reps", type=int, default=1, help="alternate runs of each version")
    args = parser.parse_args()
    before = args.before.resolve()
    files = sorted(p.relative_to(before).as_posix() for p in (before / "tests").glob("test_*.py"))
    files = [f for f in files if (ROOT / f).exists()]
    runs: dict[str, list[dict]] = {"before": [], "after": []}
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(args.reps):
            for name, checkout in (("before", before), ("after", ROOT)):
                out = Path(tmp) / f"{name}{rep}.json"
                run_tests(checkout, files, out)
                runs[name].append(json.loads(out.read_text()))
    common = set(runs["before"][0]["cpu"]) & set(runs["after"][0]["cpu"])
    added = set(runs["after"][0]["cpu"]) - common
    print(f"{len(files)} test files of the earlier version, {len(common)} tests in both, {len(added)} added to those files")
    for kind in ("cpu", "wall"):
        b = statistics.median(totals(r[kind], common) for r in runs["before"])
        a = statistics.median(totals(r[kind], common) for r in runs["after"])
        extra = statistics.median(totals(r[kind], added) for r in runs["after"])
        print(f"{kind:>4} time of the shared tests: before {b:.1f} s, after {a:.1f} s ({a / b - 1:+.1%}); "
              f"tests added to those files: {extra:.1f} s")


if __name__ == "__main__":
    main()
