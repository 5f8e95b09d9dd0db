"""A sweep worker process: ``python -m nerfmeta.sweep.worker DIR [--storage URL]`` (started by ``nerfmeta sweep``)."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from nerfmeta.errors import NerfmetaError
from nerfmeta.sweep.spec import SweepSpec
from nerfmeta.sweep.study import SPEC_FILE, work
from nerfmeta.sweep.trial import warm_imports


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="nerfmeta.sweep.worker")
    parser.add_argument("out")
    parser.add_argument("--storage", default=None)
    parser.add_argument("--index", type=int, default=0, help="worker number (seeds its sampler)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    out = Path(args.out)
    spec = SweepSpec.from_json(json.loads((out / SPEC_FILE).read_text()))
    warm_imports()
    try:
        work(spec, out, args.storage, args.index)
    except NerfmetaError as err:
        print(f"nerfmeta sweep worker: error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
