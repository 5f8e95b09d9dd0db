"""A fitted run's model and scene, loaded as the fit loaded them (for ``nerfmeta mesh`` / ``eval-geometry``).

Apart from :mod:`nerfmeta.geometry.runs`, which the fit itself imports, so that the run folder and
the geometry it reports do not import each other.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from nerfmeta.fields.base import RadianceModel
from nerfmeta.fit.restore import load_fitted_run


def load_run_model(run: str | os.PathLike) -> tuple[RadianceModel, Any]:
    """The model a ``nerfmeta fit`` run folder holds (its checkpoint) and its scene, loaded as the fit loaded it."""
    fitted = load_fitted_run(Path(run))
    return fitted.model, fitted.scene
