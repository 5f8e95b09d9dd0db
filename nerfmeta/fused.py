"""The one switch of nerfmeta's fused CPU kernels (numba), their loader, and how they split over threads.

Five families of kernels replace chains of PyTorch ops on CPU tensors with compiled loops: the grid lookups
(:mod:`nerfmeta.fields.grid_kernels`), the packed compositor (:func:`nerfmeta.render.volume.render_packed`), the
contraction of an unbounded scene's points (:meth:`nerfmeta.render.contraction.InnerBox.contract`), the occupancy
grid's march, through a contracted space or a box (:func:`nerfmeta.render.estimators.contracted_march_fused`,
:func:`~nerfmeta.render.estimators.march_fused`), and the learned start's per-voxel inputs
(:func:`nerfmeta.priors.occupancy.occupancy_inputs`).
All are optional: without numba, for tensors on a GPU, or with ``NERFMETA_FUSED_LOOKUPS=0`` in the environment
(the switch's name from when the lookups were the only kernels) PyTorch's ops run, with the same values to float
rounding (each family's tests compare both paths with a float64 reference).

Kernels are compiled on first use and cached on disk by numba (``cache=True``); a process then spends about half
a second importing numba and loading them, which a backbone's ``warm_up`` spends before a fit's clock starts.
A kernel's work is split over torch's threads as concurrent calls on ranges of it (:func:`parts`, :func:`split`):
Python threads running compiled loops that release the GIL.
"""

from __future__ import annotations

import functools
import importlib
import os
import warnings
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from types import ModuleType
from typing import Any

import torch

__all__ = ["enabled", "fused_kernels", "load", "parts", "short_openmp_wait", "split", "takes"]

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


SHORT_SPINCOUNT = 100_000
"""The largest ``GOMP_SPINCOUNT`` :func:`short_openmp_wait` counts as short (libgomp's default is 300,000)."""


def short_openmp_wait() -> bool:
    """True when PyTorch's OpenMP workers were told to spin briefly (``GOMP_SPINCOUNT`` at most
    :data:`SHORT_SPINCOUNT`, or ``OMP_WAIT_POLICY=passive``), as importing :mod:`nerfmeta` before torch does.

    Otherwise a worker spins through most of a step on the core a kernel's second thread needs: split lookups then
    measured no faster, and once 5x slower (BENCHMARKS.md, *Fused grid lookups*), so kernels stay on one thread.
    """
    if os.environ.get("OMP_WAIT_POLICY", "").strip().lower() == "passive":
        return True
    try:
        return int(os.environ.get("GOMP_SPINCOUNT", "").strip()) <= SHORT_SPINCOUNT
    except ValueError:  # unset, or libgomp's own forms ("10k", "infinite"): not known to be short
        return False


def parts(n_items: int, min_items: int) -> int:
    """How many concurrent calls a kernel over ``n_items`` is split into: torch's thread count (so ``--threads``
    and the test renders' one-thread workers hold), 1 below ``min_items`` (a thread hand-off would cost more than it
    saves) or without a short OpenMP wait (:func:`short_openmp_wait`)."""
    if n_items < min_items or not short_openmp_wait():
        return 1
    return max(1, torch.get_num_threads())


@functools.lru_cache(maxsize=None)
def _pool(workers: int, pid: int) -> ThreadPoolExecutor:
    """One pool per size and process (a forked child cannot use its parent's threads: they are not there)."""
    return ThreadPoolExecutor(workers, thread_name_prefix="nerfmeta-kernels")


def split(kernel: Callable[..., Any], calls: list[tuple[Any, ...]]) -> list[Any]:
    """``kernel(*args)`` for each of ``calls``, the last on this thread and the others at once beside it (kernels
    that release the GIL run in parallel; no numba threading layer, so no second OpenMP runtime beside PyTorch's);
    their results in the order of ``calls``."""
    futures = [_pool(len(calls) - 1, os.getpid()).submit(kernel, *args) for args in calls[:-1]]
    last = kernel(*calls[-1])
    return [future.result() for future in futures] + [last]
