""".npy and .npz headers: the declared shape and dtype of every array, read before any data.

A scene file that announces a 60000 x 60000 image must be refused from its header, not after
NumPy has allocated the array. :func:`npz_headers` and :func:`npy_header` read only the
``.npy`` headers (``numpy.lib.format``) and check that the bytes behind each header are as many
as the header declares, so a file cannot make the loader allocate more than it holds.
"""

from __future__ import annotations

import math
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np
from numpy.lib import format as npy_format

from nerfmeta.errors import SceneError

DEFLATE_MAX_RATIO = 1032
"""A deflate stream expands at most about 1032-fold: the most a compressed member can hold."""


@dataclass(frozen=True)
class ArrayHeader:
    """What a ``.npy`` header declares.

    Attributes:
        shape: the array's shape.
        dtype: its element type (object arrays are refused when the header is read).
        data_bytes: ``prod(shape) * itemsize``, the bytes that must follow the header.
    """

    shape: tuple[int, ...]
    dtype: np.dtype
    data_bytes: int


def read_header(stream: BinaryIO, *, where: str) -> tuple[ArrayHeader, int]:
    """The header at the start of a ``.npy`` stream and the number of bytes it took.

    Raises:
        SceneError: not a ``.npy`` header, an object (pickled) dtype, or a negative dimension.
    """
    try:
        version = npy_format.read_magic(stream)
        if version == (1, 0):
            shape, _, dtype = npy_format.read_array_header_1_0(stream)
        else:
            shape, _, dtype = npy_format.read_array_header_2_0(stream)
    except (ValueError, OSError, EOFError) as err:
        raise SceneError(f"{where}: cannot read as a .npy array (bad header: {err})") from err
    if dtype.hasobject:
        raise SceneError(f"{where}: holds Python objects (dtype {dtype}); only numeric arrays are read")
    shape = tuple(int(s) for s in shape)
    if any(s < 0 for s in shape):
        raise SceneError(f"{where}: declares a negative size {shape}")
    header = ArrayHeader(shape, dtype, math.prod(shape) * dtype.itemsize)
    return header, stream.tell()


def _check_holds(header: ArrayHeader, available: int, *, where: str) -> None:
    if header.data_bytes > available:
        raise SceneError(
            f"{where}: header declares shape {header.shape} ({header.data_bytes:,} bytes) but the file holds "
            f"{max(available, 0):,}; the file is truncated or forged"
        )


def npz_headers(path: Path) -> dict[str, ArrayHeader]:
    """Array name -> declared header of every ``.npy`` member of the archive ``path``.

    Each declared size is checked against the member's uncompressed size from the zip directory
    and against what its compressed bytes can expand to (the directory's size could lie).
    """
    headers: dict[str, ArrayHeader] = {}
    try:
        with zipfile.ZipFile(path) as archive:
            for info in archive.infolist():
                if not info.filename.endswith(".npy"):
                    continue
                name = info.filename[: -len(".npy")]
                where = f"{path}: {name}"
                with archive.open(info) as member:
                    header, used = read_header(member, where=where)
                stored = info.compress_size * (1 if info.compress_type == zipfile.ZIP_STORED else DEFLATE_MAX_RATIO)
                _check_holds(header, min(info.file_size, stored) - used, where=where)
                headers[name] = header
    except (OSError, zipfile.BadZipFile, zipfile.LargeZipFile) as err:
        raise SceneError(f"{path}: cannot read as a .npz archive ({err})") from err
    return headers


def npy_header(path: Path) -> ArrayHeader:
    """The declared header of the ``.npy`` file ``path``, checked against the file's size."""
    try:
        with open(path, "rb") as stream:
            header, used = read_header(stream, where=str(path))
        size = path.stat().st_size
    except OSError as err:
        raise SceneError(f"{path}: cannot read ({err})") from err
    _check_holds(header, size - used, where=str(path))
    return header
