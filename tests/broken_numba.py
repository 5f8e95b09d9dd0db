"""Test helper: a fused-kernel module whose compile fails, as on a machine where numba imports but cannot compile."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from types import ModuleType

import pytest

from nerfmeta.fused import load


@contextmanager
def kernel_that_cannot_compile(monkeypatch: pytest.MonkeyPatch, module: ModuleType, name: str) -> Iterator[None]:
    """Inside the block ``module.name`` raises "no LLVM target" and the kernel loader forgets what it loaded, so the next
    load of ``module`` runs its smoke and fails; afterwards the kernel is restored and the loader cleared again."""

    def broken(*_):
        raise RuntimeError("no LLVM target")

    monkeypatch.setattr(module, name, broken)
    load.cache_clear()
    try:
        yield
    finally:
        monkeypatch.undo()
        load.cache_clear()
