"""Typed reads of fields from JSON documents nerfmeta did not necessarily write (zoo manifests,
``init.json``): each returns the value or raises :class:`~nerfmeta.errors.ConfigError` with one line
naming the file, the field and the value, instead of a traceback where the value is first used.
"""

from __future__ import annotations

import os
from pathlib import Path, PurePosixPath
from typing import Any

from nerfmeta.errors import ConfigError


def integer(value: Any, *, where: str, minimum: int = 0, maximum: int | None = None) -> int:
    """``value`` as an int in ``[minimum, maximum]`` (a bool or a float is refused, even 2.0)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"{where} must be an integer, got {value!r}")
    if value < minimum or (maximum is not None and value > maximum):
        bound = f">= {minimum}" if maximum is None else f"between {minimum} and {maximum}"
        raise ConfigError(f"{where} must be {bound}, got {value}")
    return value


def text(value: Any, *, where: str, choices: tuple[str, ...] | None = None) -> str:
    """``value`` as a non-empty string (one of ``choices`` when given)."""
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{where} must be a non-empty string, got {value!r}")
    if choices is not None and value not in choices:
        raise ConfigError(f"{where} is {value!r}, expected one of {', '.join(choices)}")
    return value


def mapping(value: Any, *, where: str) -> dict[str, Any]:
    """``value`` as a JSON object (dict with string keys)."""
    if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
        raise ConfigError(f"{where} must be a JSON object, got {type(value).__name__}")
    return value


def inside(root: Path, rel: Any, *, where: str) -> Path:
    """``root / rel`` resolved, for a relative path that stays inside ``root`` (also through symlinks).

    Raises:
        ConfigError: ``rel`` is not a string, is absolute, or leads out of ``root`` (``..`` or a link).
    """
    rel = text(rel, where=where)
    if PurePosixPath(rel.replace("\\", "/")).is_absolute() or os.path.isabs(rel) or (len(rel) > 1 and rel[1] == ":"):
        raise ConfigError(f"{where}: path {rel!r} is absolute; it must be relative to {root}")
    base = root.resolve()
    path = (base / rel).resolve()
    if path != base and base not in path.parents:
        raise ConfigError(f"{where}: path {rel!r} leads out of {root} (to {path})")
    return path
