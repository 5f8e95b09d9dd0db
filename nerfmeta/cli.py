"""The ``nerfmeta`` command line: a thin dispatcher over :mod:`nerfmeta.commands`.

Each command module exposes ``add_parser(subparsers)``, which registers its sub-parser and sets
``func`` to a ``run(args) -> int`` that parses arguments into a config and calls one library
function. User errors (:class:`~nerfmeta.errors.NerfmetaError`) become one line on stderr and
exit code 2, and so do argparse's own errors (an unknown option, a value of the wrong type): one
line naming the option plus a pointer to ``--help``, not the whole usage.
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


class UsageError(Exception):
    """An argparse error (unknown option, missing or mistyped value), raised instead of printing the usage."""

    def __init__(self, prog: str, message: str):
        super().__init__(message)
        self.prog = prog


class OneLineParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors are one line: ``PROG: error: MESSAGE (see 'PROG --help')``.

    Sub-parsers made by ``add_subparsers`` are of the same class, so every command behaves alike.
    """

    def error(self, message: str):  # type: ignore[override]
        raise UsageError(self.prog, message)


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
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
    try:
        args = parser.parse_args(argv)
    except UsageError as err:
        command = " ".join(err.prog.split()[:2])  # "nerfmeta pretrain", as the command's own errors start
        print(f"{command}: error: {' '.join(str(err).split())} (see '{err.prog} --help')", file=sys.stderr)
        return 2
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
