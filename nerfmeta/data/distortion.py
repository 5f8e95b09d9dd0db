"""Lens distortion removed on load: the images of a scene whose cameras carry distortion coefficients are resampled
into the pinhole images of the same intrinsics, so every ray nerfmeta casts is a straight pinhole ray.

The model is OpenCV's and COLMAP's (``OPENCV``, ``RADIAL``, ``SIMPLE_RADIAL``; nerfstudio's ``k1 k2 k3 p1 p2``): for a
point ``(x, y)`` on the normalised image plane, ``r^2 = x^2 + y^2``,

    x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y

and the photo shows at pixel ``(fx x_d + cx, fy y_d + cy)`` what a pinhole camera shows at ``(fx x + cx, fy y + cy)``.
Each output pixel centre is mapped forward through it and the photo sampled there (bilinear); pixels whose source
falls outside the photo repeat its edge (COLMAP's undistorter crops them instead; keeping the size keeps the
intrinsics). Fisheye models are refused by the parsers, not handled here.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from nerfmeta.data.common import ViewStack

COEFFICIENTS = ("k1", "k2", "k3", "p1", "p2")
"""The coefficients applied, in the order of a coefficient row."""


def distort_normalised(x: torch.Tensor, y: torch.Tensor, coeffs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(x_d, y_d)``: normalised image points ``(x, y)`` moved by the distortion ``coeffs`` = (k1, k2, k3, p1, p2)."""
    k1, k2, k3, p1, p2 = (coeffs[i] for i in range(5))
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def source_grid(height: int, width: int, intrinsics: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
    """(1, height, width, 2) ``grid_sample`` coordinates (``align_corners=False``) in the distorted photo of each pixel
    centre of the undistorted image (intrinsics ``(fx, fy, cx, cy)``, pixel centres at ``i + 0.5``)."""
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    coeffs = coeffs.to(torch.float64)
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64) + 0.5,
                          torch.arange(width, dtype=torch.float64) + 0.5, indexing="ij")
    xd, yd = distort_normalised((u - cx) / fx, (v - cy) / fy, coeffs)
    grid = torch.stack([(fx * xd + cx) / width * 2 - 1, (fy * yd + cy) / height * 2 - 1], dim=-1)
    return grid.unsqueeze(0)


def undistort_image(image: torch.Tensor, intrinsics: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
    """The pinhole image (same size and intrinsics) of an ``(h, w)`` or ``(h, w, c)`` photo with distortion
    ``coeffs``."""
    planar = image.dim() == 2
    chw = (image.unsqueeze(0) if planar else image.permute(2, 0, 1)).unsqueeze(0)
    grid = source_grid(image.shape[0], image.shape[1], intrinsics, coeffs).to(image.dtype)
    out = F.grid_sample(chw, grid, mode="bilinear", padding_mode="border", align_corners=False)[0]
    return out[0] if planar else out.permute(1, 2, 0).contiguous()


def undistort_views_(views: ViewStack, intrinsics: torch.Tensor, coeffs: torch.Tensor) -> ViewStack:
    """Resample in place every image (and alpha) of ``views`` whose coefficient row (``(n, 5)``,
    :data:`COEFFICIENTS`) is not zero into its pinhole image (``intrinsics``: ``(n, 4)``, for the images as read);
    returns ``views`` (in place: a scene's image stack can be most of the memory a fit uses)."""
    for i in range(len(views.images)):
        if bool((coeffs[i] != 0).any()):
            views.images[i] = undistort_image(views.images[i], intrinsics[i], coeffs[i])
            if views.alphas is not None:
                views.alphas[i] = undistort_image(views.alphas[i], intrinsics[i], coeffs[i])
    return views
