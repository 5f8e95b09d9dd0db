"""The training curve: loss per step and validation accuracy per epoch (matplotlib, Agg)."""

from __future__ import annotations

import os
from typing import Any, Mapping

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from nerfmeta.report.plots import save_figure  # noqa: E402


def plot_training_curve(history: Mapping[str, Any], path: str | os.PathLike, *, title: str = "") -> None:
    """Plot training loss (per step, smoothed) and validation accuracy (per epoch) against steps.

    Args:
        history: as returned by :func:`classifier.train.fit_network` (``step_loss``, ``epochs``).
        path: PNG to write (atomically).
    """
    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=110)
    loss = np.asarray(history.get("step_loss", []), dtype=float)
    if len(loss):
        steps = np.arange(1, len(loss) + 1)
        ax.plot(steps, loss, color="C0", lw=0.6, alpha=0.3)
        ax.plot(steps, _smooth(loss, max(1, len(loss) // 40)), color="C0", lw=1.4, label="training loss (smoothed)")
    epochs = history.get("epochs", [])
    if epochs:
        ax.plot([e["step"] for e in epochs], [e["val_loss"] for e in epochs], "s--", color="C1", ms=4, lw=1, label="validation loss (views)")
    ax.set_xlabel("step")
    ax.set_ylabel("cross-entropy")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    if epochs:
        acc = ax.twinx()
        acc.plot([e["step"] for e in epochs], [e["val_scene_accuracy"] for e in epochs], "o-", color="C2", ms=4, lw=1, label="validation accuracy (scenes)")
        acc.plot([e["step"] for e in epochs], [e["val_view_accuracy"] for e in epochs], "^:", color="C3", ms=4, lw=1, label="validation accuracy (views)")
        acc.set_ylim(0.0, 1.02)
        acc.set_ylabel("accuracy")
        lines = ax.get_legend_handles_labels()[0] + acc.get_legend_handles_labels()[0]
        labels = ax.get_legend_handles_labels()[1] + acc.get_legend_handles_labels()[1]
        ax.legend(lines, labels, fontsize=8, loc="lower left")
    if title:
        ax.set_title(title, fontsize=10)
    save_figure(fig, path)


def _smooth(values: np.ndarray, window: int) -> np.ndarray:
    """Trailing moving average (the first points average over what exists so far)."""
    csum = np.cumsum(np.insert(values, 0, 0.0))
    idx = np.arange(1, len(values) + 1)
    lo = np.maximum(0, idx - window)
    return (csum[idx] - csum[lo]) / (idx - lo)
