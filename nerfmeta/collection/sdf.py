"""Signed-distance primitives, smooth union and rigid transforms (pure functions).

Every primitive takes ``points`` of shape (..., 3) in its own local frame (z up) and returns the
signed distance (...,): negative inside, positive outside, zero on the surface. All primitives
are exact Euclidean distances (they are 1-Lipschitz), so sphere tracing never overshoots;
:func:`smooth_union` rounds the seam between two shapes and stays a conservative bound.

Only element-wise additions, multiplications, ``abs``/``min``/``max`` and ``sqrt`` are used, never
a matrix product or a reduction whose order could change with the thread count, so results are
bit-identical however torch splits the work. Shape parameters are Python floats; device and
dtype follow ``points``.

Rotations are unit quaternions ``(w, x, y, z)`` given as Python tuples; the helpers here build
and compose them with NumPy in float64 (they are parameters, not data).
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]

IDENTITY: Quat = (1.0, 0.0, 0.0, 0.0)


def _norm2(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    return torch.sqrt(x * x + y * y)


def _norm3(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    return torch.sqrt(x * x + y * y + z * z)


# Each primitive has a component form ``*_xyz(x, y, z, ...)`` taking the three coordinate
# tensors (...,) separately (what the shape evaluator uses, to avoid stacking and unbinding
# every step) and a ``points`` form taking (..., 3).


def sphere_xyz(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor, radius: float) -> torch.Tensor:
    return _norm3(x, y, z) - radius


def sphere(points: torch.Tensor, radius: float) -> torch.Tensor:
    """Sphere of ``radius`` at the origin.

    Args:
        points: (..., 3).

    Returns:
        (...,) signed distances.
    """
    return sphere_xyz(*points.unbind(-1), radius)


def box_xyz(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor, half_size: Sequence[float], rounding: float = 0.0) -> torch.Tensor:
    qx = x.abs() - (half_size[0] - rounding)
    qy = y.abs() - (half_size[1] - rounding)
    qz = z.abs() - (half_size[2] - rounding)
    outside = _norm3(qx.clamp(min=0.0), qy.clamp(min=0.0), qz.clamp(min=0.0))
    inside = torch.maximum(torch.maximum(qx, qy), qz).clamp(max=0.0)
    return outside + inside - rounding


def box(points: torch.Tensor, half_size: Sequence[float], rounding: float = 0.0) -> torch.Tensor:
    """Axis-aligned box centred at the origin, its edges rounded with radius ``rounding``.

    Args:
        points: (..., 3).
        half_size: (3,) outer half extents; ``rounding`` must not exceed the smallest one.
        rounding: edge radius (0 for a sharp box).

    Returns:
        (...,) signed distances.
    """
    return box_xyz(*points.unbind(-1), half_size, rounding)


def cylinder_xyz(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor, radius: float, half_height: float, rounding: float = 0.0) -> torch.Tensor:
    dr = _norm2(x, y) - (radius - rounding)
    dz = z.abs() - (half_height - rounding)
    inside = torch.maximum(dr, dz).clamp(max=0.0)
    outside = _norm2(dr.clamp(min=0.0), dz.clamp(min=0.0))
    return inside + outside - rounding


def cylinder(points: torch.Tensor, radius: float, half_height: float, rounding: float = 0.0) -> torch.Tensor:
    """Capped cylinder along z centred at the origin, its rims rounded with radius ``rounding``.

    Args:
        points: (..., 3).

    Returns:
        (...,) signed distances.
    """
    return cylinder_xyz(*points.unbind(-1), radius, half_height, rounding)


def capsule_xyz(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor, a: Sequence[float], b: Sequence[float], radius: float) -> torch.Tensor:
    bax, bay, baz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    inv = 1.0 / (bax * bax + bay * bay + baz * baz)
    pax, pay, paz = x - a[0], y - a[1], z - a[2]
    h = ((pax * bax + pay * bay + paz * baz) * inv).clamp(0.0, 1.0)
    return _norm3(pax - h * bax, pay - h * bay, paz - h * baz) - radius


def capsule(points: torch.Tensor, a: Sequence[float], b: Sequence[float], radius: float) -> torch.Tensor:
    """All points within ``radius`` of the segment from ``a`` to ``b`` ((3,) each, ``a != b``).

    Args:
        points: (..., 3).

    Returns:
        (...,) signed distances.
    """
    return capsule_xyz(*points.unbind(-1), a, b, radius)


def torus_xyz(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor, major: float, minor: float) -> torch.Tensor:
    return _norm2(_norm2(x, y) - major, z) - minor


def torus(points: torch.Tensor, major: float, minor: float) -> torch.Tensor:
    """Torus in the xy-plane around z: a tube of radius ``minor`` on a circle of radius ``major``.

    Args:
        points: (..., 3).

    Returns:
        (...,) signed distances.
    """
    return torus_xyz(*points.unbind(-1), major, minor)


def capped_torus_xyz(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor, major: float, minor: float, half_angle: float) -> torch.Tensor:
    s, c = math.sin(half_angle), math.cos(half_angle)
    ax = x.abs()
    rho = _norm2(ax, y)
    k = torch.where(c * ax > s * y, ax * s + y * c, rho)
    sq = (ax * ax + y * y + z * z + (major * major) - (2.0 * major) * k).clamp(min=0.0)
    return torch.sqrt(sq) - minor


def capped_torus(points: torch.Tensor, major: float, minor: float, half_angle: float) -> torch.Tensor:
    """An arc of a torus in the xy-plane: the tube over angles within ``half_angle`` of the +y axis.

    Args:
        points: (..., 3).
        half_angle: half the arc's opening in radians, in (0, pi].

    Returns:
        (...,) signed distances.
    """
    return capped_torus_xyz(*points.unbind(-1), major, minor, half_angle)


def round_cone_xyz(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor, radius_bottom: float, radius_top: float, height: float) -> torch.Tensor:
    b = (radius_bottom - radius_top) / height
    a = math.sqrt(1.0 - b * b)
    rho = _norm2(x, y)
    k = rho * (-b) + z * a
    d_bottom = _norm2(rho, z) - radius_bottom
    d_top = _norm2(rho, z - height) - radius_top
    d_side = rho * a + z * b - radius_bottom
    return torch.where(k < 0.0, d_bottom, torch.where(k > a * height, d_top, d_side))


def round_cone(points: torch.Tensor, radius_bottom: float, radius_top: float, height: float) -> torch.Tensor:
    """Convex hull of a sphere at the origin and one at ``(0, 0, height)`` (a tapered capsule).

    Args:
        points: (..., 3).
        radius_bottom, radius_top: sphere radii; ``|radius_bottom - radius_top| < height``.

    Returns:
        (...,) signed distances.
    """
    return round_cone_xyz(*points.unbind(-1), radius_bottom, radius_top, height)


def revolution_xyz(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor, profile: Sequence[Sequence[float]], half_thickness: float) -> torch.Tensor:
    rho = _norm2(x, y)
    best = None
    for (ar, az), (br, bz) in zip(profile[:-1], profile[1:]):
        ba_r, ba_z = br - ar, bz - az
        inv = 1.0 / (ba_r * ba_r + ba_z * ba_z)
        pa_r, pa_z = rho - ar, z - az
        h = ((pa_r * ba_r + pa_z * ba_z) * inv).clamp(0.0, 1.0)
        dr, dz = pa_r - h * ba_r, pa_z - h * ba_z
        d2 = dr * dr + dz * dz
        best = d2 if best is None else torch.minimum(best, d2)
    return torch.sqrt(best) - half_thickness


def revolution(points: torch.Tensor, profile: Sequence[Sequence[float]], half_thickness: float) -> torch.Tensor:
    """Thin shell of revolution around z: points within ``half_thickness`` of a swept polyline.

    The polyline lives in the (r, z) half-plane (r >= 0) and is revolved around the z axis; a
    profile starting at r = 0 gives a closed bottom, one ending at r > 0 an open rim. The
    distance in the (r, z) half-plane is the 3-D distance, since the nearest point of a surface
    of revolution lies in the point's own meridian plane.

    Args:
        points: (..., 3).
        profile: (K, 2) polyline vertices ``(r, z)``, K >= 2, consecutive vertices distinct.
        half_thickness: half the wall thickness.

    Returns:
        (...,) signed distances.
    """
    return revolution_xyz(*points.unbind(-1), profile, half_thickness)


def prism_xyz(
    x: torch.Tensor, y: torch.Tensor, z: torch.Tensor, polygon: Sequence[Sequence[float]], half_height: float, rounding: float = 0.0
) -> torch.Tensor:
    # 2-D signed distance to a convex polygon: the distance to the nearest edge segment, signed
    # by the largest signed distance to the edges' lines (all <= 0 exactly inside). Then extruded.
    n = len(polygon)
    orient = 1.0 if _signed_area(polygon) > 0 else -1.0
    d2 = None
    line = None
    for i in range(n):
        vi, vj = polygon[i], polygon[(i + 1) % n]
        ex, ey = vj[0] - vi[0], vj[1] - vi[1]
        length = math.hypot(ex, ey)
        nx, ny = orient * ey / length, -orient * ex / length  # outward unit normal
        wx, wy = x - vi[0], y - vi[1]
        h = ((wx * ex + wy * ey) * (1.0 / (length * length))).clamp(0.0, 1.0)
        bx, by = wx - h * ex, wy - h * ey
        dd = bx * bx + by * by
        li = wx * nx + wy * ny
        d2 = dd if d2 is None else torch.minimum(d2, dd)
        line = li if line is None else torch.maximum(line, li)
    dist = torch.sqrt(d2)
    d_plane = torch.where(line > 0.0, dist, -dist)
    dz = z.abs() - (half_height - rounding)
    outside = _norm2(d_plane.clamp(min=0.0), dz.clamp(min=0.0))
    return torch.maximum(d_plane, dz).clamp(max=0.0) + outside - rounding


def _signed_area(polygon: Sequence[Sequence[float]]) -> float:
    n = len(polygon)
    return 0.5 * sum(polygon[i][0] * polygon[(i + 1) % n][1] - polygon[(i + 1) % n][0] * polygon[i][1] for i in range(n))


def is_convex(polygon: Sequence[Sequence[float]]) -> bool:
    """True for a convex polygon with distinct consecutive vertices (either orientation)."""
    n = len(polygon)
    if n < 3:
        return False
    signs = set()
    for i in range(n):
        a, b, c = polygon[i], polygon[(i + 1) % n], polygon[(i + 2) % n]
        cross = (b[0] - a[0]) * (c[1] - b[1]) - (b[1] - a[1]) * (c[0] - b[0])
        if a == b:
            return False
        if abs(cross) > 1e-12:
            signs.add(cross > 0)
    return len(signs) == 1


def prism(points: torch.Tensor, polygon: Sequence[Sequence[float]], half_height: float, rounding: float = 0.0) -> torch.Tensor:
    """A convex polygon in the xy-plane extruded along z to ``[-half_height, half_height]``.

    With ``rounding`` > 0 the slab is thinned by ``rounding`` and then grown by it, so its edges
    are rounded and its outline lies ``rounding`` outside the polygon.

    Args:
        points: (..., 3).
        polygon: (K, 2) vertices ``(x, y)`` of a convex polygon in either order, K >= 3 (see
            :func:`is_convex`).

    Returns:
        (...,) signed distances.
    """
    return prism_xyz(*points.unbind(-1), polygon, half_height, rounding)


def smooth_union(a: torch.Tensor, b: torch.Tensor, k: float) -> torch.Tensor:
    """Polynomial smooth minimum of two distance fields (the plain minimum when ``k == 0``).

    The seam is filled with a fillet of size about ``k``; the result is at most ``k / 4`` below
    ``min(a, b)``, so the surface grows by at most ``k / 4``.

    Args:
        a, b: (...,) signed distances.

    Returns:
        (...,) signed distances.
    """
    if k <= 0.0:
        return torch.minimum(a, b)
    h = (0.5 + (0.5 / k) * (b - a)).clamp(0.0, 1.0)
    return b + h * (a - b) - k * h * (1.0 - h)


# ---------------------------------------------------------------------------------------------
# Rigid transforms (parameters: NumPy float64; data: element-wise torch)


def quat_from_axis_angle(axis: Sequence[float], angle: float) -> Quat:
    """Unit quaternion ``(w, x, y, z)`` rotating by ``angle`` radians around ``axis``."""
    ax = np.asarray(axis, dtype=np.float64)
    ax = ax / np.linalg.norm(ax)
    s = math.sin(0.5 * angle)
    return (math.cos(0.5 * angle), float(ax[0] * s), float(ax[1] * s), float(ax[2] * s))


def quat_mul(q: Sequence[float], r: Sequence[float]) -> Quat:
    """Hamilton product ``q * r``: the rotation ``r`` followed by ``q``."""
    w1, x1, y1, z1 = q
    w2, x2, y2, z2 = r
    return (
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    )


def quat_to_matrix(q: Sequence[float]) -> np.ndarray:
    """(3, 3) float64 rotation matrix of a quaternion ``(w, x, y, z)`` (normalised first)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(np.asarray(q, dtype=np.float64))
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_from_matrix(m: np.ndarray) -> Quat:
    """Unit quaternion ``(w, x, y, z)`` of a (3, 3) rotation matrix (Shepperd's method)."""
    m = np.asarray(m, dtype=np.float64)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = (0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s)
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = ((m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s)
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = ((m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = ((m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s)
    n = math.sqrt(sum(v * v for v in q))
    return tuple(float(v / n) for v in q)  # type: ignore[return-value]


def to_local_xyz(
    x: torch.Tensor, y: torch.Tensor, z: torch.Tensor, position: Sequence[float], matrix: Sequence[Sequence[float]] | None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Component form of :func:`to_local`; ``matrix`` is the (3, 3) rotation as nested floats, or
    None for no rotation."""
    x = x - position[0]
    y = y - position[1]
    z = z - position[2]
    if matrix is None:
        return x, y, z
    m = matrix
    # local_j = sum_i p_i R[i][j], written out so the summation order is fixed.
    return (
        x * m[0][0] + y * m[1][0] + z * m[2][0],
        x * m[0][1] + y * m[1][1] + z * m[2][1],
        x * m[0][2] + y * m[1][2] + z * m[2][2],
    )


def to_local(points: torch.Tensor, position: Sequence[float], rotation: Sequence[float]) -> torch.Tensor:
    """Express world points in a frame placed at ``position`` with orientation ``rotation``.

    The frame maps local ``p`` to world ``R p + position``; this returns ``R^T (points - position)``.

    Args:
        points: (..., 3).
        position: (3,) frame origin.
        rotation: (4,) unit quaternion ``(w, x, y, z)``.

    Returns:
        (..., 3) local coordinates.
    """
    matrix = None if tuple(float(v) for v in rotation) == IDENTITY else quat_to_matrix(rotation).tolist()
    return torch.stack(to_local_xyz(*points.unbind(-1), position, matrix), dim=-1)
