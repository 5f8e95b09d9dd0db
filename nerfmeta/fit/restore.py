"""A finished (or checkpointed) fit run loaded back: its config, its scene as the fit saw it, its model.

What ``nerfmeta render``, ``nerfmeta mesh``, ``nerfmeta eval-geometry`` and the benchmark scripts
start from. The scene is loaded with the run's own options and put in the fit's space
(:func:`nerfmeta.fit.run.run_scene`: NDC for a forward-facing scene), and the backbone config is
resolved for that scene (a contracted space for an unbounded one), so the checkpoint fits the model.
"""

from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass
from pathlib import Path

import torch

from nerfmeta.data.scene import Scene
from nerfmeta.errors import ConfigError
from nerfmeta.fields.base import RadianceModel
from nerfmeta.fields.registry import build_model
from nerfmeta.fit.checkpoint import CHECKPOINT_NAME, load_checkpoint, restore_model
from nerfmeta.fit.run import RunConfig, run_scene
from nerfmeta.runfolder import is_run_of


@dataclass(frozen=True)
class FittedRun:
    """A fit run folder's contents, ready to render.

    Attributes:
        config: the run's ``config.json``.
        scene: the scene as the fit saw it (its space, bounds and splits).
        model: the checkpoint's model, in eval mode, on ``config.device``.
    """

    config: RunConfig
    scene: Scene
    model: RadianceModel


def load_fitted_run(folder: str | os.PathLike, device: str | None = None) -> FittedRun:
    """Load the fit run in ``folder`` (``device`` overrides the run's own).

    Raises:
        ConfigError: not a fit run folder with a checkpoint, an unreadable config, or CUDA asked for
            where there is none (one line naming the file or value).
    """
    folder = Path(folder)
    if not is_run_of(folder, "fit") or not (folder / CHECKPOINT_NAME).is_file():
        raise ConfigError(f"{folder}: not a 'nerfmeta fit' run folder with a {CHECKPOINT_NAME}")
    try:
        config = RunConfig.from_json(json.loads((folder / "config.json").read_text()))
    except (OSError, ValueError, TypeError) as err:
        raise ConfigError(f"{folder / 'config.json'}: unreadable run config ({err})") from None
    if device is not None:
        config = dataclasses.replace(config, device=device)
    if config.device.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"--device {config.device}: CUDA is not available on this machine (pass --device cpu)")
    scene = run_scene(config)
    model = build_model(config.backbone, config.model_config(scene), scene.bounds, seed=config.fit.seed,
                        device=torch.device(config.device))
    restore_model(model, load_checkpoint(folder / CHECKPOINT_NAME))
    model.eval()
    return FittedRun(config, scene, model)
