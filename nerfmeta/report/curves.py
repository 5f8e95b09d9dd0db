"""Numbers read off PSNR curves: the test PSNR at an iteration, when a target is reached, who is ahead.

Pure functions over the evaluated points of a fit (the ``metrics.jsonl`` records that carry a
``test_psnr``). The rules, stated once here and repeated in every report:

- **Test PSNR at iteration N** is the *last evaluation at or before N* (no interpolation), and
  "none" when the run stopped before N or had no evaluation by then. With ``eval_every`` dividing
  N it is the evaluation at N itself.
- **Reaching a target** (e.g. the baseline's final test PSNR): the first evaluation at or above
  the target, *linearly interpolated* (in iterations and in optimisation time, with the same
  fraction) between it and the evaluation before it. When the very first evaluation already
  reaches the target there is nothing before it to interpolate from, so its iteration and time
  are used (an upper bound; flagged ``before_first_eval``). Never reached: ``None``.
- **Ahead**: strictly higher test PSNR, compared at the iterations where both fits were evaluated.

Intermediate evaluations score the first ``eval_views`` test views, the final one all of them
(see :class:`~nerfmeta.fit.loop.FitConfig`); the curves mix the two as the fit logged them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

X_KEYS = ("iter", "time_s")


@dataclass(frozen=True)
class Evaluations:
    """The evaluated points of one fit, in iteration order.

    Attributes:
        iters: (n,) int iterations at which the test PSNR was measured.
        time_s: (n,) float optimisation time (evaluation excluded) at those iterations.
        psnr: (n,) float test PSNR in dB.
    """

    iters: np.ndarray
    time_s: np.ndarray
    psnr: np.ndarray

    def __len__(self) -> int:
        return len(self.iters)

    def x(self, key: str) -> np.ndarray:
        """The ``iter`` or ``time_s`` coordinates, as floats."""
        if key not in X_KEYS:
            raise ValueError(f"x key {key!r}: expected one of {X_KEYS}")
        return (self.iters if key == "iter" else self.time_s).astype(float)


def evaluations(records: Sequence[Mapping]) -> Evaluations:
    """The records with a ``test_psnr``, sorted by iteration (``metrics.jsonl`` lines)."""
    points = sorted((int(r["iter"]), float(r["time_s"]), float(r["test_psnr"]))
                    for r in records if r.get("test_psnr") is not None)
    if not points:
        return Evaluations(np.zeros(0, dtype=int), np.zeros(0), np.zeros(0))
    iters, times, psnrs = zip(*points)
    return Evaluations(np.array(iters, dtype=int), np.array(times, dtype=float), np.array(psnrs, dtype=float))


def psnr_at_iter(ev: Evaluations, n: int, last_iter: int) -> tuple[float | None, int | None]:
    """Test PSNR at iteration ``n``: the last evaluation at or before ``n``, and its iteration.

    Args:
        ev: the fit's evaluations.
        n: the iteration asked about.
        last_iter: the fit's final iteration; a fit that stopped before ``n`` gives ``(None, None)``.
    """
    if last_iter < n:
        return None, None
    k = int(np.searchsorted(ev.iters, n, side="right")) - 1
    if k < 0:
        return None, None
    return float(ev.psnr[k]), int(ev.iters[k])


@dataclass(frozen=True)
class Reach:
    """Where a fit first reaches a target PSNR (see the module rules).

    Attributes:
        iter: interpolated iteration (a float).
        time_s: interpolated optimisation time.
        before_first_eval: the first evaluation already reached the target: ``iter``/``time_s``
            are that evaluation's, an upper bound.
    """

    iter: float
    time_s: float
    before_first_eval: bool


def first_reach(ev: Evaluations, target: float) -> Reach | None:
    """The first crossing of ``target`` by the test-PSNR curve, interpolated; None if never reached."""
    hits = np.nonzero(ev.psnr >= target)[0]
    if len(hits) == 0:
        return None
    k = int(hits[0])
    if k == 0:
        return Reach(float(ev.iters[0]), float(ev.time_s[0]), True)
    p0, p1 = ev.psnr[k - 1], ev.psnr[k]
    frac = float((target - p0) / (p1 - p0))  # p0 < target <= p1, so 0 < frac <= 1
    it = ev.iters[k - 1] + frac * (ev.iters[k] - ev.iters[k - 1])
    t = ev.time_s[k - 1] + frac * (ev.time_s[k] - ev.time_s[k - 1])
    return Reach(float(it), float(t), False)


def speedup(baseline: float | None, method: float | None) -> float | None:
    """``baseline / method`` (iterations or seconds to a target); None when either never got there."""
    if baseline is None or method is None or method <= 0:
        return None
    return baseline / method


@dataclass(frozen=True)
class Ahead:
    """Whether a fit's test PSNR is strictly above the baseline's at every shared evaluation.

    Attributes:
        ahead: True/False; None when the two fits share no evaluated iteration.
        not_ahead_at: shared iterations where it is not strictly above.
        compared_iters: all shared evaluated iterations.
    """

    ahead: bool | None
    not_ahead_at: tuple[int, ...]
    compared_iters: tuple[int, ...]


def ahead_of(method: Evaluations, baseline: Evaluations) -> Ahead:
    """Compare two fits at the iterations where both were evaluated."""
    base = dict(zip(baseline.iters.tolist(), baseline.psnr.tolist()))
    shared = [(it, p) for it, p in zip(method.iters.tolist(), method.psnr.tolist()) if it in base]
    behind = tuple(it for it, p in shared if not p > base[it])
    compared = tuple(it for it, _ in shared)
    return Ahead(None if not compared else not behind, behind, compared)


def shifted(ev: Evaluations, seconds: float) -> Evaluations:
    """``ev`` with ``seconds`` added to every time (optimisation time -> wall-clock time of a fit that began
    ``seconds`` after its clock started, e.g. after classifying the scene and loading its start)."""
    return Evaluations(ev.iters, ev.time_s + float(seconds), ev.psnr)


@dataclass(frozen=True)
class AheadInTime:
    """A fit against a baseline on the time axis, at the fit's evaluations inside the baseline's evaluated time range.

    Attributes:
        ahead: strictly above the baseline's curve (linearly interpolated in time) at every such
            evaluation; None when there is none.
        behind_db: the largest amount the fit is below the baseline there (0.0 if never below; None without any).
        compared: how many evaluations were compared.
    """

    ahead: bool | None
    behind_db: float | None
    compared: int


def ahead_in_time(method: Evaluations, baseline: Evaluations) -> AheadInTime:
    """Compare ``method`` with ``baseline`` on the time axis (see :class:`AheadInTime`)."""
    if not len(method) or not len(baseline):
        return AheadInTime(None, None, 0)
    t = method.time_s
    inside = (t >= baseline.time_s[0]) & (t <= baseline.time_s[-1])
    if not inside.any():
        return AheadInTime(None, None, 0)
    gap = np.interp(t[inside], baseline.time_s, baseline.psnr) - method.psnr[inside]
    return AheadInTime(bool((gap < 0).all()), float(max(gap.max(), 0.0)), int(inside.sum()))


@dataclass(frozen=True)
class Band:
    """Mean and spread of several fits' test-PSNR curves on a shared grid.

    Attributes:
        x: (m,) grid (iterations or seconds) inside every fit's evaluated range.
        mean: (m,) mean test PSNR over the fits.
        sd: (m,) sample standard deviation (``ddof=1``; 0 for a single fit).
        n_runs: number of fits averaged (the same at every point).
    """

    x: np.ndarray
    mean: np.ndarray
    sd: np.ndarray
    n_runs: int

    def as_json(self) -> dict:
        return {"x": [round(float(v), 4) for v in self.x], "mean": [round(float(v), 4) for v in self.mean],
                "sd": [round(float(v), 4) for v in self.sd], "n_runs": self.n_runs}


TIME_GRID_POINTS = 64


def mean_band(evs: Sequence[Evaluations], key: str) -> Band | None:
    """Mean +- sd of the curves ``evs`` against ``key`` (``iter`` or ``time_s``).

    Each curve is linearly interpolated onto a shared grid that lies inside *every* curve's
    evaluated range ``[max of first x, min of last x]`` (so each point averages the same fits; no
    extrapolation). The iteration grid is the union of the evaluated iterations in that range; the
    time grid is :data:`TIME_GRID_POINTS` evenly spaced seconds. None when there is no curve or
    the ranges do not overlap.
    """
    evs = [e for e in evs if len(e)]
    if not evs:
        return None
    lo = max(float(e.x(key)[0]) for e in evs)
    hi = min(float(e.x(key)[-1]) for e in evs)
    if lo > hi:
        return None
    if key == "iter":
        grid = np.unique(np.concatenate([e.x(key) for e in evs]))
        grid = grid[(grid >= lo) & (grid <= hi)]
    else:
        grid = np.linspace(lo, hi, TIME_GRID_POINTS) if hi > lo else np.array([lo])
    ys = np.stack([np.interp(grid, e.x(key), e.psnr) for e in evs])
    sd = ys.std(axis=0, ddof=1) if len(evs) > 1 else np.zeros(len(grid))
    return Band(grid, ys.mean(axis=0), sd, len(evs))
