"""The one switch of nerfmeta's fused CPU kernels (numba), and their loader.

Two families of kernels replace chains of PyTorch ops on CPU tensors with compiled loops: the grid lookups
(:mod:`nerfmeta.fields.grid_kernels`) and the packed compositor (:func:`nerfmeta.render.volume.render_packed`).
Both are optional: without numba, for tensors on a GPU, or with ``NERFMETA_FUSED_LOOKUPS=0`` in the environment
(the switch's name from when the lookups were the only kernels) PyTorch's ops run, with the same values to float
rounding (each family's tests compare both paths with a float64 reference).

Kernels are compiled on first use and cached on disk by numba (``cache=True``); a process then spends about half
a second importing numba and loading them, which a backbone's ``warm_up`` spends before a fit's clock starts.
"""

from __future__ import annotations

import functools
import importlib
import os
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import ModuleType

import torch

__all__ = ["enabled", "fused_kernels", "load", "takes"]

_ENABLED = [os.environ.get("NERFMETA_FUSED_LOOKUPS", "1") != "0"]


def enabled() -> bool:
    """True unless the fused kernels are switched off (the environment, or :func:`fused_kernels`)."""
    return _ENABLED[0]


def takes(*tensors: torch.Tensor) -> bool:
    """True when every one of ``tensors`` is on the CPU in float32 or float64, the dtypes the kernels are built for
    (each family checks its own further conditions, and :func:`enabled`)."""
    return all(t.device.type == "cpu" and t.dtype in (torch.float32, torch.float64) for t in tensors)


@contextmanager
def fused_kernels(on: bool) -> Iterator[None]:
    """Switch every fused kernel on or off inside the block (tests and benchmarks compare both paths)."""
    before = _ENABLED[0]
    _ENABLED[0] = on
    try:
        yield
    finally:
        _ENABLED[0] = before


@functools.lru_cache(maxsize=None)
def load(module: str, smoke: Callable[[ModuleType], None], what: str) -> ModuleType | None:
    """The compiled kernels' ``module``, or None without a working numba; once per process.

    ``smoke(module)`` runs each kernel on a tiny input, so they are compiled (or read from numba's cache) here: a
    numba that imports but cannot compile on this machine means PyTorch's path, with a warning naming ``what``,
    not a failed fit.
    """
    try:
        kernels = importlib.import_module(module)
    except ImportError:
        return None
    try:
        smoke(kernels)
    except Exception as exc:  # noqa: BLE001 - any compiler failure: fall back, say why
        warnings.warn(f"numba could not compile the {what} ({type(exc).__name__}: {exc}); using PyTorch's", stacklevel=2)
        return None
    return kernels
