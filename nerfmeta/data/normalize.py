"""Scene normalisation at load time: the similarity transform that brings a scene into range.

The rule (:func:`normalization_for`), applied by every parser through
:func:`~nerfmeta.data.common.build_scene` unless ``LoadOptions(normalize=False)``:

- **Scale**: a scene whose ``far`` lies in :data:`SANE_FAR` (0.1 to 100) keeps its scale;
  otherwise every length is multiplied by ``CANONICAL_FAR / far``, so the loaded ``far`` is 6 (the
  NeRF-synthetic value) and everything a ray can reach lies within 6 of a camera.
- **Offset**: a scene whose box centre ``c`` (the centre of ``bounds``: the file's ``aabb``, else
  the camera frusta's box) lies within ``far`` of the origin keeps its position; otherwise the
  scene is moved so that ``c`` is at the origin.

Each part is the identity unless it is needed, so scenes already in a sane range are loaded
exactly as written: NeRF-synthetic scenes (cameras at radius 4, near/far 2/6), the tiny test
scene and generated collections (objects in ``[-1, 1]^3``, far = radius + 2) all get the
identity. The decision reads only ``far`` and the box centre: every scene of a collection has the
same ``far`` and a box inside the canonical ``[-1, 1]^3``, so all of them get the same transform
(the identity for any camera radius below 98), and category models and meta-learned
initialisations, which live in that canonical box, keep meaning the same place in every scene.

The transform is a similarity (one scale, no rotation), so rays, renders and PSNR are the same
as in the file's frame up to rounding; what it removes is the loss of float32 precision and of
fixed tolerances for scenes of extreme size or far from the origin.
"""

from __future__ import annotations

import torch

from nerfmeta.data.scene import Normalization

SANE_FAR = (0.1, 100.0)
"""A scene whose ``far`` lies in this range (inclusive) keeps its scale."""
CANONICAL_FAR = 6.0
"""``far`` of a rescaled scene (NeRF-synthetic's, so the defaults tuned on it apply)."""


def normalization_for(bounds: torch.Tensor, far: float) -> Normalization:
    """The transform the loader applies to a scene (see the module docstring for the rule).

    Args:
        bounds: (2, 3) ``[min_xyz, max_xyz]`` box of the content in the file's frame.
        far: the file's ray end distance (> 0).

    Returns:
        The :class:`Normalization` (scale ``CANONICAL_FAR / far`` or 1, offset moving the box
        centre to the origin or 0).
    """
    if not far > 0:
        raise ValueError(f"far must be > 0, got {far}")
    lo, hi = SANE_FAR
    scale = 1.0 if lo <= far <= hi else CANONICAL_FAR / far
    centre = 0.5 * (bounds[0].double() + bounds[1].double())
    if float(torch.linalg.vector_norm(centre)) <= far:
        return Normalization(scale, (0.0, 0.0, 0.0))
    offset = tuple(float(v) for v in -scale * centre)
    return Normalization(scale, offset)  # type: ignore[arg-type]


def describe(norm: Normalization) -> str:
    """One line for reports: ``none (identity)`` or the scale and offset that were applied."""
    if norm.is_identity:
        return "none (identity)"
    offset = ", ".join(f"{v:.6g}" for v in norm.offset)
    return f"scale {norm.scale:.6g}, offset [{offset}] (loaded = scale * file + offset)"
