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
import re
import sys

from nerfmeta import __version__
from nerfmeta.config import did_you_mean
from nerfmeta.errors import NerfmetaError

# Order is the order shown in ``nerfmeta --help``.
COMMAND_MODULES = (
    "nerfmeta.commands.inspect",
    "nerfmeta.commands.fit",
    "nerfmeta.commands.poses",
    "nerfmeta.commands.render",
    "nerfmeta.commands.make_collection",
    "nerfmeta.commands.pretrain",
    "nerfmeta.commands.demo",
    "nerfmeta.commands.meta_train",
    "nerfmeta.commands.classifier",
    "nerfmeta.commands.classify",
    "nerfmeta.commands.report",
    "nerfmeta.commands.sweep",
    "nerfmeta.commands.mesh",
    "nerfmeta.commands.eval_geometry",
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


ARGPARSE_PHRASES = ("invalid ", "expected ", "ignored ", "not allowed ")
"""How argparse's own complaints about an option's value begin (the typed options' begin with the value)."""


def _name_option_first(message: str) -> str:
    """``argument --iters: 0: must be >= 1`` -> ``--iters 0: must be >= 1``; argparse's own phrases keep a colon."""
    match = re.match(r"argument (--[\w-]+)(?:/--[\w-]+)?: (.*)", message)
    if match is None:
        return message
    flag, rest = match.groups()
    return f"{flag}{':' if rest.startswith(ARGPARSE_PHRASES) else ''} {rest}"


def _command_parser(parser: argparse.ArgumentParser, argv: list[str]) -> argparse.ArgumentParser:
    """The (sub-)parser of the command that ``argv`` names (e.g. ``pretrain category``), else ``parser``."""
    current = parser
    for token in argv:
        sub = next((a for a in current._actions if isinstance(a, argparse._SubParsersAction)), None)
        if sub is None:
            break
        if token in sub.choices:
            current = sub.choices[token]
    return current


def _suggest(parser: argparse.ArgumentParser, message: str) -> str:
    """``"; did you mean '--iters'?"`` for the first unrecognised option of ``message`` close to one of ``parser``'s."""
    known = [s[2:] for action in parser._actions for s in action.option_strings if s.startswith("--")]
    for token in message.removeprefix("unrecognized arguments:").split():
        if token.startswith("--"):
            hint = did_you_mean(token.partition("=")[0][2:], known)
            if hint:
                return hint.replace("'", "'--", 1)
    return ""


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        args = parser.parse_args(argv)
    except UsageError as err:
        prog, message = err.prog, " ".join(str(err).split())
        message = _name_option_first(message)
        if message.startswith("unrecognized arguments:"):  # reported by the top parser: name the command's options
            command_parser = _command_parser(parser, argv)
            prog, message = command_parser.prog, message + _suggest(command_parser, message)
        command = " ".join(prog.split()[:2])  # "nerfmeta pretrain", as the command's own errors start
        print(f"{command}: error: {message} (see '{prog} --help')", file=sys.stderr)
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
