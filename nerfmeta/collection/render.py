"""Batched sphere tracing of signed-distance fields on the CPU, with shading and anti-aliasing.

Pure functions: the field is given as two callables, ``sdf(points (N, 3)) -> (N,)`` and
``albedo(points (N, 3)) -> (N, 3)``; cameras as camera-to-world poses in nerfmeta's OpenGL
convention (x right, y up, looking along -z, pixel centres at ``i + 0.5``).

How an image is made (:func:`render_views`):

1. one ray through every pixel centre of every view, all traced together; rays are clipped to
   the object's box, marched with the distance as step (never overshooting an exact SDF),
   dropped from the batch when they hit (distance below ``hit_epsilon`` of a pixel footprint)
   or leave the box, and stopped after ``max_steps``;
2. hits are shaded: albedo x (ambient x ambient occlusion + Lambert terms of fixed world-space
   lights) + an optional Blinn-Phong highlight; normals by a tetrahedral finite difference;
3. pixels on a silhouette, near a silhouette (a ray that passed within a pixel of the surface)
   or on a colour edge are traced again with ``supersample x supersample`` rays; their alpha is
   the fraction of those rays that hit and their colour the mean colour of the hits. With
   ``adaptive=False`` every pixel is supersampled.

Background is transparent: alpha 0 and RGB 0. All arithmetic is element-wise or an exact
min/max, so images are bit-identical for any number of threads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import torch
import torch.nn.functional as F

from nerfmeta.render.rays import intersect_aabb

if TYPE_CHECKING:
    from nerfmeta.collection.shapes import Shape

SdfFn = Callable[[torch.Tensor], torch.Tensor]

# Fixed world-space lights (unit direction towards the light, intensity): a key light from
# above, a weaker fill from the other side and a faint bounce from below, so that undersides
# seen by full-sphere cameras are not black. Ambient light comes mostly from the sky (+z).
LIGHTS: tuple[tuple[tuple[float, float, float], float], ...] = (
    ((0.4364357804719848, -0.3273268353539886, 0.8382736431011233), 0.72),
    ((-0.6139406135149205, 0.6139406135149205, 0.49613893835683387), 0.28),
    ((0.18814417367671948, 0.2822162605150792, -0.9407208683835974), 0.18),
)


@dataclass(frozen=True)
class RenderConfig:
    """How SDF scenes are rendered."""

    supersample: int = 2
    """Rays per pixel along each axis on anti-aliased pixels (supersample**2 rays)."""
    adaptive: bool = True
    """Supersample only silhouette, near-silhouette and colour-edge pixels (False: every pixel)."""
    max_steps: int = 96
    """Sphere-tracing steps before a ray is given up (then a hit only if within a pixel)."""
    hit_epsilon: float = 0.1
    """A ray hits when the distance falls below this fraction of a (sub)pixel footprint."""
    ambient: float = 0.32
    """Strength of the sky light (brighter on upward-facing surfaces)."""
    ambient_occlusion: float = 2.5
    """Strength of the 3-tap SDF ambient occlusion (0 disables it)."""
    specular: float = 0.0
    """Strength of a white Blinn-Phong highlight from the lights (0 keeps shading view-independent)."""
    shininess: int = 32
    """Blinn-Phong exponent, a power of two."""
    edge_contrast: float = 0.2
    """Colour difference to a 4-neighbour that marks a hit pixel for supersampling."""

    def validate(self) -> None:
        if self.supersample < 1:
            raise ValueError(f"supersample must be >= 1, got {self.supersample}")
        if self.shininess < 1 or self.shininess & (self.shininess - 1):
            raise ValueError(f"shininess must be a power of two, got {self.shininess}")
        if self.max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {self.max_steps}")


def pixel_rays(
    poses: torch.Tensor, focal: float, height: int, width: int, view: torch.Tensor, px: torch.Tensor, py: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """World rays through image positions of several cameras (pinhole, principal point at the centre).

    Args:
        poses: (V, 4, 4) camera-to-world matrices (OpenGL convention).
        focal: focal length in pixels.
        view: (N,) long, which camera each ray belongs to.
        px, py: (N,) image positions in pixels (``i + 0.5`` is the centre of column ``i``).

    Returns:
        origins (N, 3) and unit directions (N, 3), in the dtype of ``px``.
    """
    c2w = poses.to(px.dtype)[view]  # (N, 4, 4)
    dx = (px - 0.5 * width) / focal
    dy = -(py - 0.5 * height) / focal
    # d = R @ (dx, dy, -1), written out element-wise so the summation order is fixed.
    cols = [c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2]]
    d = cols[0] * dx[:, None] + cols[1] * dy[:, None] - cols[2]
    x, y, z = d.unbind(-1)
    d = d / torch.sqrt(x * x + y * y + z * z)[:, None]
    return c2w[:, :3, 3].contiguous(), d


@dataclass(frozen=True)
class Trace:
    """What :func:`sphere_trace` found along each ray.

    Attributes:
        t: (N,) distance of the hit, or where marching stopped.
        hit: (N,) bool.
        closest: (N,) the smallest ``sdf / t`` seen along the ray (for near-miss cone tests).
        last: (N,) the field's value at ``t`` (meaningful for hits).
        free: (N,) the cone of half-angle ``cone`` around the ray is proven empty from
            ``t_start`` up to this distance (``t_start`` when no cone was given).
    """

    t: torch.Tensor
    hit: torch.Tensor
    closest: torch.Tensor
    last: torch.Tensor
    free: torch.Tensor


def sphere_trace(
    sdf: SdfFn,
    origins: torch.Tensor,
    directions: torch.Tensor,
    t_start: torch.Tensor,
    t_end: torch.Tensor,
    hit_scale: float,
    max_steps: int,
    cone: float = 0.0,
) -> Trace:
    """March rays through a distance field until they hit, pass ``t_end`` or run out of steps.

    Each step evaluates ``d = sdf(o + t dir)`` and moves ``t`` by ``d``: the ball of radius ``d``
    is empty, so an exact SDF is never overshot. With ``cone > 0`` the same balls also prove a
    cone around the ray empty: the cross-section at ``t'`` (radius ``cone * t'``) lies in the ball
    at ``t`` while ``|t' - t| (1 + cone) + cone * t <= d``; ``free`` is how far a chain of such
    overlapping pieces reaches, so rays inside the cone (a pixel's supersamples) may start there.

    Args:
        sdf: maps (M, 3) points to (M,) signed distances.
        origins: (N, 3).
        directions: (N, 3) unit vectors.
        t_start: (N,) positive distance to start at.
        t_end: (N,) distance past which a ray has missed.
        hit_scale: a ray hits where ``sdf < hit_scale * t`` (a cone of that half-angle).
        max_steps: at most this many field evaluations per ray; rays still marching then hit
            when their last distance is below ``4 * hit_scale * t``.
        cone: half-angle (radians) of the cone whose empty stretch ``free`` reports.

    Returns:
        a :class:`Trace`.
    """
    n = origins.shape[0]
    t_out = t_start.clone()
    hit_out = torch.zeros(n, dtype=torch.bool, device=origins.device)
    close_out = torch.full((n,), float("inf"), dtype=origins.dtype, device=origins.device)
    last_out = torch.zeros(n, dtype=origins.dtype, device=origins.device)
    free_out = t_start.clone()
    idx = torch.arange(n, device=origins.device)
    o, d, t, t_max = origins, directions, t_start, t_end
    closest = close_out.clone()
    free = t_start.clone()
    chain = torch.ones(n, dtype=torch.bool, device=origins.device)
    dist = None
    for _ in range(max_steps):
        if idx.numel() == 0:
            break
        dist = sdf(o + d * t[:, None])
        closest = torch.minimum(closest, dist / t)
        if cone > 0.0:
            reach = (dist - cone * t) * (1.0 / (1.0 + cone))
            chain = chain & (reach > 0.0) & (t - reach <= free)
            free = torch.where(chain, torch.maximum(free, t + reach), free)
        is_hit = dist < hit_scale * t
        t_next = t + dist
        done = is_hit | (t_next > t_max)
        if bool(done.any()):
            fin = done.nonzero(as_tuple=True)[0]
            gi = idx[fin]
            t_out[gi] = t[fin]
            hit_out[gi] = is_hit[fin]
            close_out[gi] = closest[fin]
            last_out[gi] = dist[fin]
            free_out[gi] = free[fin]
            keep = (~done).nonzero(as_tuple=True)[0]
            idx, o, d, t_max, closest, dist = idx[keep], o[keep], d[keep], t_max[keep], closest[keep], dist[keep]
            free, chain = free[keep], chain[keep]
            t = t_next[keep]
        else:
            t = t_next
    if idx.numel() and dist is not None:
        t_out[idx] = t
        hit_out[idx] = dist < 4.0 * hit_scale * t
        close_out[idx] = closest
        last_out[idx] = dist
        free_out[idx] = free
    return Trace(t_out, hit_out, close_out, last_out, free_out)


def sdf_normals(sdf: SdfFn, points: torch.Tensor, values: torch.Tensor, h: float) -> torch.Tensor:
    """Unit outward normals by forward differences of step ``h`` (three field evaluations).

    Args:
        points: (N, 3).
        values: (N,) the field at ``points`` (known from tracing).

    Returns:
        (N, 3) unit normals.
    """
    n = points.shape[0]
    x, y, z = points.unbind(-1)
    shifted = torch.cat(
        [torch.stack([x + h, y, z], -1), torch.stack([x, y + h, z], -1), torch.stack([x, y, z + h], -1)], dim=0
    )
    gx, gy, gz = (sdf(shifted).reshape(3, n) - values).unbind(0)
    norm = torch.sqrt(gx * gx + gy * gy + gz * gz).clamp(min=1e-12)
    return torch.stack([gx / norm, gy / norm, gz / norm], dim=-1)


def shade(
    sdf: SdfFn,
    albedo: SdfFn,
    points: torch.Tensor,
    values: torch.Tensor,
    directions: torch.Tensor,
    config: RenderConfig,
    normal_step: float = 1e-3,
) -> torch.Tensor:
    """Colour of surface points lit by :data:`LIGHTS` (no shadows).

    Args:
        points: (N, 3) surface points.
        values: (N,) the field at ``points``.
        directions: (N, 3) unit directions of the rays that found them.

    Returns:
        (N, 3) RGB in [0, 1].
    """
    n = points.shape[0]
    if n == 0:
        return points.new_zeros(0, 3)
    normal = sdf_normals(sdf, points, values, normal_step)
    nx, ny, nz = normal.unbind(-1)
    light = config.ambient * (0.7 + 0.3 * nz)
    if config.ambient_occlusion > 0:
        # Three taps along the normal: an exact SDF gives d = s away from other geometry.
        taps = (0.03, 0.08, 0.15)
        dists = sdf(torch.cat([points + normal * s for s in taps], dim=0)).reshape(len(taps), n)
        occ = None
        for i, s in enumerate(taps):
            term = (s - dists[i]).clamp(min=0.0) * (0.75**i)
            occ = term if occ is None else occ + term
        light = light * (1.0 - config.ambient_occlusion * occ).clamp(0.0, 1.0)
    spec = torch.zeros_like(light)
    for (lx, ly, lz), intensity in LIGHTS:
        ndl = (nx * lx + ny * ly + nz * lz).clamp(min=0.0)
        light = light + intensity * ndl
        if config.specular > 0:
            hx, hy, hz = lx - directions[:, 0], ly - directions[:, 1], lz - directions[:, 2]
            hn = torch.sqrt(hx * hx + hy * hy + hz * hz).clamp(min=1e-12)
            s = ((nx * hx + ny * hy + nz * hz) / hn).clamp(min=0.0)
            for _ in range(int(math.log2(config.shininess))):
                s = s * s
            spec = spec + (config.specular * intensity) * s * (ndl > 0).to(s.dtype)
    rgb = albedo(points) * light[:, None] + spec[:, None]
    return rgb.clamp(0.0, 1.0)


def render_rays(
    sdf: SdfFn,
    albedo: SdfFn,
    origins: torch.Tensor,
    directions: torch.Tensor,
    aabb: torch.Tensor,
    footprint: float,
    config: RenderConfig,
    near_angle: float | None = None,
    t_min: torch.Tensor | None = None,
    cone: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Trace and shade rays against a field whose surface lies inside ``aabb``.

    Args:
        origins: (N, 3), outside the surface.
        directions: (N, 3) unit.
        aabb: (2, 3) box holding the surface.
        footprint: angular size of a ray's pixel (radians); sets the hit tolerance.
        near_angle: cone half-angle (radians) of the near-miss test; ``2 * footprint`` if None.
        t_min: (N,) distances before which each ray is known to meet nothing (or None).
        cone: half-angle of the cone whose empty stretch is reported (see :func:`sphere_trace`).

    Returns:
        rgb (N, 3) (zero for misses); hit (N,) bool; near (N,) bool: the ray came within
        ``near_angle`` of the surface (true for hits; sphere tracing samples the distance only at
        its steps, but the true minimum along the ray is at least half the smallest sample, so
        ``near_angle`` should be twice the cone of interest); free (N,): the cone is empty up to
        this distance (0 for rays that miss the box).
    """
    n = origins.shape[0]
    t_in, t_out, box_hit = intersect_aabb(origins, directions, aabb.to(origins.dtype))
    rgb = origins.new_zeros(n, 3)
    hit = torch.zeros(n, dtype=torch.bool, device=origins.device)
    near = torch.zeros_like(hit)
    free = origins.new_zeros(n)
    sel = box_hit.nonzero(as_tuple=True)[0]
    if sel.numel() == 0:
        return rgb, hit, near, free
    o, d = origins[sel], directions[sel]
    t0 = t_in[sel].clamp(min=1e-4)
    if t_min is not None:
        t0 = torch.maximum(t0, t_min[sel])
    tr = sphere_trace(sdf, o, d, t0, t_out[sel], config.hit_epsilon * footprint, config.max_steps, cone)
    hs = sel[tr.hit]
    hit[hs] = True
    near[sel] = tr.hit | (tr.closest < (2.0 * footprint if near_angle is None else near_angle))
    free[sel] = tr.free
    hp = tr.hit.nonzero(as_tuple=True)[0]
    rgb[hs] = shade(sdf, albedo, o[hp] + d[hp] * tr.t[hp, None], tr.last[hp], d[hp], config)
    return rgb, hit, near, free


def _neighbour_contrast(img: torch.Tensor) -> torch.Tensor:
    """(V, H, W, C) -> (V, H, W): the largest per-channel absolute difference to the 4 neighbours."""
    pad = F.pad(img.permute(0, 3, 1, 2), (1, 1, 1, 1), mode="replicate").permute(0, 2, 3, 1)
    centre = pad[:, 1:-1, 1:-1]
    out = None
    for nb in (pad[:, 1:-1, :-2], pad[:, 1:-1, 2:], pad[:, :-2, 1:-1], pad[:, 2:, 1:-1]):
        diff = (nb - centre).abs().amax(dim=-1)
        out = diff if out is None else torch.maximum(out, diff)
    return out


def render_views(
    sdf: SdfFn,
    albedo: SdfFn,
    poses: torch.Tensor,
    focal: float,
    height: int,
    width: int,
    aabb: torch.Tensor,
    config: RenderConfig = RenderConfig(),
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """Render RGBA images of a signed-distance field from several cameras at once.

    Args:
        sdf: (M, 3) -> (M,) signed distances (world units).
        albedo: (M, 3) -> (M, 3) RGB in [0, 1].
        poses: (V, 4, 4) camera-to-world matrices; the cameras must be outside the surface.
        focal: focal length in pixels (square pixels, principal point at the image centre).
        aabb: (2, 3) box holding the surface.
        dtype: arithmetic precision of the rays and the field.

    Returns:
        (V, H, W, 4) RGBA in [0, 1]; straight (not premultiplied) alpha, RGB 0 where alpha is 0.
    """
    config.validate()
    v_count = poses.shape[0]
    device = poses.device
    vv, yy, xx = torch.meshgrid(
        torch.arange(v_count, device=device),
        torch.arange(height, device=device),
        torch.arange(width, device=device),
        indexing="ij",
    )
    view, row, col = vv.reshape(-1), yy.reshape(-1), xx.reshape(-1)
    px, py = col.to(dtype) + 0.5, row.to(dtype) + 0.5
    origins, dirs = pixel_rays(poses, focal, height, width, view, px, py)
    ss = config.supersample
    # Centre rays: a miss passing within a pixel's half-diagonal (0.71 px) may still cover part of
    # its pixel, so the near-miss cone is twice that.
    # The centre pass also proves, per pixel, how far a cone covering the whole pixel (0.75 px,
    # beyond its half-diagonal) is empty: the pixel's supersamples start tracing there.
    rgb, hit, near, free = render_rays(sdf, albedo, origins, dirs, aabb, 1.0 / (focal * ss), config, 1.5 / focal, cone=0.75 / focal)
    alpha = hit.to(dtype)
    if ss == 1:
        out = torch.cat([rgb, alpha[:, None]], dim=-1)
        return out.reshape(v_count, height, width, 4)

    if config.adaptive:
        # A hit pixel is partly uncovered only where a 4-neighbour misses; a missed pixel is
        # partly covered only if its ray came within the pixel's half-diagonal of the surface.
        hit_img = hit.reshape(v_count, height, width)
        pad = F.pad(hit_img, (1, 1, 1, 1), value=False)
        all_nb = pad[:, 1:-1, :-2] & pad[:, 1:-1, 2:] & pad[:, :-2, 1:-1] & pad[:, 2:, 1:-1]
        colour_edge = (_neighbour_contrast(rgb.reshape(v_count, height, width, 3)) > config.edge_contrast) & hit_img
        edge = ((hit_img & ~all_nb) | colour_edge).reshape(-1) | (near & ~hit)
    else:
        edge = torch.ones_like(hit)
    e = edge.nonzero(as_tuple=True)[0]
    if e.numel():
        offsets = [((i + 0.5) / ss - 0.5, (j + 0.5) / ss - 0.5) for j in range(ss) for i in range(ss)]
        sub_view = view[e].repeat(len(offsets))
        ox = torch.tensor([o[0] for o in offsets], dtype=dtype, device=device).repeat_interleave(e.numel())
        oy = torch.tensor([o[1] for o in offsets], dtype=dtype, device=device).repeat_interleave(e.numel())
        so, sd = pixel_rays(poses, focal, height, width, sub_view, px[e].repeat(len(offsets)) + ox, py[e].repeat(len(offsets)) + oy)
        start = free[e].repeat(len(offsets))
        s_rgb, s_hit, _, _ = render_rays(sdf, albedo, so, sd, aabb, 1.0 / (focal * ss), config, t_min=start)
        s_rgb = s_rgb.reshape(len(offsets), e.numel(), 3)
        s_hit = s_hit.reshape(len(offsets), e.numel()).to(dtype)
        count, total = s_hit[0], s_rgb[0]
        for k in range(1, len(offsets)):  # fixed-order sums
            count = count + s_hit[k]
            total = total + s_rgb[k]
        alpha[e] = count / len(offsets)
        rgb[e] = total / count.clamp(min=1.0)[:, None]
    out = torch.cat([rgb, alpha[:, None]], dim=-1)
    return out.reshape(v_count, height, width, 4)


def render_shape(shape: "Shape", poses: torch.Tensor, focal: float, height: int, width: int, config: RenderConfig = RenderConfig()) -> torch.Tensor:
    """Render a :class:`~nerfmeta.collection.shapes.Shape` (its box padded by 0.02).

    Args:
        poses: (V, 4, 4) camera-to-world matrices.

    Returns:
        (V, H, W, 4) RGBA in [0, 1].
    """
    from nerfmeta.collection.shapes import shape_bounds

    aabb = torch.as_tensor(shape_bounds(shape), dtype=torch.float32)
    pad = torch.tensor([[-0.02] * 3, [0.02] * 3])
    return render_views(shape.sdf, shape.albedo, poses, focal, height, width, aabb + pad, config)
