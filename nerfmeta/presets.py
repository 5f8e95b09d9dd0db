"""Named recipes for ``nerfmeta fit --preset NAME``: backbone settings and fit settings measured together for a kind of scene.

A preset is data, a constant here. It fills in values *under* the command line's own: ``--set KEY=VALUE`` wins over
the preset's backbone settings, and an option given (``--batch-rays 1024``) over its fit settings. A preset names its
backbone; ``--backbone`` may repeat it but not contradict it. What a preset sets lands in the run's ``config.json``
like any other value, so the run resumes, reads and compares without it.

Why presets exist: a recipe of eight settings typed by hand is easy to get wrong, and a missing one can fail
silently. Session 16 left out three of the concave recipe's settings by mistake and the cup was never carved
(BENCHMARKS.md, *Surfaces: carving concavities*, section 14).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Collection, Mapping

from nerfmeta.errors import ConfigError


@dataclass(frozen=True)
class Preset:
    """One recipe.

    Attributes:
        backbone: the backbone it is for.
        model: backbone config values (field name -> typed value), as ``--set`` would give them.
        fit: :class:`~nerfmeta.fit.loop.FitConfig` values (field name -> value), as the fit options would give them.
        about: one line for ``--help``: what it is for and where it was measured.
    """

    backbone: str
    model: Mapping[str, Any]
    fit: Mapping[str, Any]
    about: str


PRESETS: Mapping[str, Preset] = MappingProxyType({
    "concave": Preset(
        backbone="sdf",
        model=MappingProxyType({
            "view_dependent": False,  # a diffuse colour cannot fake the concavity's parallax
            "init_variance": 0.1,  # start soft (s = e), so the surface can still change topology
            "variance_lr": 1e-2,
            "color_grid": 64,  # texture in a grid, not in the SDF network's features
            "eikonal_start_weight": 1e-3,  # a weak eikonal term early lets the cup open ...
            "eikonal_ramp": (3500, 5000),  # ... the full one from step 5000 makes it a distance again
            "occupancy_margin": 1.0,  # march a narrow band: 40-50 % more steps in the same time
            "shell_weight": 5e-3,  # walls the photos barely place end thin, not thick (3 mugs: 0.25-0.31 % Chamfer)
        }),
        fit=MappingProxyType({
            "batch_rays": 512,
            "lr_decay": 0.3,  # rates end at 0.3 of their start, not 0.1: a fuller carve, a thinner inner wall in 10 min
            "holdout_tile": 0.0,  # every pixel trained on, and no early stop: the recipe's eikonal ramp runs late
        }),
        about="surfaces of concave objects (a cup, a bowl) with --backbone sdf: the README recipe that carved every "
              "generated mug in 10-minute fits (BENCHMARKS.md, Surfaces: carving concavities, sections 9-16); its "
              "eikonal ramp ends at step 5000, so give it a budget well beyond that",
    ),
})
"""The presets by name."""


def get_preset(name: str) -> Preset:
    """The preset called ``name``; a one-line :class:`ConfigError` naming the choices otherwise."""
    if name not in PRESETS:
        raise ConfigError(f"--preset {name!r}: unknown preset; choose one of {', '.join(sorted(PRESETS))}")
    return PRESETS[name]


def preset_backbone(name: str, preset: Preset, backbone: str | None) -> str:
    """The backbone of a fit with ``preset``: its own, which ``backbone`` (the ``--backbone`` given, or None) may repeat
    but not contradict."""
    if backbone is not None and backbone != preset.backbone:
        raise ConfigError(f"--preset {name} is a recipe for --backbone {preset.backbone}, not --backbone {backbone}; "
                          f"leave --backbone out or use {preset.backbone}")
    return preset.backbone


def describe(name: str, preset: Preset, overridden: Collection[str] = ()) -> str:
    """What ``preset`` sets, as the options a user would type (for the fit's first printed line and the help).

    ``overridden``: the preset's keys (fit fields and ``--set`` keys) the options given replace; they are left out of
    the list and named at its end, so the line never shows a value the fit does not use.
    """
    def show(value: Any) -> str:
        if isinstance(value, bool):
            return str(value).lower()
        if isinstance(value, tuple):
            return "[" + ",".join(str(v) for v in value) + "]"
        return f"{value:g}" if isinstance(value, float) else str(value)

    options = [f"--backbone {preset.backbone}"]
    options += [f"--{key.replace('_', '-')} {show(value)}" for key, value in preset.fit.items() if key not in overridden]
    options += [f"--set {key}={show(value)}" for key, value in preset.model.items() if key not in overridden]
    replaced = [f"--{key.replace('_', '-')}" for key in preset.fit if key in overridden]
    replaced += [f"--set {key}" for key in preset.model if key in overridden]
    return f"--preset {name}: " + " ".join(options) + (f" ({', '.join(replaced)}: the options given)" if replaced else "")
