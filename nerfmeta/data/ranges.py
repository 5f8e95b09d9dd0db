"""Ranges a scene's numbers must lie in: refuse what no capture produces instead of fitting garbage.

Every value here is finite and of the right sign already (see :mod:`nerfmeta.data.common`); these
checks catch numbers that are finite but absurd, which used to end in a ZeroDivisionError or NaN
deep in a fit, or in a "successful" fit at 0.6 dB. Lengths are compared with ``far`` (the ray
length), so the rules are the same at every scale:

- ``far`` lies in :data:`FAR_RANGE` (any unit: beyond it the normalisation factor and squared
  distances leave float range); ``far / near <= MAX_DEPTH_RATIO`` when ``near > 0``.
- The cameras' spread (largest distance of a camera centre from their mean) is at most
  ``MAX_SPREAD_PER_FAR * far`` and, unless every camera stands at one point, at least
  ``MIN_SPREAD_PER_FAR * far``.
- Camera coordinates are at most ``MAX_POSITION_PER_SIZE`` scene sizes (``max(spread, far)``) from the
  origin: farther, float64 cannot tell the cameras apart.
- A file's ``aabb`` is between ``MIN_SPREAD_PER_FAR * far`` and ``MAX_SPREAD_PER_FAR * far`` in size
  and some camera is within ``far`` of it (otherwise no ray reaches it).
- Focal lengths are between ``MIN_FOCAL_PER_SIZE`` and ``MAX_FOCAL_PER_SIZE`` times the image size
  (a field of view between about 180 and 6e-5 degrees) and the principal point lies within one
  image size of the image (``-W <= cx <= 2 W``).
"""

from __future__ import annotations

import torch

from nerfmeta.errors import SceneError

FAR_RANGE = (1e-12, 1e12)
"""Smallest and largest accepted ``far``, in the file's units."""
MAX_DEPTH_RATIO = 1e6
"""Largest accepted ``far / near`` (a float32 depth cannot resolve more)."""
MIN_SPREAD_PER_FAR = 1e-9
"""Smallest camera spread (and aabb size) per ``far``, unless every camera stands at one point."""
MAX_SPREAD_PER_FAR = 1e6
"""Largest camera spread (and aabb size) per ``far``."""
MAX_POSITION_PER_SIZE = 1e9
"""Largest distance of a camera from the origin per scene size (``max(spread, far)``)."""
MIN_FOCAL_PER_SIZE = 1e-3
"""Smallest focal length per image size (a field of view just under 180 degrees)."""
MAX_FOCAL_PER_SIZE = 1e6
"""Largest focal length per image size."""


def check_depth_range(near: float, far: float, *, where: str) -> None:
    """Refuse a ``far`` outside :data:`FAR_RANGE` or a ``far / near`` above :data:`MAX_DEPTH_RATIO`."""
    lo, hi = FAR_RANGE
    if not lo <= far <= hi:
        raise SceneError(f"{where}: far {far:g} is outside {lo:g}..{hi:g}; rescale the scene's units")
    if near > 0 and far / near > MAX_DEPTH_RATIO:
        raise SceneError(f"{where}: far / near is {far / near:.3g} (near {near:g}, far {far:g}); "
                         f"it must be at most {MAX_DEPTH_RATIO:g}")


def check_intrinsics(intrinsics: torch.Tensor, height: int, width: int, *, where: str) -> None:
    """Refuse focal lengths and principal points no pinhole camera has.

    Args:
        intrinsics: (n, 4) ``(fx, fy, cx, cy)`` in pixels for ``height`` x ``width`` images.
    """
    sizes = torch.tensor([width, height, width, height], dtype=torch.float64)
    rel = intrinsics.double() / sizes
    names = ("fx", "fy", "cx", "cy")
    for col in (0, 1):
        bad = (rel[:, col] < MIN_FOCAL_PER_SIZE) | (rel[:, col] > MAX_FOCAL_PER_SIZE)
        if bool(bad.any()):
            k = int(bad.nonzero()[0])
            raise SceneError(f"{where}: view {k}: focal {names[col]} {float(intrinsics[k, col]):g} px is not between "
                             f"{MIN_FOCAL_PER_SIZE:g} and {MAX_FOCAL_PER_SIZE:g} times the image size")
    for col in (2, 3):
        bad = (rel[:, col] < -1.0) | (rel[:, col] > 2.0)
        if bool(bad.any()):
            k = int(bad.nonzero()[0])
            raise SceneError(f"{where}: view {k}: principal point {names[col]} {float(intrinsics[k, col]):g} px lies "
                             f"more than one image size outside the {width}x{height} image")


def camera_spread(poses: torch.Tensor) -> float:
    """Largest distance of a camera centre from the mean centre. poses: (n, 4, 4) camera-to-world."""
    centres = poses[:, :3, 3].double()
    return float(torch.linalg.vector_norm(centres - centres.mean(0), dim=-1).max())


def check_geometry(poses: torch.Tensor, far: float, aabb: torch.Tensor | None, *, where: str) -> None:
    """Refuse camera layouts and boxes out of proportion with ``far`` (rules in the module docstring).

    Args:
        poses: (n, 4, 4) camera-to-world in the file's frame.
        far: the ray length in the file's units.
        aabb: (2, 3) the file's box, or None.
    """
    spread = camera_spread(poses)
    if spread > MAX_SPREAD_PER_FAR * far or 0 < spread < MIN_SPREAD_PER_FAR * far:
        raise SceneError(f"{where}: the cameras are spread over {spread:g} but rays end at far {far:g}; "
                         "near/far and the camera positions must be in the same units")
    position = float(poses[:, :3, 3].double().abs().max())
    if position > MAX_POSITION_PER_SIZE * max(spread, far):
        raise SceneError(f"{where}: a camera stands {position:g} from the origin, too far for a scene of size "
                         f"{max(spread, far):g} (float precision); move the scene nearer the origin")
    if aabb is None:
        return
    size = float((aabb[1] - aabb[0]).max())
    if not MIN_SPREAD_PER_FAR * far <= size <= MAX_SPREAD_PER_FAR * far:
        raise SceneError(f"{where}: aabb of size {size:g} is out of proportion with far {far:g}")
    centres = poses[:, :3, 3].double()
    gap = torch.linalg.vector_norm((aabb[0].double() - centres).clamp(min=0) + (centres - aabb[1].double()).clamp(min=0), dim=-1)
    if float(gap.min()) >= far:
        raise SceneError(f"{where}: aabb is {float(gap.min()):g} from the nearest camera but rays end at far {far:g}")
