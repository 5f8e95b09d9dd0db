"""Options from one source: the frozen config dataclasses.

The command line is generated from the configs' fields: a field's type annotation says how its
text is parsed (:func:`parse_value`), its one-line attribute docstring is its ``--help``
(:func:`field_docs`), and an optional declared range (:func:`bounded`) is checked at parse time
and whenever the config is built (:func:`check_fields`). ``--set KEY=VALUE`` overrides are parsed
against the same annotations (:func:`parse_overrides`). So a wrong value is refused in one line
naming the option, before a command writes anything.

Example::

    @dataclass(frozen=True)
    class Demo:
        iters: int = bounded(100, low=1)
        \"\"\"Iterations.\"\"\"

    add_config_options(parser, Demo)          # --iters N   Iterations. (default 100)
    Demo(**given_values(parser.parse_args(argv), Demo))
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import difflib
import functools
import inspect
import json
import math
import re
import textwrap
import types
import typing
from dataclasses import dataclass
from typing import Any, Callable, Literal, Mapping, Sequence

from nerfmeta.errors import ConfigError

BOUNDS = "nerfmeta.bounds"
"""Key of a field's declared :class:`Bounds` in ``dataclasses.field(metadata=...)``."""

TRUE_WORDS = ("true", "yes", "on", "1")
FALSE_WORDS = ("false", "no", "off", "0")
NONE_WORDS = ("none", "null")


@dataclass(frozen=True)
class Bounds:
    """A numeric field's declared range (``None``: unbounded on that side) and whether inf/NaN are allowed."""

    low: float | None = None
    """Smallest allowed value (included unless ``low_open``)."""
    high: float | None = None
    """Largest allowed value (included unless ``high_open``)."""
    low_open: bool = False
    """Exclude ``low`` itself (``> low`` instead of ``>= low``)."""
    high_open: bool = False
    """Exclude ``high`` itself."""
    nonfinite: bool = False
    """Allow ``inf``, ``-inf`` and ``nan``."""

    def describe(self) -> str:
        """The range as text, e.g. ``> 0``, ``>= 1`` or ``in (0, 1]``."""
        if self.low is not None and self.high is not None:
            return f"in {'(' if self.low_open else '['}{self.low:g}, {self.high:g}{')' if self.high_open else ']'}"
        if self.low is not None:
            return f"{'>' if self.low_open else '>='} {self.low:g}"
        if self.high is not None:
            return f"{'<' if self.high_open else '<='} {self.high:g}"
        return "any finite number"

    def problem(self, value: float) -> str | None:
        """Why ``value`` is out of range, or None when it is allowed."""
        if not math.isfinite(value):
            if self.nonfinite:
                return None
            return "must be a finite number" + ("" if self == FINITE else f" {self.describe()}")
        low_bad = self.low is not None and (value < self.low or (self.low_open and value == self.low))
        high_bad = self.high is not None and (value > self.high or (self.high_open and value == self.high))
        return f"must be {self.describe()}" if low_bad or high_bad else None


FINITE = Bounds()
"""The range of a float field that declares none: any finite number."""


def bounded(default: Any, *, low: float | None = None, high: float | None = None, low_open: bool = False,
            high_open: bool = False, nonfinite: bool = False) -> Any:
    """A dataclass field with ``default`` and a declared range (see :class:`Bounds`), e.g. ``iters: int = bounded(3000, low=1)``."""
    return dataclasses.field(default=default, metadata={BOUNDS: Bounds(low, high, low_open, high_open, nonfinite)})


def field_bounds(field: dataclasses.Field) -> Bounds:
    """A field's declared range, or :data:`FINITE` (numbers must be finite unless a field says otherwise)."""
    return field.metadata.get(BOUNDS, FINITE)


def check_fields(config: Any, what: str) -> None:
    """Raise a one-line :class:`ConfigError` for any field of ``config`` not of its declared type or outside its range.

    For configs built in code or from JSON (``config.json``, a zoo manifest), where no parser ran:
    ``FitConfig(batch_rays="abc")`` is refused like ``--batch-rays abc``. ``what`` names the
    config in the message (e.g. ``fit config``); ``None`` passes where the type allows it.
    """
    hints = field_types(type(config))
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if not _is_instance(value, hints[f.name]):
            raise ConfigError(f"{what} {f.name}={value!r}: expected {_type_name(hints[f.name])}")
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            problem = field_bounds(f).problem(float(value))
            if problem:
                raise ConfigError(f"{what} {f.name}={value!r}: {problem}")


def _is_instance(value: Any, hint: Any) -> bool:
    """Whether ``value`` is of type ``hint`` as a parsed option would be (an int is a float; a bool is no number)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return any(_is_instance(value, a) for a in args)
    if origin is Literal:
        return value in args
    if origin is tuple:
        if not isinstance(value, (tuple, list)):
            return False
        item_types = [args[0]] * len(value) if len(args) == 2 and args[1] is Ellipsis else list(args)
        return len(item_types) == len(value) and all(_is_instance(v, t) for v, t in zip(value, item_types))
    if hint is type(None):
        return value is None
    if hint in (int, float):
        return isinstance(value, (int, float) if hint is float else int) and not isinstance(value, bool)
    if hint in (bool, str):
        return isinstance(value, hint)
    return True  # dicts, Any, nested configs: checked by their own code


def field_docs(cls: type) -> dict[str, str]:
    """Attribute docstrings of a dataclass (the string literal under each field), by field name, as one line.

    Docstrings of base classes are included (a subclass's own win). Sphinx roles and double
    backquotes are reduced to plain text: ``:class:`A``` -> ``A``. Read from the source once per
    class (every command line builds its parser from them).
    """
    return dict(_field_docs(cls))


@functools.cache
def _field_docs(cls: type) -> dict[str, str]:
    docs: dict[str, str] = {}
    for klass in reversed([k for k in cls.__mro__ if dataclasses.is_dataclass(k)]):
        tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        body = tree.body[0].body  # type: ignore[attr-defined]
        for node, after in zip(body, body[1:]):
            if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and isinstance(after, ast.Expr)
                    and isinstance(after.value, ast.Constant) and isinstance(after.value.value, str)):
                text = re.sub(r":\w+:`~?([^`]*)`", r"\1", " ".join(after.value.value.split()))
                docs[node.target.id] = text.replace("``", "")
    return docs


def field_types(cls: type) -> dict[str, Any]:
    """The resolved type annotation of every field of dataclass ``cls``."""
    return dict(_field_types(cls))


@functools.cache
def _field_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


# ----- the typed parser ---------------------------------------------------------------------------


def parse_value(text: str, hint: Any, *, bounds: Bounds = FINITE) -> Any:
    """Parse command-line ``text`` as a value of type ``hint``, or raise ``ValueError`` saying what was expected.

    Supported: ``int`` (also an exact integer written as ``1e6``), ``float`` (finite unless
    ``bounds.nonfinite``), ``bool`` (true/false, yes/no, on/off, 1/0), ``str``, ``Literal[...]``,
    ``X | None`` (``none``/``null`` -> None), unions tried left to right with ``str`` last (so
    ``bool | str`` reads ``true`` as True and ``auto`` as "auto"), ``tuple[X, ...]`` and fixed
    ``tuple[X, Y]`` (comma-separated or a JSON list; empty text -> ``()``), ``dict``/``Any`` as JSON.
    Numbers are checked against ``bounds``.
    """
    text = text.strip()
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is Any or hint is dict or origin is dict:
        return _json_or_text(text)
    if origin is Literal:
        for option in args:
            try:
                value = parse_value(text, type(option))
            except ValueError:
                continue
            if value == option:
                return option
        raise ValueError(f"expected one of {', '.join(str(a) for a in args)}")
    if origin in (typing.Union, types.UnionType):
        members = [a for a in args if a is not type(None)]
        if len(members) < len(args) and text.lower() in NONE_WORDS:
            return None
        errors = []
        for member in sorted(members, key=lambda m: m is str):  # str accepts anything: try it last
            try:
                return parse_value(text, member, bounds=bounds)
            except ValueError as err:
                if not str(err).startswith("expected "):
                    raise  # the right type but out of range: say so
                errors.append(str(err).removeprefix("expected "))
        none = " or none" if len(members) < len(args) else ""
        raise ValueError(f"expected {' or '.join(errors)}{none}")
    if origin is tuple:
        return _parse_tuple(text, args, bounds)
    if hint is bool:
        word = text.lower()
        if word in TRUE_WORDS or word in FALSE_WORDS:
            return word in TRUE_WORDS
        raise ValueError("expected true or false")
    if hint is int:
        return _check_number(_parse_int(text), bounds)
    if hint is float:
        try:
            value = float(text)
        except ValueError:
            raise ValueError("expected a number") from None
        return _check_number(value, bounds)
    if hint is str:
        return json.loads(text) if len(text) >= 2 and text[0] == text[-1] == '"' else text
    raise TypeError(f"no command-line parser for type {hint!r}")


def _parse_int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        pass
    try:
        value = float(text)
    except ValueError:
        raise ValueError("expected a whole number") from None
    if not (math.isfinite(value) and value.is_integer() and abs(value) < 2**53):
        raise ValueError("expected a whole number")
    return int(value)


def _check_number(value: float, bounds: Bounds) -> Any:
    problem = bounds.problem(float(value))
    if problem:
        raise ValueError(problem)
    return value


def _parse_tuple(text: str, args: tuple, bounds: Bounds) -> tuple:
    if text.startswith("["):
        try:
            items = [json.dumps(v) if not isinstance(v, str) else v for v in json.loads(text)]
        except (json.JSONDecodeError, TypeError):
            raise ValueError("expected a list such as 1,2,3 or [1, 2, 3]") from None
    else:
        items = [part for part in text.split(",") if part.strip()] if text else []
    if len(args) == 2 and args[1] is Ellipsis:
        types_ = [args[0]] * len(items)
    else:
        types_ = list(args)
        if len(items) != len(types_):
            raise ValueError(f"expected {len(types_)} comma-separated values")
    return tuple(parse_value(item, t, bounds=bounds) for item, t in zip(items, types_))


def _json_or_text(text: str) -> Any:
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def _show(text: str) -> str:
    return text if text and not any(c.isspace() for c in text) else repr(text)


def did_you_mean(name: str, known: Sequence[str]) -> str:
    """``"; did you mean 'lr'?"`` for the closest of ``known``, or ``""``."""
    close = difflib.get_close_matches(name, known, n=1, cutoff=0.6)
    return f"; did you mean {close[0]!r}?" if close else ""


def parse_overrides(items: Sequence[str], cls: type, *, option: str = "--set") -> dict[str, Any]:
    """``KEY=VALUE`` texts -> ``{field: typed value}`` for the fields of dataclass ``cls``.

    Raises:
        ConfigError: one line naming the item: no ``=``, an unknown key (with the closest one),
            or a value that is not of the field's type or not in its range.
    """
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = field_types(cls)
    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep:
            raise ConfigError(f"{option} {item!r}: expected KEY=VALUE with KEY one of {', '.join(sorted(fields))}")
        if key not in fields:
            raise ConfigError(f"{option} {item!r}: unknown key {key!r}{did_you_mean(key, list(fields))} "
                              f"(known: {', '.join(sorted(fields))})")
        try:
            out[key] = parse_value(text, hints[key], bounds=field_bounds(fields[key]))
        except ValueError as err:
            raise ConfigError(f"{option} {key}={_show(text)}: {err}") from None
    return out


# ----- argparse options from a config ---------------------------------------------------------------


class _TypedArg:
    """argparse ``type=``: :func:`parse_value` for one field, its errors as argparse's one-line errors."""

    def __init__(self, hint: Any, bounds: Bounds, custom: Callable[[str], Any] | None):
        self.hint, self.bounds, self.custom = hint, bounds, custom
        self.__name__ = getattr(hint, "__name__", str(hint))

    def __call__(self, text: str) -> Any:
        try:
            if self.custom is not None:
                return self.custom(text)
            return parse_value(text, self.hint, bounds=self.bounds)
        except (ValueError, ConfigError) as err:
            raise argparse.ArgumentTypeError(f"{_show(text)}: {err}") from None


def _metavar(hint: Any) -> str:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        members = [a for a in args if a is not type(None)]
        return _metavar(members[0]) if len(members) == 1 else "|".join(_metavar(m) for m in members)
    if origin is tuple:
        return f"{_metavar(args[0])},..."
    if origin is Literal:
        return "{" + ",".join(str(a) for a in args) + "}"
    return {int: "N", float: "X", str: "TEXT", bool: "BOOL"}.get(hint, "VALUE")


def option_flag(name: str, flags: Mapping[str, str]) -> str:
    """The command-line spelling of field ``name``: ``flags[name]`` or ``--`` + its name with dashes."""
    return flags.get(name, "--" + name.replace("_", "-"))


def add_config_options(
    parser: argparse.ArgumentParser,
    cls: type,
    *,
    only: Sequence[str] | None = None,
    skip: Sequence[str] = (),
    flags: Mapping[str, str] = {},
    parsers: Mapping[str, Callable[[str], Any]] = {},
    choices: Mapping[str, Sequence[str]] = {},
    metavars: Mapping[str, str] = {},
    notes: Mapping[str, str] = {},
    defaults: Mapping[str, str] = {},
) -> list[str]:
    """Add one option per field of dataclass ``cls``; returns the field names added, in order.

    Every option defaults to None ("not given", see :func:`given_values`) and is parsed by the
    field's annotation (:func:`parse_value`, or ``parsers[name]`` for a special spelling such as
    a colour name) and checked against its declared range; a field without a default is a
    required option. Its help is the field's docstring,
    then ``notes[name]``, then the default (``defaults[name]`` or the field's). A ``bool`` field
    becomes ``--name/--no-name``. Fields holding nested configs, dicts or non-parseable types
    are skipped unless a parser is given.
    """
    docs, hints = field_docs(cls), field_types(cls)
    instance_defaults = _defaults(cls)
    added = []
    for f in dataclasses.fields(cls):
        name, hint = f.name, hints[f.name]
        if (only is not None and name not in only) or name in skip:
            continue
        if name not in parsers and not _parseable(hint):
            continue
        flag = option_flag(name, flags)
        default = defaults.get(name, _default_text(instance_defaults.get(name, dataclasses.MISSING)))
        parts = [docs.get(name, "").rstrip("."), notes.get(name, ""), f"default {default}" if default else ""]
        text = "; ".join(p for p in parts if p).replace("%", "%%")
        if hint is bool:
            parser.add_argument(flag, dest=name, action=argparse.BooleanOptionalAction, default=None, help=text)
        else:
            parser.add_argument(flag, dest=name, default=None, type=_TypedArg(hint, field_bounds(f), parsers.get(name)),
                                choices=choices.get(name), metavar=metavars.get(name, None if name in choices else _metavar(hint)),
                                required=name not in instance_defaults, help=text)
        added.append(name)
    return added


def describe_fields(config: Any, heading: str, *, width: int = 100) -> str:
    """A help section listing every field of dataclass instance ``config`` as ``name (type, VALUE): docstring``.

    ``VALUE`` is the instance's value as ``--set KEY=VALUE`` takes it; lines are wrapped to
    ``width``. Used as the ``epilog`` that documents the backbone configs' fields.
    """
    docs, hints = field_docs(type(config)), field_types(type(config))
    lines = [heading]
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        shown = json.dumps(list(value) if isinstance(value, tuple) else value)
        head = f"{f.name} ({_type_name(hints[f.name])}, default {shown}): "
        lines.append(textwrap.fill(head + docs.get(f.name, ""), width=width, initial_indent="  ", subsequent_indent="      "))
    return "\n".join(lines)


def _type_name(hint: Any) -> str:
    return (str(hint) if typing.get_origin(hint) else getattr(hint, "__name__", str(hint))).replace("typing.", "")


def given_values(args: argparse.Namespace, cls: type) -> dict[str, Any]:
    """The fields of ``cls`` given on the command line (present in ``args`` and not None), by field name."""
    return {f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if getattr(args, f.name, None) is not None}


def build_config(cls: type, values: Mapping[str, Any]) -> Any:
    """``cls(**values)``; a ``TypeError`` from a wrong keyword becomes a one-line :class:`ConfigError`."""
    try:
        return cls(**values)
    except TypeError as err:
        raise ConfigError(f"{cls.__name__}: {err}") from None


def _parseable(hint: Any) -> bool:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return all(_parseable(a) for a in args if a is not type(None))
    if origin is tuple:
        return all(_parseable(a) for a in args if a is not Ellipsis)
    return origin is Literal or hint in (int, float, bool, str)


def _defaults(cls: type) -> dict[str, Any]:
    out = {}
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING:
            out[f.name] = f.default
        elif f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
            out[f.name] = f.default_factory()  # type: ignore[misc]
    return out


def _default_text(value: Any) -> str:
    if value is dataclasses.MISSING or value is None:
        return ""
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, tuple):
        return ",".join(str(v) for v in value) or "none"
    return f"{value:g}" if isinstance(value, float) else str(value)
