"""Atomic file writing, JSON helpers and safetensors checkpoints.

Every file nerfmeta writes goes to a temporary name in the same folder and is renamed into place,
so a crash or a kill never leaves half a file behind (STYLE rule 10).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import torch
from safetensors.torch import load_file, save_file

from nerfmeta.errors import ConfigError


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        # mkstemp makes 0600, and some writers (safetensors) recreate the file with it: give every file
        # the ordinary, umask-respecting permissions once it is written
        os.chmod(tmp_path, 0o666 & ~_umask())
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def to_jsonable(obj: Any) -> Any:
    """Turn dataclasses, paths, tuples and tensors into plain JSON values."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, torch.Tensor):
        return obj.tolist()
    if hasattr(obj, "item") and callable(obj.item):  # numpy scalars
        return obj.item()
    return obj


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Write ``obj`` (dataclasses allowed) as indented JSON, atomically."""
    text = json.dumps(to_jsonable(obj), indent=2, sort_keys=False) + "\n"
    write_bytes_atomic(path, text.encode())


def read_metrics(path: str | os.PathLike) -> list[dict[str, Any]]:
    """The records of a ``metrics.jsonl`` run log, one dict a line; [] when the file is missing.

    Reading stops at the first line that is not JSON: a kill can tear the last line, and what
    follows a torn line is not trusted.
    """
    path = Path(path)
    if not path.exists():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            break
    return out


def save_tensors(path: str | os.PathLike, tensors: dict[str, torch.Tensor], metadata: dict[str, str] | None = None) -> None:
    """Save a flat name -> tensor dict as safetensors, atomically."""
    flat = {k: v.detach().contiguous().cpu() for k, v in tensors.items()}
    with atomic_path(path) as tmp:
        try:
            save_file(flat, str(tmp), metadata=metadata)
        except Exception as err:  # safetensors reports a failed write (a full disk) as its own error type
            code = re.search(r"\(os error (\d+)\)", str(err))
            if code is None:
                raise
            raise OSError(int(code[1]), os.strerror(int(code[1])), str(path)) from None


def load_tensors(path: str | os.PathLike, device: str | torch.device = "cpu") -> dict[str, torch.Tensor]:
    return load_file(str(path), device=str(device))


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(chunk), b""):
            h.update(block)
    return h.hexdigest()


def read_json_index(path: str | os.PathLike, expected_format: str, *, what: str, missing: str) -> dict[str, Any]:
    """Read a JSON index file (a manifest, an ``init.json``) and check its ``format`` field.

    Args:
        path: the index file.
        expected_format: the value its ``format`` must hold.
        what: what the file is, for the error ("a nerfmeta model zoo manifest").
        missing: what to say when the file is absent (how to get one).

    Raises:
        ConfigError: a missing or unreadable file, or another format (one line naming the file).
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: missing; {missing}")
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ConfigError(f"{path}: not readable JSON ({err})") from None
    found = doc.get("format") if isinstance(doc, dict) else None
    if found != expected_format:
        raise ConfigError(f"{path}: not {what} (format {found!r}, expected {expected_format!r})")
    return doc


def check_sha256(path: str | os.PathLike, expected: Any, index: str | os.PathLike, consequence: str) -> None:
    """Raise a one-line ConfigError when ``path``'s SHA-256 differs from ``expected`` (as recorded in ``index``)."""
    actual = sha256_file(path)
    if actual != expected:
        raise ConfigError(f"{path}: SHA-256 {actual[:12]}... does not match {index} ({str(expected)[:12]}...); {consequence}")
