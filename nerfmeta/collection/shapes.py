"""Shapes as typed lists of SDF parts, with colour and texture, and their JSON round trip.

A :class:`Shape` is an ordered tuple of :class:`Part` records. Each part is one primitive (a
frozen dataclass such as :class:`Box` or :class:`Revolution`) placed by a position and a unit
quaternion in the *shape frame*, with a :class:`Material` and a ``blend`` radius: part ``i`` is
smooth-unioned with the union of parts ``0..i-1``. The shape frame is mapped to the world by
``world = (shape_point - center) * scale``, which is how samplers' free proportions are
normalised to the canonical ShapeNet-like box (z up, centred, inside ``[-1, 1]^3``).

:func:`shape_to_json` / :func:`shape_from_json` are exact inverses (floats survive JSON), so
``shape_sdf(shape_from_json(record), points)`` is the very geometry that was rendered.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping, Union

import numpy as np
import torch

from nerfmeta.collection import sdf as S

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]

# ---------------------------------------------------------------------------------------------
# Primitives: each knows its signed distance and a conservative local bounding box.


@dataclass(frozen=True)
class Sphere:
    """Sphere at the local origin."""

    radius: float
    kind: ClassVar[str] = "sphere"

    def sdf_xyz(self, x: torch.Tensor, y: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return S.sphere_xyz(x, y, z, self.radius)

    def bounds(self) -> np.ndarray:
        r = self.radius
        return np.array([[-r, -r, -r], [r, r, r]])


@dataclass(frozen=True)
class Box:
    """Box centred at the local origin with outer half extents ``half_size`` and rounded edges."""

    half_size: Vec3
    rounding: float = 0.0
    kind: ClassVar[str] = "box"

    def sdf_xyz(self, x: torch.Tensor, y: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return S.box_xyz(x, y, z, self.half_size, self.rounding)

    def bounds(self) -> np.ndarray:
        h = np.asarray(self.half_size)
        return np.stack([-h, h])


@dataclass(frozen=True)
class Cylinder:
    """Capped cylinder along local z, centred, with rounded rims."""

    radius: float
    half_height: float
    rounding: float = 0.0
    kind: ClassVar[str] = "cylinder"

    def sdf_xyz(self, x: torch.Tensor, y: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return S.cylinder_xyz(x, y, z, self.radius, self.half_height, self.rounding)

    def bounds(self) -> np.ndarray:
        r, h = self.radius, self.half_height
        return np.array([[-r, -r, -h], [r, r, h]])


@dataclass(frozen=True)
class Capsule:
    """Points within ``radius`` of the segment ``a``-``b`` (local coordinates)."""

    a: Vec3
    b: Vec3
    radius: float
    kind: ClassVar[str] = "capsule"

    def sdf_xyz(self, x: torch.Tensor, y: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return S.capsule_xyz(x, y, z, self.a, self.b, self.radius)

    def bounds(self) -> np.ndarray:
        a, b = np.asarray(self.a), np.asarray(self.b)
        return np.stack([np.minimum(a, b) - self.radius, np.maximum(a, b) + self.radius])


@dataclass(frozen=True)
class Torus:
    """Torus in the local xy-plane around z."""

    major: float
    minor: float
    kind: ClassVar[str] = "torus"

    def sdf_xyz(self, x: torch.Tensor, y: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return S.torus_xyz(x, y, z, self.major, self.minor)

    def bounds(self) -> np.ndarray:
        R, r = self.major + self.minor, self.minor
        return np.array([[-R, -R, -r], [R, R, r]])


@dataclass(frozen=True)
class CappedTorus:
    """Arc of a torus in the local xy-plane, ``half_angle`` radians either side of +y."""

    major: float
    minor: float
    half_angle: float
    kind: ClassVar[str] = "capped_torus"

    def sdf_xyz(self, x: torch.Tensor, y: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return S.capped_torus_xyz(x, y, z, self.major, self.minor, self.half_angle)

    def bounds(self) -> np.ndarray:
        phi = np.linspace(-self.half_angle, self.half_angle, 65)
        x, y = self.major * np.sin(phi), self.major * np.cos(phi)
        r = self.minor
        return np.array([[x.min() - r, y.min() - r, -r], [x.max() + r, y.max() + r, r]])


@dataclass(frozen=True)
class RoundCone:
    """Tapered capsule from a sphere at the local origin to one at ``(0, 0, height)``."""

    radius_bottom: float
    radius_top: float
    height: float
    kind: ClassVar[str] = "round_cone"

    def sdf_xyz(self, x: torch.Tensor, y: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return S.round_cone_xyz(x, y, z, self.radius_bottom, self.radius_top, self.height)

    def bounds(self) -> np.ndarray:
        r = max(self.radius_bottom, self.radius_top)
        return np.array([[-r, -r, -self.radius_bottom], [r, r, self.height + self.radius_top]])


@dataclass(frozen=True)
class Revolution:
    """Thin shell swept by revolving the ``(r, z)`` polyline ``profile`` around local z."""

    profile: tuple[tuple[float, float], ...]
    half_thickness: float
    kind: ClassVar[str] = "revolution"

    def sdf_xyz(self, x: torch.Tensor, y: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return S.revolution_xyz(x, y, z, self.profile, self.half_thickness)

    def bounds(self) -> np.ndarray:
        prof = np.asarray(self.profile)
        r = prof[:, 0].max() + self.half_thickness
        t = self.half_thickness
        return np.array([[-r, -r, prof[:, 1].min() - t], [r, r, prof[:, 1].max() + t]])


@dataclass(frozen=True)
class Prism:
    """Convex polygon ``polygon`` (local xy, vertices in order) extruded along local z, edges rounded."""

    polygon: tuple[tuple[float, float], ...]
    half_height: float
    rounding: float = 0.0
    kind: ClassVar[str] = "prism"

    def __post_init__(self) -> None:
        if not S.is_convex(self.polygon):
            raise ValueError(f"prism polygon must be convex, got {self.polygon}")

    def sdf_xyz(self, x: torch.Tensor, y: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return S.prism_xyz(x, y, z, self.polygon, self.half_height, self.rounding)

    def bounds(self) -> np.ndarray:
        poly = np.asarray(self.polygon)
        r = self.rounding
        return np.array([[*(poly.min(0) - r), -self.half_height], [*(poly.max(0) + r), self.half_height]])


Primitive = Union[Sphere, Box, Cylinder, Capsule, Torus, CappedTorus, RoundCone, Revolution, Prism]
PRIMITIVES: dict[str, type] = {
    cls.kind: cls for cls in (Sphere, Box, Cylinder, Capsule, Torus, CappedTorus, RoundCone, Revolution, Prism)
}

# ---------------------------------------------------------------------------------------------
# Materials: a colour, optionally mixed with a second colour by a procedural texture.

TEXTURES = ("plain", "stripes", "checker", "noise")


@dataclass(frozen=True)
class Material:
    """Surface colour of a part; textures are evaluated in the part's local frame (shape units).

    Attributes:
        color: RGB in [0, 1].
        texture: ``plain``, ``stripes`` (bands across ``axis``), ``checker`` (3-D checkerboard)
            or ``noise`` (two-octave value noise blending ``color`` into ``color2``).
        color2: the second RGB of the texture.
        frequency: texture cycles per shape unit.
        axis: stripe direction (unit vector, local frame).
        duty: fraction of each stripe period painted ``color``.
        phase: shift of the stripes and the checkerboard, in periods.
        seed: decorrelates the noise.
    """

    color: Vec3
    texture: str = "plain"
    color2: Vec3 = (0.0, 0.0, 0.0)
    frequency: float = 1.0
    axis: Vec3 = (0.0, 0.0, 1.0)
    duty: float = 0.5
    phase: float = 0.0
    seed: int = 0


def _hash01(ix: torch.Tensor, iy: torch.Tensor, iz: torch.Tensor, seed: int) -> torch.Tensor:
    """(...,) pseudo-random values in [0, 1] of integer lattice points; exact integer arithmetic."""
    h = (ix * 73856093) ^ (iy * 19349663) ^ (iz * 83492791) ^ (seed * 2654435 + 12345)
    h = h & 0x7FFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0x7FFFFFFF
    h = h ^ (h >> 16)
    return (h & 0xFFFF).to(torch.float32) * (1.0 / 65535.0)


def value_noise(points: torch.Tensor, seed: int) -> torch.Tensor:
    """Trilinear value noise with smoothstep fade, in [0, 1].

    Args:
        points: (..., 3) noise coordinates (one lattice cell per unit).

    Returns:
        (...,) noise values, same dtype as ``points``.
    """
    cell = torch.floor(points)
    f = points - cell
    u = f * f * (3.0 - 2.0 * f)
    i = cell.to(torch.int64)
    ix, iy, iz = i.unbind(-1)
    ux, uy, uz = u.unbind(-1)
    out = None
    for dx in (0, 1):
        wx = ux if dx else 1.0 - ux
        for dy in (0, 1):
            wy = uy if dy else 1.0 - uy
            for dz in (0, 1):
                wz = uz if dz else 1.0 - uz
                v = _hash01(ix + dx, iy + dy, iz + dz, seed).to(points.dtype)
                term = v * (wx * wy * wz)
                out = term if out is None else out + term
    return out


def material_albedo(material: Material, local: torch.Tensor) -> torch.Tensor:
    """RGB albedo of ``material`` at part-local points.

    Args:
        local: (N, 3) points in the part's local frame.

    Returns:
        (N, 3) RGB in [0, 1].
    """
    c1 = torch.tensor(material.color, dtype=local.dtype, device=local.device)
    if material.texture == "plain":
        return c1.expand(local.shape[0], 3)
    c2 = torch.tensor(material.color2, dtype=local.dtype, device=local.device)
    f = material.frequency
    phase = material.phase
    x, y, z = local.unbind(-1)
    if material.texture == "stripes":
        ax, ay, az = material.axis
        s = (x * ax + y * ay + z * az) * f + phase
        w = ((s - torch.floor(s)) >= material.duty).to(local.dtype)
    elif material.texture == "checker":
        s = torch.floor(x * f + phase) + torch.floor(y * f + phase) + torch.floor(z * f + phase)
        w = s - 2.0 * torch.floor(s * 0.5)
    elif material.texture == "noise":
        p = local * f
        n = value_noise(p, material.seed) * 0.65 + value_noise(p * 2.03 + 17.0, material.seed + 1) * 0.35
        t = ((n - 0.3) * 2.5).clamp(0.0, 1.0)
        w = t * t * (3.0 - 2.0 * t)
    else:
        raise ValueError(f"unknown texture {material.texture!r}; expected one of {TEXTURES}")
    w = w.unsqueeze(-1)
    return c1 + w * (c2 - c1)


# ---------------------------------------------------------------------------------------------
# Parts and shapes


@dataclass(frozen=True)
class Part:
    """One primitive placed in the shape frame.

    Attributes:
        name: readable role, e.g. ``seat`` or ``leg_2``.
        primitive: the geometry in its local frame.
        material: colour and texture (local frame).
        position: (3,) where the local origin sits in the shape frame.
        rotation: (4,) unit quaternion ``(w, x, y, z)`` from local to shape frame.
        blend: smooth-union radius with the union of the parts before this one (0 = hard union).
    """

    name: str
    primitive: Primitive
    material: Material
    position: Vec3 = (0.0, 0.0, 0.0)
    rotation: Quat = S.IDENTITY
    blend: float = 0.0

    @functools.cached_property
    def matrix(self) -> tuple[tuple[float, ...], ...] | None:
        """The (3, 3) local-to-shape rotation as nested floats, None for the identity."""
        if tuple(float(v) for v in self.rotation) == S.IDENTITY:
            return None
        return tuple(tuple(row) for row in S.quat_to_matrix(self.rotation).tolist())

    def local_xyz(self, x: torch.Tensor, y: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Shape-frame coordinates (N,) each -> part-local coordinates (N,) each."""
        return S.to_local_xyz(x, y, z, self.position, self.matrix)

    def local(self, p: torch.Tensor) -> torch.Tensor:
        """(N, 3) shape-frame points -> (N, 3) part-local points."""
        return torch.stack(self.local_xyz(*p.unbind(-1)), dim=-1)

    def sdf(self, p: torch.Tensor) -> torch.Tensor:
        """(N, 3) shape-frame points -> (N,) signed distance to this part alone."""
        return self.primitive.sdf_xyz(*self.local_xyz(*p.unbind(-1)))

    def bounds(self) -> np.ndarray:
        """(2, 3) conservative shape-frame bounding box ``[min, max]``."""
        lo, hi = self.primitive.bounds()
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        world = corners @ S.quat_to_matrix(self.rotation).T + np.asarray(self.position)
        return np.stack([world.min(0), world.max(0)])


@dataclass(frozen=True)
class Shape:
    """A procedural object: parts in a shape frame plus the map to the canonical world frame.

    Attributes:
        category: the category name it was sampled from.
        parts: the parts, unioned in order.
        center: (3,) shape-frame point placed at the world origin.
        scale: world units per shape unit (``world = (shape_point - center) * scale``).
        traits: the sampler's high-level choices (proportions, counts, styles), for the record;
            the geometry is defined by ``parts`` alone.
    """

    category: str
    parts: tuple[Part, ...]
    center: Vec3 = (0.0, 0.0, 0.0)
    scale: float = 1.0
    traits: Mapping[str, Any] = field(default_factory=dict)

    def sdf(self, points: torch.Tensor) -> torch.Tensor:
        """(N, 3) world points -> (N,) signed distances (see :func:`shape_sdf`)."""
        return shape_sdf(self, points)

    def albedo(self, points: torch.Tensor) -> torch.Tensor:
        """(N, 3) world points -> (N, 3) RGB (see :func:`shape_albedo`)."""
        return shape_albedo(self, points)


def _to_shape_frame(shape: Shape, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    x, y, z = points.unbind(-1)
    inv = 1.0 / shape.scale
    cx, cy, cz = shape.center
    return x * inv + cx, y * inv + cy, z * inv + cz


def shape_sdf(shape: Shape, points: torch.Tensor) -> torch.Tensor:
    """Signed distance to ``shape`` at world points (negative inside).

    Args:
        points: (N, 3) world coordinates; dtype and device are kept.

    Returns:
        (N,) signed distances in world units.
    """
    x, y, z = _to_shape_frame(shape, points)
    d = None
    for part in shape.parts:
        dp = part.primitive.sdf_xyz(*part.local_xyz(x, y, z))
        d = dp if d is None else S.smooth_union(d, dp, part.blend)
    return d * shape.scale


def shape_albedo(shape: Shape, points: torch.Tensor) -> torch.Tensor:
    """RGB albedo at world points: the material of the nearest part, textured in its frame.

    Args:
        points: (N, 3) world coordinates (normally on the surface).

    Returns:
        (N, 3) RGB in [0, 1].
    """
    x, y, z = _to_shape_frame(shape, points)
    locals_ = [part.local_xyz(x, y, z) for part in shape.parts]
    dists = torch.stack([part.primitive.sdf_xyz(*loc) for part, loc in zip(shape.parts, locals_)], dim=-1)
    nearest = dists.argmin(dim=-1)
    out = torch.zeros(points.shape[0], 3, dtype=points.dtype, device=points.device)
    for k, (part, loc) in enumerate(zip(shape.parts, locals_)):
        sel = (nearest == k).nonzero(as_tuple=True)[0]
        if sel.numel():
            out[sel] = material_albedo(part.material, torch.stack([c[sel] for c in loc], dim=-1))
    return out


def shape_part_bounds(parts: tuple[Part, ...]) -> np.ndarray:
    """(2, 3) conservative shape-frame box around ``parts``, grown by each blend's bulge (k/4)."""
    boxes = np.stack([p.bounds() for p in parts])
    pad = max((p.blend for p in parts), default=0.0) * 0.25
    return np.stack([boxes[:, 0].min(0) - pad, boxes[:, 1].max(0) + pad])


def shape_bounds(shape: Shape) -> np.ndarray:
    """(2, 3) conservative world-space box ``[min, max]`` holding the surface."""
    b = shape_part_bounds(shape.parts)
    return (b - np.asarray(shape.center)) * shape.scale


def normalized(category: str, parts: tuple[Part, ...], traits: Mapping[str, Any], half_diagonal: float = 1.0) -> Shape:
    """A :class:`Shape` whose bounding box is centred at the origin with the given half-diagonal.

    This is ShapeNet's normalisation (unit-diagonal box, here of diagonal ``2 * half_diagonal``),
    so every object fits in ``[-1, 1]^3`` and in the unit sphere.
    """
    lo, hi = shape_part_bounds(parts)
    center = 0.5 * (lo + hi)
    scale = half_diagonal / float(np.linalg.norm(0.5 * (hi - lo)))
    return Shape(category, tuple(parts), tuple(float(v) for v in center), float(scale), dict(traits))


# ---------------------------------------------------------------------------------------------
# JSON


def _tuplify(value: Any) -> Any:
    if isinstance(value, list):
        return tuple(_tuplify(v) for v in value)
    return value


def primitive_to_json(prim: Primitive) -> dict[str, Any]:
    return {"kind": prim.kind, **{f.name: _listify(getattr(prim, f.name)) for f in dataclasses.fields(prim)}}


def _listify(value: Any) -> Any:
    if isinstance(value, tuple):
        return [_listify(v) for v in value]
    return value


def primitive_from_json(doc: Mapping[str, Any]) -> Primitive:
    kind = doc.get("kind")
    if kind not in PRIMITIVES:
        raise ValueError(f"unknown primitive kind {kind!r}; expected one of {sorted(PRIMITIVES)}")
    return PRIMITIVES[kind](**{k: _tuplify(v) for k, v in doc.items() if k != "kind"})


def shape_to_json(shape: Shape) -> dict[str, Any]:
    """Plain-JSON record of ``shape`` (lists, floats, strings); inverse of :func:`shape_from_json`."""
    parts = []
    for part in shape.parts:
        parts.append(
            {
                "name": part.name,
                "primitive": primitive_to_json(part.primitive),
                "position": list(part.position),
                "rotation": list(part.rotation),
                "blend": part.blend,
                "material": {f.name: _listify(getattr(part.material, f.name)) for f in dataclasses.fields(Material)},
            }
        )
    return {
        "category": shape.category,
        "center": list(shape.center),
        "scale": shape.scale,
        "traits": dict(shape.traits),
        "parts": parts,
    }


def shape_from_json(doc: Mapping[str, Any]) -> Shape:
    """Rebuild the exact :class:`Shape` recorded by :func:`shape_to_json`."""
    parts = tuple(
        Part(
            name=p["name"],
            primitive=primitive_from_json(p["primitive"]),
            material=Material(**{k: _tuplify(v) for k, v in p["material"].items()}),
            position=tuple(p["position"]),
            rotation=tuple(p["rotation"]),
            blend=p["blend"],
        )
        for p in doc["parts"]
    )
    return Shape(doc["category"], parts, tuple(doc["center"]), doc["scale"], dict(doc.get("traits", {})))
