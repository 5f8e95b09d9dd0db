"""Output paths named by the user (``classify --json-out FILE``, ``inspect --out DIR``): checked
before any work, written with every OS failure (full disk, read-only place) turned into one line
naming the path.

Run folders (fit, pretraining, ...) are :mod:`nerfmeta.io`'s business; this module is for the
plain files and folders a command writes. Writes stay atomic (:func:`nerfmeta.io.write_json`).
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator, Sequence

from nerfmeta.errors import ConfigError
from nerfmeta.io import write_json


def _inputs_hit(target: Path, inputs: Sequence[str | os.PathLike | None]) -> Path | None:
    """The input (file or folder) that ``target`` is, or lies inside, if any."""
    resolved = target.resolve()
    for given in inputs:
        if given is None:
            continue
        source = Path(given).resolve()
        if resolved == source or source in resolved.parents:
            return Path(given)
    return None


def check_output_file(path: str | os.PathLike, *, option: str, inputs: Sequence[str | os.PathLike | None] = ()) -> Path:
    """The file to write for ``option``, or a one-line :class:`ConfigError` when it cannot be written.

    Refused: a path naming a folder (existing, or written with a trailing slash), anything that
    exists and is not a regular file (a device such as ``/dev/full``, a pipe: an atomic write would
    replace it), a symbolic link to a missing target, a path below a regular file, a folder the
    process may not write in, and an existing file that is or lies inside one of ``inputs`` (the
    command's own input files and folders are never replaced). A link to an existing file gives
    that file.
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
        hit = _inputs_hit(path, inputs)
        if hit is not None:
            raise ConfigError(f"{option} {path}: would replace a file of the input {hit}; write elsewhere")
    _check_creatable(path.parent, path, option)
    return path


def check_output_folder(path: str | os.PathLike, *, option: str, inputs: Sequence[str | os.PathLike | None] = ()) -> Path:
    """The folder to write for ``option`` (existing or to be made), or a one-line :class:`ConfigError`:
    something that is not a folder, a symbolic link to a missing target, a path below a regular file,
    a place the process may not write in, or one of ``inputs`` or a folder inside one."""
    path = Path(path)
    hit = _inputs_hit(path, inputs)
    if hit is not None:
        raise ConfigError(f"{option} {path}: is the input {hit} or lies inside it; write elsewhere")
    if path.is_symlink() and not path.exists():
        raise ConfigError(f"{option} {path}: is a symbolic link to a missing target ({os.readlink(path)})")
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{option} {path}: exists and is not a folder")
    _check_creatable(path, path, option)
    return path


def _check_creatable(folder: Path, path: Path, option: str) -> None:
    """``folder`` exists as a writable folder, or its nearest existing ancestor is one (so it can be made)."""
    while not folder.exists():
        if folder.is_symlink():
            raise ConfigError(f"{option} {path}: {folder} is a symbolic link to a missing target")
        folder = folder.parent
    if not folder.is_dir():
        raise ConfigError(f"{option} {path}: cannot be created because {folder} is a file, not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ConfigError(f"{option} {path}: folder {folder} is not writable")


@contextmanager
def os_errors_named(path: Path, *, option: str) -> Iterator[None]:
    """Turn an OS failure inside the block (full disk, read-only place) into one line naming ``path``."""
    try:
        yield
    except OSError as err:
        reason = err.strerror or type(err).__name__
        raise ConfigError(f"{option} {path}: cannot write ({reason})") from None


def write_output_json(path: Path, obj: Any, *, option: str) -> None:
    """Write ``obj`` as JSON to ``path`` (atomically); an OS failure is a one-line :class:`ConfigError`."""
    with os_errors_named(path, option=option):
        write_json(path, obj)
