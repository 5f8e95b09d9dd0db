"""Fuzz scene files (issue 15): mutate valid scenes of every format and count the outcomes.

Each case must load (exit 0) or be refused in one line (exit 2); anything else (a traceback, an
exception, extra lines on stderr such as a numpy warning) is ``broken`` and printed. The mutations
are in ``tests/fuzz_scenes.py`` (shared with ``tests/test_hostile_inputs.py``, which runs a few).
The exit status is 1 when any case is broken.

Usage::

    .venv/bin/python scripts/fuzz_inputs.py [--cases N] [--seed S] [--kind blender ...]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from fuzz_scenes import KINDS, fuzz  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=200, help="cases per kind (default 200)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--kind", nargs="+", choices=KINDS, default=list(KINDS))
    args = parser.parse_args()
    broken = 0
    print("| kind | cases | loaded | refused in one line | broken |")
    print("| --- | --- | --- | --- | --- |")
    with tempfile.TemporaryDirectory() as tmp:
        for kind in args.kind:
            outcomes = fuzz(kind, args.cases, Path(tmp), seed=args.seed)
            bad = [o for o in outcomes if o.broken]
            counts = Counter(o.code for o in outcomes if not o.broken)
            print(f"| {kind} | {len(outcomes)} | {counts[0]} | {counts[2]} | {len(bad)} |", flush=True)
            for o in bad[:5]:
                print(f"    broken: {kind} case {o.case}: exit {o.code}: {' / '.join(o.stderr[-3:])}", file=sys.stderr)
            broken += len(bad)
    return 1 if broken else 0


if __name__ == "__main__":
    raise SystemExit(main())
