"""PSNR curves (per iteration and against wall-clock time) and render strips, via matplotlib (Agg)."""

from __future__ import annotations

import os
from typing import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from nerfmeta.io import atomic_path  # noqa: E402


def plot_psnr_curves(
    runs: Mapping[str, Sequence[Mapping]], x_key: str, path: str | os.PathLike, *, title: str = ""
) -> None:
    """Plot train PSNR (thin) and test PSNR (markers) of one or more runs against ``x_key``.

    Args:
        runs: method name -> metrics records (``metrics.jsonl`` lines: ``iter``, ``time_s``,
            ``train_psnr`` and, where evaluated, ``test_psnr``).
        x_key: ``"iter"`` or ``"time_s"``.
        path: PNG to write (atomically).
    """
    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=110)
    for i, (name, records) in enumerate(runs.items()):
        color = f"C{i}"
        xs = np.array([r[x_key] for r in records], dtype=float)
        train = np.array([r["train_psnr"] for r in records], dtype=float)
        if len(xs):
            ax.plot(xs, _smooth(train), color=color, lw=1.2, alpha=0.8, label=f"{name} (train, smoothed)")
        tests = [(r[x_key], r["test_psnr"]) for r in records if r.get("test_psnr") is not None]
        if tests:
            tx, ty = zip(*tests)
            ax.plot(tx, ty, "o--", color=color, ms=4, lw=1, label=f"{name} (test)")
    ax.set_xlabel("iteration" if x_key == "iter" else "optimisation time (s)")
    ax.set_ylabel("PSNR (dB)")
    ax.grid(alpha=0.3)
    if title:
        ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def _smooth(values: np.ndarray, window: int = 25) -> np.ndarray:
    """Trailing moving average (the first points average over what exists so far)."""
    if len(values) == 0:
        return values
    csum = np.cumsum(np.insert(values, 0, 0.0))
    idx = np.arange(1, len(values) + 1)
    lo = np.maximum(0, idx - window)
    return (csum[idx] - csum[lo]) / (idx - lo)


def image_strip(images: Sequence[np.ndarray], gap: int = 2) -> np.ndarray:
    """Concatenate (H, W, 3) float images in [0, 1] side by side with white gaps -> uint8."""
    h = max(im.shape[0] for im in images)
    parts = []
    for k, im in enumerate(images):
        if k:
            parts.append(np.ones((h, gap, 3)))
        pad = np.ones((h, im.shape[1], 3))
        pad[: im.shape[0]] = im
        parts.append(pad)
    return (np.clip(np.concatenate(parts, 1), 0, 1) * 255 + 0.5).astype(np.uint8)
