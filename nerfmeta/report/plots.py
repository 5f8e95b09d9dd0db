"""PSNR curves (per iteration and against wall-clock time), mean +- sd bands over runs, render strips
and labelled image grids, via matplotlib (Agg)."""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from nerfmeta.io import atomic_path  # noqa: E402

if TYPE_CHECKING:
    from nerfmeta.report.curves import Band

X_LABELS = {"iter": "iteration", "time_s": "optimisation time (s)",
            "wall_s": "wall-clock time (s), classification and loading included"}
"""Axis label of each x key."""


def save_figure(fig, path: str | os.PathLike) -> None:
    """Lay out a pyplot figure, write it as PNG atomically (a temporary file renamed into place), and close it."""
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def plot_psnr_curves(
    runs: Mapping[str, Sequence[Mapping]], x_key: str, path: str | os.PathLike, *, title: str = ""
) -> None:
    """Plot train PSNR (thin) and test PSNR (markers) of one or more runs against ``x_key``.

    Args:
        runs: method name -> metrics records (``metrics.jsonl`` lines: ``iter``, ``time_s``,
            ``train_psnr`` and, where evaluated, ``test_psnr``).
        x_key: a key of :data:`X_LABELS` (``"iter"``, ``"time_s"``, ``"wall_s"``).
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
    ax.set_xlabel(X_LABELS[x_key])
    ax.set_ylabel("PSNR (dB)")
    ax.grid(alpha=0.3)
    if title:
        ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8, loc="lower right")
    save_figure(fig, path)


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


def plot_image_grid(
    cells: Sequence[Sequence[np.ndarray | None]],
    path: str | os.PathLike,
    *,
    col_titles: Sequence[str] = (),
    row_labels: Sequence[str] = (),
    cell_notes: Sequence[Sequence[str]] = (),
    title: str = "",
) -> None:
    """Draw images in a labelled grid and write it as a PNG (atomically).

    Args:
        cells: rows of (H, W, 3) images (uint8, or float in [0, 1]); None leaves a cell blank.
        col_titles: one title per column, above the first row.
        row_labels: one label per row, left of the first column.
        cell_notes: per cell, a short note under it ("" for none).
    """
    n_rows, n_cols = len(cells), max(len(r) for r in cells)
    shape = next(im.shape for r in cells for im in r if im is not None)
    cell = 2.2
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(cell * n_cols, cell * shape[0] / shape[1] * n_rows + 0.6),
                             dpi=100, squeeze=False)
    for i in range(n_rows):
        for j in range(n_cols):
            ax = axes[i, j]
            ax.set_xticks([])
            ax.set_yticks([])
            image = cells[i][j] if j < len(cells[i]) else None
            if image is not None:
                ax.imshow(image, interpolation="nearest")
            else:
                ax.axis("off")
            if i == 0 and j < len(col_titles):
                ax.set_title(col_titles[j], fontsize=9)
            if j == 0 and i < len(row_labels):
                ax.axis("on")
                ax.set_ylabel(row_labels[i], fontsize=9)
            if i < len(cell_notes) and j < len(cell_notes[i]) and cell_notes[i][j]:
                ax.set_xlabel(cell_notes[i][j], fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    save_figure(fig, path)


def plot_psnr_bands(
    bands: Mapping[str, Band | None], x_key: str, path: str | os.PathLike, *, title: str = ""
) -> None:
    """Plot mean test PSNR (line) +- one standard deviation (band) per method against ``x_key``.

    Args:
        bands: method name -> :class:`~nerfmeta.report.curves.Band` (``x``, ``mean``, ``sd``,
            ``n_runs``); None entries are skipped.
        x_key: a key of :data:`X_LABELS` (``"iter"``, ``"time_s"``, ``"wall_s"``).
        path: PNG to write (atomically).
    """
    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=110)
    for i, (name, band) in enumerate(bands.items()):
        if band is None:
            continue
        color = f"C{i}"
        ax.plot(band.x, band.mean, "o-" if len(band.x) < 30 else "-", color=color, ms=3, lw=1.4,
                label=f"{name} (n={band.n_runs})")
        ax.fill_between(band.x, band.mean - band.sd, band.mean + band.sd, color=color, alpha=0.2, lw=0)
    ax.set_xlabel(X_LABELS[x_key])
    ax.set_ylabel("test PSNR (dB), mean ± sd")
    ax.grid(alpha=0.3)
    if title:
        ax.set_title(title, fontsize=10)
    if ax.lines:
        ax.legend(fontsize=8, loc="lower right")
    save_figure(fig, path)
