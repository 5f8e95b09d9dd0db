"""The README's main job: make a scene, inspect it, fit it, and say where the reports are.

Until classify-and-fit exists this runs a from-scratch fit of the grid backbone on one
procedurally generated object (a chair from ``nerfmeta make-collection``), so it needs no data
from outside the project.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from nerfmeta.collection.generate import CollectionConfig, generate_collection, load_collection
from nerfmeta.data.common import LoadOptions
from nerfmeta.errors import ConfigError
from nerfmeta.fit.loop import Callback, FitConfig
from nerfmeta.fit.run import RunConfig, run_fit
from nerfmeta.inspect import SceneSummary, inspect_scene


@dataclass(frozen=True)
class DemoConfig:
    """Settings of the demo."""

    category: str = "chair"
    """Category of the generated object."""
    resolution: int = 64
    """Image size of the generated views."""
    views: int = 40
    """Training views."""
    test_views: int = 8
    """Test views (on other directions than the training views)."""
    time_budget_s: float = 60.0
    """Optimisation time of the fit."""
    seed: int = 0
    """Seed of the object and of the fit."""


@dataclass(frozen=True)
class DemoResult:
    scene: Path
    inspect: SceneSummary
    summary: dict[str, Any]
    out: Path


def run_demo(config: DemoConfig, out: str | Path, *, overwrite: bool = False, callbacks: Sequence[Callback] = ()) -> DemoResult:
    """Generate one object scene into ``out/scene``, plot its cameras into ``out/inspect``, fit it into ``out/fit``."""
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise ConfigError(f"{out}: folder exists and is not empty; pass --overwrite to replace it")
        shutil.rmtree(out)
    collection = config_collection(config)
    index = generate_collection(collection, out / "scene")
    coll = load_collection(index)
    scene_path = coll.scene_path(coll.scenes[0])
    summary = inspect_scene(scene_path, LoadOptions(), out=out / "inspect")
    run = RunConfig(scene=str(scene_path), backbone="grid", fit=FitConfig(iters=100_000, time_budget_s=config.time_budget_s, seed=config.seed))
    fit_summary = run_fit(run, out / "fit", callbacks=callbacks)
    return DemoResult(scene_path, summary, fit_summary, out)


def config_collection(config: DemoConfig) -> CollectionConfig:
    return CollectionConfig(
        categories=(config.category,), scenes_per_category=1, views=config.views, test_views=config.test_views,
        resolution=config.resolution, seed=config.seed, val_fraction=0.0, test_fraction=0.0,
    )
