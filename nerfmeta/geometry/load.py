"""A fitted run's model and scene, loaded as the fit loaded them (for ``nerfmeta mesh`` / ``eval-geometry``).

Apart from :mod:`nerfmeta.geometry.runs`, which the fit itself imports, so that the run folder and
the geometry it reports do not import each other.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from nerfmeta.data import load_scene
from nerfmeta.errors import ConfigError
from nerfmeta.fields.base import RadianceModel
from nerfmeta.fields.registry import build_model
from nerfmeta.fit.checkpoint import CHECKPOINT_NAME, load_checkpoint, restore_model
from nerfmeta.fit.run import RunConfig


def load_run_model(run: str | os.PathLike) -> tuple[RadianceModel, Any]:
    """The model a ``nerfmeta fit`` run folder holds (its checkpoint) and its scene, loaded as the fit loaded it."""
    run = Path(run)
    if not (run / "config.json").is_file() or not (run / CHECKPOINT_NAME).is_file():
        raise ConfigError(f"{run}: not a fit run folder (no config.json and {CHECKPOINT_NAME})")
    config = RunConfig.from_json(json.loads((run / "config.json").read_text()))
    scene = load_scene(config.scene, downscale=config.downscale, background=config.background, normalize=config.normalize)
    model = build_model(config.backbone, config.model_config(scene), scene.bounds, seed=0)
    restore_model(model, load_checkpoint(run / CHECKPOINT_NAME))
    return model, scene
