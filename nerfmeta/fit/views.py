"""Views that the fit cannot reconcile with the others (a wrong camera pose, most often).

Structure from motion can register a photo confidently and wrongly: on 100 of lego's training views
given as a photo folder, COLMAP placed 6 on the far side of the model, 178 degrees from their true
orientation, their matches supporting the flip (BENCHMARKS.md, *Poses from photos*, session 28). Such a
view cannot be fitted together with the rest: over the last steps of 60-s fits (three seeds) the five
flipped training views stood 7.3-10.1 dB below the median training view, and no correctly posed one
more than 7; in a fit of lego with its true poses every view was within 5.9 dB of the median, on beer
within 3.8 dB. The margin is narrow on both sides, and measured on one failure.

The fit keeps each training view's squared error from its own training batches (no extra renders), in
a window of about the last :data:`WINDOW_STEPS` steps (:class:`ViewErrors`); at the end the views more
than :data:`SUSPECT_DB` dB below the median are named (:func:`suspect_views`) in a warning and in
``summary.json``; where none is, the held-out views more than :data:`TEST_SUSPECT_DB` dB below theirs
(from the final evaluation's per-view PSNR). Nothing is dropped on the fit's own say-so: ``nerfmeta fit
--drop-views`` leaves named views out of the next fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from nerfmeta.fit.evaluate import MSE_FLOOR
from nerfmeta.metrics import mse_to_psnr

WINDOW_STEPS = 100
"""Steps over which a view's error is averaged (an exponential window): late enough that the model has
settled, long enough that every view has thousands of rays (4096 rays a step over 100 views: ~4000)."""

SUSPECT_DB = 7.0
"""A training view this many dB below the median training view is named as suspect. Chosen on one case
(module doc): wrongly posed views 7.3-10.1 dB below, correctly posed ones at most 5.9 dB below."""

TEST_SUSPECT_DB = 10.0
"""A held-out view this many dB below the median held-out view is named as suspect too, but only when no
training view is: wrongly posed training views drag correctly posed held-out ones down with them (7.2-8.5 dB
below their median on lego's flipped scene). With the five flipped training views dropped, the flipped held-out
view stood 15.5 dB below and the next 1.0; on clean fits of lego and beer every held-out view was within 3.8 dB."""

MIN_RAYS = 256.0
"""A view with fewer rays than this in the window is not judged (too few to tell)."""


@dataclass
class ViewErrors:
    """Per-view sums of squared colour error and ray counts, decayed each step (an exponential window).

    Attributes:
        sse: (V,) float64 decayed sum of per-ray mean squared error (over the colour channels).
        rays: (V,) float64 decayed ray count.
        decay: factor applied to both before each step's rays are added.
    """

    sse: torch.Tensor
    rays: torch.Tensor
    decay: float = 1.0 - 1.0 / WINDOW_STEPS

    @staticmethod
    def empty(n_views: int, *, window: int = WINDOW_STEPS) -> "ViewErrors":
        zeros = torch.zeros(n_views, dtype=torch.float64)
        return ViewErrors(zeros, zeros.clone(), 1.0 - 1.0 / window)

    def add(self, views: torch.Tensor, rgb: torch.Tensor, target: torch.Tensor) -> None:
        """One step's rays: ``views`` (n,) their view positions, ``rgb`` and ``target`` (n, 3)."""
        err = (rgb.detach() - target).pow(2).mean(-1).double().cpu()
        views = views.cpu()
        self.sse.mul_(self.decay).index_add_(0, views, err)
        self.rays.mul_(self.decay).index_add_(0, views, torch.ones_like(err))

    def psnr(self) -> torch.Tensor:
        """(V,) PSNR of each view over the window; NaN where it has fewer than :data:`MIN_RAYS` rays."""
        out = mse_to_psnr((self.sse / self.rays.clamp(min=1e-12)).clamp(min=MSE_FLOOR))
        return torch.where(self.rays >= MIN_RAYS, out, torch.full_like(out, float("nan")))


def suspect_views(psnr: torch.Tensor, *, below_db: float = SUSPECT_DB) -> list[tuple[int, float]]:
    """``(position, dB below the median)`` of the views more than ``below_db`` under the median of the
    judged ones (NaN: not judged), worst first; none when fewer than 4 views are judged."""
    judged = ~torch.isnan(psnr)
    if int(judged.sum()) < 4:
        return []
    median = float(psnr[judged].median())
    gap = median - psnr
    out = [(i, float(gap[i])) for i in torch.nonzero(judged & (gap > below_db)).flatten().tolist()]
    return sorted(out, key=lambda item: -item[1])
