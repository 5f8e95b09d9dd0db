"""Test helper: a fused kernel's work split over a given number of threads, with the splits counted."""

from __future__ import annotations

from types import ModuleType

import pytest
import torch

from nerfmeta import fused


def split_over(monkeypatch: pytest.MonkeyPatch, threads: int, module: ModuleType, min_name: str) -> list[int]:
    """From now on in the test, kernels split over ``threads`` threads (a short OpenMP wait, torch's thread count) and
    ``module.min_name`` (the least work split) is 1; returns the list each :func:`nerfmeta.fused.split` call appends its
    number of parts to."""
    monkeypatch.setenv("GOMP_SPINCOUNT", "10000")
    monkeypatch.setattr(torch, "get_num_threads", lambda: threads)
    monkeypatch.setattr(module, min_name, 1)
    calls: list[int] = []
    real = fused.split
    monkeypatch.setattr(fused, "split", lambda kernel, args: (calls.append(len(args)), real(kernel, args))[1])
    return calls
