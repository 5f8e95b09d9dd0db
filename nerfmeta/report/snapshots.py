"""Snapshot renders during a fit: what the model shows at chosen iterations.

Layout of ``RUN/snapshots/``::

    target_view_VVV.png          ground truth of scene view VVV (written with the first snapshot)
    iter_IIIII_view_VVV.png      view VVV rendered after IIIII optimisation steps
                                 (00000: the starting point, i.e. the initialisation)

``VVV`` is the scene's view index (as in ``renders/test_VVV.png``), ``IIIII`` the ``iter`` of the
``metrics.jsonl`` record. Rendering is a callback that runs after the step's time was taken, so
it never counts in ``time_s`` (see :func:`nerfmeta.fit.loop.fit`); the starting point is rendered
before the fit starts and the final one after it ends.
"""

from __future__ import annotations

import logging
import re
import time
from pathlib import Path
from typing import Iterable, Sequence

import imageio.v3 as iio
import numpy as np
import torch

from nerfmeta.data.scene import Scene
from nerfmeta.errors import ConfigError
from nerfmeta.fields.base import RadianceModel
from nerfmeta.fit.evaluate import render_view
from nerfmeta.io import atomic_path

log = logging.getLogger(__name__)

SNAPSHOT_ITERS = (0, 25, 50, 100, 200, 500, 1000)
"""A good default for ``RunConfig.snapshot_iters``: the init, then roughly doubling."""
SNAPSHOT_VIEWS = 2
"""How many views :func:`default_views` picks."""
SNAPSHOT_DIR = "snapshots"

_SNAPSHOT_RE = re.compile(r"^iter_(\d{5,})_view_(\d{3,})\.png$")


def snapshot_name(iteration: int, view: int) -> str:
    return f"iter_{iteration:05d}_view_{view:03d}.png"


def target_name(view: int) -> str:
    return f"target_view_{view:03d}.png"


def default_views(scene: Scene, n: int = SNAPSHOT_VIEWS) -> tuple[int, ...]:
    """The first ``n`` test views, or the first ``n`` training views when the scene has no test split."""
    views = scene.splits.get("test") or scene.splits.get("train") or ()
    return tuple(views[:n])


def read_snapshots(folder: str | Path) -> dict[int, dict[int, Path]]:
    """The snapshots in a ``snapshots/`` folder: view -> iteration -> PNG path (empty if none)."""
    out: dict[int, dict[int, Path]] = {}
    folder = Path(folder)
    if not folder.is_dir():
        return out
    for path in folder.iterdir():
        m = _SNAPSHOT_RE.match(path.name)
        if m:
            out.setdefault(int(m.group(2)), {})[int(m.group(1))] = path
    return {v: dict(sorted(its.items())) for v, its in sorted(out.items())}


def to_uint8(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) float in [0, 1] -> uint8, rounded."""
    return (np.clip(image, 0.0, 1.0) * 255 + 0.5).astype(np.uint8)


def _write_png(path: Path, image: torch.Tensor) -> None:
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, to_uint8(image.numpy()), extension=".png")


class SnapshotWriter:
    """Fit callback rendering ``views`` at the iterations in ``iters`` into ``out_dir``.

    Use: ``start(model)`` before the fit (renders iteration 0 when it is in ``iters``), the writer
    itself as a callback, and ``finish(model, step)`` after the fit (renders the final iteration).
    The model is rendered without gradients in eval mode, and its train/eval mode is restored.

    Args:
        scene: the scene being fitted (its views, image size and ground truth).
        views: scene view indices to render (e.g. :func:`default_views`).
        iters: iterations (>= 0) to render after; 0 is the starting point.
        out_dir: the ``snapshots/`` folder (created).
        background: (3,) RGB on the model's device.
        chunk: rays rendered at once.

    Raises:
        ConfigError: a negative iteration or a view index outside the scene.
    """

    def __init__(self, scene: Scene, views: Sequence[int], iters: Iterable[int], out_dir: str | Path,
                 background: torch.Tensor, *, chunk: int = 16384):
        iters = tuple(int(i) for i in iters)
        bad = [i for i in iters if i < 0]
        if bad:
            raise ConfigError(f"snapshot iterations {bad}: must be 0 (the starting point) or more")
        bad = [v for v in views if not 0 <= v < scene.n_views]
        if bad:
            raise ConfigError(f"snapshot views {bad}: the scene has views 0..{scene.n_views - 1}")
        self.scene = scene
        self.views = tuple(int(v) for v in views)
        self.iters = frozenset(iters)
        self.out_dir = Path(out_dir)
        self.background = background
        self.chunk = chunk
        self.written: list[int] = []
        self.render_time_s = 0.0

    def __call__(self, record, model: RadianceModel, state) -> None:
        if record.iter in self.iters:
            self.write(record.iter, model)

    def start(self, model: RadianceModel) -> None:
        """Render the starting point (iteration 0) if asked for; call before the first step."""
        if 0 in self.iters:
            self.write(0, model)

    def finish(self, model: RadianceModel, step: int) -> None:
        """Render the final iteration ``step`` unless it was just rendered."""
        if step not in self.written:
            self.write(step, model)

    def write(self, iteration: int, model: RadianceModel) -> None:
        """Render every snapshot view now and save it as ``iter_{iteration}_view_{view}.png``."""
        t0 = time.perf_counter()
        was_training = model.training
        model.eval()
        try:
            renders = [render_view(model, self.scene, v, self.background, chunk=self.chunk) for v in self.views]
        finally:
            model.train(was_training)
        for r in renders:
            target = self.out_dir / target_name(r.view)
            if not target.exists():
                _write_png(target, r.target)
            _write_png(self.out_dir / snapshot_name(iteration, r.view), r.rgb)
        self.written.append(iteration)
        self.render_time_s += time.perf_counter() - t0
        log.debug("snapshot at iteration %d: %d views in %.2f s", iteration, len(renders), time.perf_counter() - t0)

    def as_json(self) -> dict:
        """For ``summary.json["snapshots"]``: the folder, the views, the iterations on disk for every
        view (a resumed fit keeps those written before the interruption) and this session's render time."""
        on_disk = read_snapshots(self.out_dir)
        iters = set.intersection(*(set(on_disk.get(v, {})) for v in self.views)) if self.views else set()
        return {"folder": SNAPSHOT_DIR, "views": list(self.views), "iters": sorted(iters),
                "render_time_s": round(self.render_time_s, 3)}
