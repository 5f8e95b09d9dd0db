"""Output files named by the user (``classify --json-out FILE``): checked before any work, written
with every OS failure (full disk, read-only place) turned into one line naming the path.

Folders written by commands (run folders) are :mod:`nerfmeta.io`'s business; this module is for
single files the user names. Writes stay atomic (:func:`nerfmeta.io.write_json`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from nerfmeta.errors import ConfigError
from nerfmeta.io import write_json


def check_output_file(path: str | os.PathLike, *, option: str) -> Path:
    """The file to write for ``option``, or a one-line :class:`ConfigError` when it cannot be written.

    Refused: a path naming a folder (existing, or written with a trailing slash), anything that
    exists and is not a regular file (a device such as ``/dev/full``, a pipe: an atomic write would
    replace it), a symbolic link to a missing target, a path below a regular file, and a folder the
    process may not write in. A link to an existing file gives that file.
    """
    text = os.fspath(path)
    path = Path(text)
    if text.endswith(("/", os.sep)):
        raise ConfigError(f"{option} {text}: names a folder; give a file path")
    if path.is_symlink() and not path.exists():
        raise ConfigError(f"{option} {path}: is a symbolic link to a missing target ({os.readlink(path)})")
    if path.exists():
        path = path.resolve()
        if path.is_dir():
            raise ConfigError(f"{option} {path}: is a folder; give a file path")
        if not path.is_file():
            raise ConfigError(f"{option} {path}: exists and is not a regular file (a device or pipe); refusing to replace it")
    parent = path.parent
    while not parent.exists():
        if parent.is_symlink():
            raise ConfigError(f"{option} {path}: {parent} is a symbolic link to a missing target")
        parent = parent.parent
    if not parent.is_dir():
        raise ConfigError(f"{option} {path}: cannot be created because {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ConfigError(f"{option} {path}: folder {parent} is not writable")
    return path


def write_output_json(path: Path, obj: Any, *, option: str) -> None:
    """Write ``obj`` as JSON to ``path`` (atomically); an OS failure is a one-line :class:`ConfigError`."""
    try:
        write_json(path, obj)
    except OSError as err:
        reason = err.strerror or type(err).__name__
        raise ConfigError(f"{option} {path}: cannot write ({reason}); nothing was written") from None
