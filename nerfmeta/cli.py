"""The ``nerfmeta`` command line: a thin dispatcher over :mod:`nerfmeta.commands`.

Each command module exposes ``add_parser(subparsers)``, which registers its sub-parser and sets
``func`` to a ``run(args) -> int`` that parses arguments into a config and calls one library
function. User errors (:class:`~nerfmeta.errors.NerfmetaError`) become one line on stderr and
exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from nerfmeta import __version__
from nerfmeta.errors import NerfmetaError

# Order is the order shown in ``nerfmeta --help``.
COMMAND_MODULES = (
    "nerfmeta.commands.inspect",
    "nerfmeta.commands.fit",
    "nerfmeta.commands.make_collection",
    "nerfmeta.commands.pretrain",
    "nerfmeta.commands.demo",
    "nerfmeta.commands.meta_train",
    "nerfmeta.commands.classifier",
    "nerfmeta.commands.classify",
    "nerfmeta.commands.report",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="nerfmeta",
        description="Category-aware NeRF transfer and meta-learning toolkit.",
    )
    parser.add_argument("--version", action="version", version=f"nerfmeta {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details to stderr")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(name).add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)  # argparse itself exits 2 with a usage line on bad flags
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    try:
        return int(args.func(args) or 0)
    except NerfmetaError as err:
        print(f"nerfmeta {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"nerfmeta {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
