"""Silhouette carving: a density and colour start for the voxel grid from the scene's training views.

A point belongs to the *visual hull* when every training view that sees it (it projects inside
the image, in front of the camera) shows foreground there. The foreground comes from the views'
alpha when the scene has one, else from a uniform background detected on the image borders; a scene
with neither (a photograph with a busy background) is not carved, and the reason is returned.

Everything here is a pure function of tensors (shapes in the docstrings) and works in the scene's
own loaded (normalised) frame: the poses and the grid points it is given are in that frame.
The colour start is the mean, over the views that see a hull point, of the colour it projects to
(occlusion ignored: a blurred but right-coloured start). :func:`carve_start` bundles it for a fit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from nerfmeta.data.scene_type import border_pixels

ALPHA_FOREGROUND = 0.5
"""A pixel is foreground when its alpha exceeds this."""
BORDER_PIXELS = 2
"""Width (pixels) of the image border the background colour is read from."""
BACKGROUND_TOLERANCE = 0.04
"""Largest per-channel difference from the background colour for a pixel to count as background."""
UNIFORM_FRACTION = 0.97
"""The background is uniform when at least this fraction of border pixels lies within the tolerance."""
MIN_FOREGROUND = 0.002
"""A view's foreground must cover at least this fraction of its pixels (else the mask is not trusted)."""
MIN_VIEWS = 4
"""Fewest training views a hull is carved from (fewer views leave most of the box uncarved)."""
HULL_MARGIN_VOXELS = 5.0
"""Foreground masks are dilated by this many grid voxels (as seen from the cameras, rounded up to whole pixels): a voxel
centre's projection is not pixel-exact, and a hull that cuts into the object leaves surface the fit cannot grow back
(points outside the hull start empty and are never sampled again). On the seed-7 design chair (1.2 pixels a coarse
voxel) a one-pixel dilation ended 0.20 dB below scratch at 1000 steps, two pixels 0.16, three 0.14 and five 0.11. On
the seed-13 table (a top on thin legs) 2.4 voxels (3 px) ended 0.47 dB below scratch, 5 voxels 0.12; on the seed-11
lamp and the seed-17 airplane and chair 5 voxels changed the PSNR at 200-1000 steps by 0.1 dB or less. 8 voxels fill
the space between an airplane's wings (1.8 dB behind scratch). BENCHMARKS.md, *concave objects and the early check*."""
HULL_MISSES = 1
"""A point stays in the hull when at most this many views that see it show background there (mask noise)..."""
SEEN_FRACTION = 0.5
"""A point on foreground in every view that sees it, but seen by fewer than this fraction of the views, is *unknown*,
not hull: few silhouettes cut little (on lego, whose cameras look down from a hemisphere, such points far from the
object made the fine box 48 % of the scene box against scratch's 3.7 %). Unknown points start as scratch's do."""
MISS_EVERY = 8
"""... and at most one per this many views that see it (a point seen by few views gets no benefit of the doubt)."""


@dataclass(frozen=True)
class Silhouettes:
    """Foreground masks of a scene's training views, or why there are none.

    Attributes:
        masks: (V, H, W) bool foreground, None when the scene cannot be carved.
        source: ``alpha``, ``background`` (a uniform background colour) or ``none``.
        background: the RGB background the masks were cut from (``background`` source), else None.
        reason: one sentence saying where the masks came from or why there are none.
    """

    masks: torch.Tensor | None
    source: str
    background: tuple[float, float, float] | None
    reason: str


@dataclass(frozen=True)
class CarveStart:
    """A carved start on a grid's points.

    Attributes:
        occupied: (N,) bool, the points inside the visual hull.
        unknown: (N,) bool, the points no view shows on background but fewer than :data:`SEEN_FRACTION` of the views see.
        rgb: (N, 3) mean projected colour in [0, 1] (the background colour outside the hull).
        hull_fraction: fraction of the points inside the hull.
        silhouettes: where the masks came from.
        margin_px: pixels the masks were dilated by.
    """

    occupied: torch.Tensor
    unknown: torch.Tensor
    rgb: torch.Tensor
    hull_fraction: float
    silhouettes: Silhouettes
    margin_px: int = 1


def uniform_background(images: torch.Tensor, *, tolerance: float = BACKGROUND_TOLERANCE,
                       fraction: float = UNIFORM_FRACTION) -> tuple[tuple[float, float, float] | None, float]:
    """The background colour of (V, H, W, 3) images when their borders are uniform, else None; and the uniform fraction.

    The colour is the per-channel median of the border pixels; the borders are uniform when at least
    ``fraction`` of them lie within ``tolerance`` (every channel) of it.
    """
    border = border_pixels(images, BORDER_PIXELS)
    colour = border.median(0).values
    close = ((border - colour).abs() <= tolerance).all(-1).float().mean().item()
    if close < fraction:
        return None, close
    return tuple(float(x) for x in colour), close


def dilate_masks(masks: torch.Tensor, pixels: int) -> torch.Tensor:
    """(V, H, W) bool masks dilated by ``pixels`` (a square structuring element)."""
    if pixels <= 0:
        return masks
    k = 2 * pixels + 1
    pool = torch.nn.functional.max_pool2d
    rows = pool(masks.float()[:, None], (1, k), stride=1, padding=(0, pixels))  # a square is a row then a column
    return pool(rows, (k, 1), stride=1, padding=(pixels, 0))[:, 0] > 0


def pixels_per_unit(poses: torch.Tensor, intrinsics: torch.Tensor, centre: torch.Tensor) -> float:
    """Pixels one world unit spans at ``centre`` (3,), as seen by the median of the (V, 4, 4) cameras (intrinsics (V, 4))."""
    distance = torch.linalg.vector_norm(poses[:, :3, 3] - centre, dim=-1).clamp_min(1e-6)
    return float((intrinsics[:, :2].mean(-1) / distance).median())


def silhouettes(images: torch.Tensor, alphas: torch.Tensor | None) -> Silhouettes:
    """Foreground masks of (V, H, W, 3) images with optional (V, H, W) alphas, or the reason there are none."""
    if images.shape[0] < MIN_VIEWS:
        return Silhouettes(None, "none", None, f"{images.shape[0]} training views: carving needs at least {MIN_VIEWS}")
    if alphas is not None and bool((alphas < 1.0 - 1e-3).any()):
        masks, source, bg = alphas > ALPHA_FOREGROUND, "alpha", None
        reason = "foreground from the views' alpha"
    else:
        bg, close = uniform_background(images)
        if bg is None:
            return Silhouettes(None, "none", None, f"no alpha, and the image borders are not a uniform background "
                               f"({100 * close:.0f}% of border pixels within {BACKGROUND_TOLERANCE:g} of their median, "
                               f"{100 * UNIFORM_FRACTION:.0f}% needed): not carved")
        colour = torch.tensor(bg, dtype=images.dtype, device=images.device)
        masks, source = ((images - colour).abs() > BACKGROUND_TOLERANCE).any(-1), "background"
        reason = f"foreground where the views differ from the uniform background {[round(c, 3) for c in bg]}"
    cover = masks.float().mean((1, 2))
    if bool((cover < MIN_FOREGROUND).any()) or bool((cover > 1.0 - MIN_FOREGROUND).all()):
        return Silhouettes(None, "none", bg, f"{reason}, but some view's foreground covers "
                           f"{100 * float(cover.min()):.2f}%..{100 * float(cover.max()):.1f}% of it: not carved")
    return Silhouettes(masks, source, bg, reason)


def project(points: torch.Tensor, poses: torch.Tensor, intrinsics: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel positions of world points in every view (OpenGL cameras, looking along -z).

    Args:
        points: (N, 3) world points.
        poses: (V, 4, 4) camera-to-world.
        intrinsics: (V, 4) ``(fx, fy, cx, cy)``.

    Returns:
        (V, N, 2) ``(x, y)`` pixel positions (pixel ``(i, j)`` covers ``[i, i+1) x [j, j+1)``) and
        (V, N) bool, in front of the camera.
    """
    rot, t = poses[:, :3, :3], poses[:, :3, 3]
    cam = torch.einsum("vji,vnj->vni", rot, points[None] - t[:, None])  # R^T (p - t)
    depth = -cam[..., 2]
    front = depth > 1e-6
    z = depth.clamp(min=1e-6)
    fx, fy, cx, cy = (intrinsics[:, k, None] for k in range(4))
    x = cx + fx * cam[..., 0] / z
    y = cy - fy * cam[..., 1] / z
    return torch.stack([x, y], -1), front


def lookup(points: torch.Tensor, masks: torch.Tensor, poses: torch.Tensor, intrinsics: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Where (N, 3) points fall in every view: (V, N) flat pixel index, (V, N) bool seen (in front, inside the image),
    and (V, N) bool the (V, H, W) ``masks`` are set there (and seen)."""
    v, h, w = masks.shape
    xy, front = project(points, poses, intrinsics)
    col, row = xy[..., 0].floor().long(), xy[..., 1].floor().long()
    seen = front & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    flat = row.clamp(0, h - 1) * w + col.clamp(0, w - 1)
    return flat, seen, torch.gather(masks.reshape(v, -1), 1, flat) & seen


def visual_hull(points: torch.Tensor, masks: torch.Tensor, poses: torch.Tensor, intrinsics: torch.Tensor,
                *, misses: int = HULL_MISSES, chunk: int = 1 << 16) -> tuple[torch.Tensor, torch.Tensor]:
    """Which points lie in the visual hull.

    Args:
        points: (N, 3) world points.
        masks: (V, H, W) bool foreground.
        poses: (V, 4, 4) camera-to-world; intrinsics: (V, 4).
        misses: views that see a point on background it may still survive (mask noise), at most one per
            :data:`MISS_EVERY` views that see it.

    Returns:
        (N,) bool: seen by at least one view, and on background in at most that many of the views that see it; and
        (N,) float: the fraction of the views that see each point.
    """
    inside, seen_fraction = [], []
    for p in points.split(chunk):
        _, seen, fg = lookup(p, masks, poses, intrinsics)
        inside.append(in_hull(seen, fg, misses=misses))
        seen_fraction.append(seen.sum(0).float() / masks.shape[0])
    return torch.cat(inside), torch.cat(seen_fraction)


def in_hull(seen: torch.Tensor, fg: torch.Tensor, *, misses: int = HULL_MISSES) -> torch.Tensor:
    """(N,) bool :func:`visual_hull`'s test from (V, N) bool ``seen`` and ``fg`` (seen on foreground)."""
    n_seen = seen.sum(0)
    allowed = torch.clamp(n_seen // MISS_EVERY, max=misses)
    return (n_seen > 0) & ((seen & ~fg).sum(0) <= allowed)


def mean_colour(points: torch.Tensor, masks: torch.Tensor, images: torch.Tensor, poses: torch.Tensor,
                intrinsics: torch.Tensor, fallback: torch.Tensor, *, chunk: int = 1 << 16) -> torch.Tensor:
    """(N, 3) mean colour the (N, 3) points project to over the views where they fall on foreground (``masks``
    (V, H, W) bool); ``fallback`` (3,) for points on no view's foreground. ``images``: (V, H, W, 3)."""
    v = images.shape[0]
    flat_images = images.reshape(v, -1, 3)
    out = []
    for p in points.split(chunk):
        flat, _, fg = lookup(p, masks, poses, intrinsics)
        rgb = torch.gather(flat_images, 1, flat[..., None].expand(-1, -1, 3))  # (V, n, 3)
        weight = fg.to(rgb.dtype)[..., None]
        total = weight.sum(0)
        mean = (rgb * weight).sum(0) / total.clamp(min=1.0)
        out.append(torch.where(total > 0, mean, fallback.to(rgb.dtype)))
    return torch.cat(out)


def start_colours(occupied: torch.Tensor, points: torch.Tensor, masks: torch.Tensor, images: torch.Tensor,
                  poses: torch.Tensor, intrinsics: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """(N, 3) a start's colours: :func:`mean_colour` on the (N,) ``occupied`` points, ``background`` (3,) elsewhere."""
    return torch.where(occupied[:, None], mean_colour(points, masks, images, poses, intrinsics, background), background)


def carve(points: torch.Tensor, images: torch.Tensor, alphas: torch.Tensor | None, poses: torch.Tensor,
          intrinsics: torch.Tensor, background: torch.Tensor, *, voxel: float = 0.0) -> CarveStart | Silhouettes:
    """The carved start on (N, 3) ``points`` from training views, or the :class:`Silhouettes` saying why not.

    Args:
        points: (N, 3) grid points in the scene's loaded frame.
        voxel: the grid's voxel side (world units): the masks are dilated by :data:`HULL_MARGIN_VOXELS` of them as seen
            from the cameras at the points' centre, at least one pixel (0: one pixel).
        images: (V, H, W, 3) training images composited on ``background`` (3,).
        alphas: (V, H, W) their alpha, None for opaque images.
        poses: (V, 4, 4); intrinsics: (V, 4).
    """
    sil = silhouettes(images, alphas)
    if sil.masks is None:
        return sil
    centre = 0.5 * (points.amin(0) + points.amax(0))
    margin = max(1, math.ceil(HULL_MARGIN_VOXELS * voxel * pixels_per_unit(poses, intrinsics, centre) - 1e-6))
    inside, seen_fraction = visual_hull(points, dilate_masks(sil.masks, margin), poses, intrinsics)
    occupied, unknown = inside & (seen_fraction >= SEEN_FRACTION), inside & (seen_fraction < SEEN_FRACTION)
    if not bool(occupied.any()):
        return Silhouettes(None, "none", sil.background, f"{sil.reason}, but no grid point lies in every silhouette: not carved")
    rgb = start_colours(occupied, points, sil.masks, images, poses, intrinsics, background)
    return CarveStart(occupied, unknown, rgb, float(occupied.float().mean()), sil, margin)
