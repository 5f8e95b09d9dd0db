"""Category samplers: a random generator in, a :class:`~nerfmeta.collection.shapes.Shape` out.

Every category is a parametric family: proportions, part counts and part styles are drawn from
the generator, so two chairs share a structure (seat, legs, back) without being copies, and
colours and textures are drawn per scene so appearance never identifies the category.
Samplers build in a free "shape frame" (roughly metres), canonically oriented like ShapeNet:
**z up, front facing +x**, left-right along y. :func:`sample_shape` then centres the bounding
box at the origin and scales it to a half-diagonal of 1 (the object fits in ``[-1, 1]^3``).

The registry :data:`CATEGORIES` maps each name to a :class:`Category` with a one-line description.
"""

from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from nerfmeta.collection import sdf as S
from nerfmeta.collection.shapes import (
    Box,
    CappedTorus,
    Capsule,
    Cylinder,
    Material,
    Part,
    Prism,
    Revolution,
    RoundCone,
    Shape,
    Sphere,
    Torus,
    normalized,
)

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]
DEG = math.pi / 180.0


def rx(angle: float) -> Quat:
    return S.quat_from_axis_angle((1.0, 0.0, 0.0), angle)


def ry(angle: float) -> Quat:
    return S.quat_from_axis_angle((0.0, 1.0, 0.0), angle)


def rz(angle: float) -> Quat:
    return S.quat_from_axis_angle((0.0, 0.0, 1.0), angle)


def quat_between(a: Sequence[float], b: Sequence[float]) -> Quat:
    """Shortest rotation taking direction ``a`` to direction ``b`` (not opposite)."""
    a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
    b = np.asarray(b, dtype=np.float64) / np.linalg.norm(b)
    axis = np.cross(a, b)
    s = float(np.linalg.norm(axis))
    if s < 1e-12:
        return S.IDENTITY
    return S.quat_from_axis_angle(axis, math.atan2(s, float(np.dot(a, b))))


def _v(*xs: float) -> Vec3:
    return tuple(float(x) for x in xs)  # type: ignore[return-value]


class _Builder:
    """Collects parts and traits while a sampler draws from ``rng``."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.parts: list[Part] = []
        self.traits: dict[str, Any] = {}

    # -- random draws, rounded so collection.json stays readable (the record is still exact)
    def u(self, lo: float, hi: float) -> float:
        return round(float(self.rng.uniform(lo, hi)), 4)

    def chance(self, p: float) -> bool:
        return bool(self.rng.random() < p)

    def pick(self, options: Sequence[Any], p: Sequence[float] | None = None) -> Any:
        return options[int(self.rng.choice(len(options), p=p))]

    def integer(self, lo: int, hi: int) -> int:
        """Uniform integer in ``[lo, hi]``."""
        return int(self.rng.integers(lo, hi + 1))

    def trait(self, name: str, value: Any) -> Any:
        self.traits[name] = value
        return value

    def add(
        self,
        name: str,
        primitive: Any,
        material: Material,
        position: Sequence[float] = (0.0, 0.0, 0.0),
        rotation: Quat = S.IDENTITY,
        blend: float = 0.0,
    ) -> None:
        self.parts.append(Part(name, primitive, material, _v(*position), tuple(float(q) for q in rotation), float(blend)))

    # -- colours and materials
    def hsv(self, h: float, s: float, v: float) -> Vec3:
        r, g, b = colorsys.hsv_to_rgb(h % 1.0, min(max(s, 0.0), 1.0), min(max(v, 0.0), 1.0))
        return (round(r, 4), round(g, 4), round(b, 4))

    def wood(self) -> Vec3:
        return self.hsv(self.u(0.04, 0.11), self.u(0.35, 0.75), self.u(0.28, 0.78))

    def metal(self) -> Vec3:
        return self.hsv(self.u(0.0, 1.0), self.u(0.0, 0.12), self.u(0.35, 0.85))

    def fabric(self) -> Vec3:
        return self.hsv(self.u(0.0, 1.0), self.u(0.15, 0.75), self.u(0.3, 0.9))

    def paint(self) -> Vec3:
        return self.hsv(self.u(0.0, 1.0), self.u(0.5, 0.95), self.u(0.45, 0.95))

    def pale(self) -> Vec3:
        return self.hsv(self.u(0.0, 1.0), self.u(0.0, 0.3), self.u(0.8, 0.97))

    def dark(self) -> Vec3:
        return self.hsv(self.u(0.0, 1.0), self.u(0.0, 0.3), self.u(0.06, 0.2))

    def second_color(self, color: Vec3) -> Vec3:
        """A contrasting colour: a lighter/darker shade of ``color`` or another hue."""
        h, s, v = colorsys.rgb_to_hsv(*color)
        if self.chance(0.5):
            return self.hsv(h, s, v * 0.45 if v > 0.5 else min(1.0, v + 0.4))
        return self.hsv(h + self.u(0.25, 0.75), self.u(0.3, 0.9), self.u(0.35, 0.95))

    def material(
        self,
        color: Vec3,
        p_texture: float = 0.0,
        textures: Sequence[str] = ("stripes", "checker", "noise"),
        frequency: tuple[float, float] = (4.0, 10.0),
        axis: Vec3 | None = None,
    ) -> Material:
        """``color``, with probability ``p_texture`` mixed with a second colour by a texture."""
        if not self.chance(p_texture):
            return Material(color)
        kind = self.pick(list(textures))
        if axis is None:
            axis = self.pick([(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)])
        return Material(
            color=color,
            texture=kind,
            color2=self.second_color(color),
            frequency=self.u(*frequency),
            axis=_v(*axis),
            duty=self.u(0.3, 0.7),
            phase=self.u(0.0, 1.0),
            seed=int(self.rng.integers(0, 1_000_000)),
        )

    def shape(self, category: str) -> Shape:
        return normalized(category, tuple(self.parts), self.traits)


# ---------------------------------------------------------------------------------------------
# Furniture


def _legs_at(
    b: _Builder,
    name: str,
    corners: Sequence[tuple[float, float]],
    top: float,
    thickness: float,
    style: str,
    material: Material,
    splay: float = 0.0,
    bottom: float = 0.0,
) -> list[tuple[Vec3, Vec3]]:
    """Legs from ``top`` down to ``bottom`` at (x, y) corners, splayed outwards by ``splay`` radians.

    Returns, for each leg, its top point and unit up vector (for attaching stretchers).
    """
    length = top - bottom
    out = []
    for k, (cx, cy) in enumerate(corners):
        n = math.hypot(cx, cy) or 1.0
        up = np.array([-cx / n * math.sin(splay), -cy / n * math.sin(splay), math.cos(splay)])
        top_pt = np.array([cx, cy, top])
        seg = length / math.cos(splay)
        center = top_pt - up * seg / 2
        rot = quat_between((0.0, 0.0, 1.0), up)
        if style == "square":
            prim = Box(_v(thickness / 2, thickness / 2, seg / 2), round(thickness * 0.15, 4))
        elif style == "tapered":
            prim = RoundCone(round(thickness * 0.3, 4), round(thickness / 2, 4), round(seg - thickness * 0.8, 4))
            center = top_pt - up * (seg - thickness * 0.3)
        else:
            prim = Cylinder(thickness / 2, seg / 2, round(thickness * 0.15, 4))
        b.add(f"{name}_{k}", prim, material, center, rot)
        out.append((_v(*top_pt), _v(*up)))
    return out


def chair(b: _Builder) -> Shape:
    width = b.trait("seat_width", b.u(0.42, 0.6))
    depth = b.trait("seat_depth", b.u(0.4, 0.55))
    thick = b.trait("seat_thickness", b.u(0.03, 0.08))
    height = b.trait("seat_height", b.u(0.4, 0.5))
    base = b.trait("base", b.pick(["four_legs", "pedestal", "sled"], p=[0.6, 0.25, 0.15]))
    back = b.trait("back", b.pick(["solid", "vertical_slats", "horizontal_slats"], p=[0.45, 0.35, 0.2]))
    arms = b.trait("arms", b.chance(0.3))
    back_h = b.trait("back_height", b.u(0.3, 0.6))
    tilt = b.trait("back_tilt_deg", b.u(0.0, 14.0))

    frame_color = b.pick([b.wood, b.metal, b.paint])()
    frame = b.material(frame_color, 0.15, ("stripes", "noise"), (6.0, 14.0))
    cushion = b.material(b.fabric(), 0.5, frequency=(5.0, 14.0))
    seat_round = round(min(thick / 2 - 0.002, b.u(0.005, 0.03)), 4)
    b.add("seat", Box(_v(depth / 2, width / 2, thick / 2), seat_round), cushion, (0.0, 0.0, height - thick / 2))

    bottom = height - thick
    if base == "four_legs":
        leg_t = b.trait("leg_thickness", b.u(0.025, 0.05))
        inset = b.u(0.005, 0.04)
        splay = b.trait("leg_splay_deg", b.u(0.0, 6.0)) * DEG
        style = b.trait("leg_style", b.pick(["square", "round", "tapered"]))
        cx, cy = depth / 2 - inset - leg_t / 2, width / 2 - inset - leg_t / 2
        corners = [(cx, cy), (cx, -cy), (-cx, cy), (-cx, -cy)]
        legs = _legs_at(b, "leg", corners, bottom, leg_t, style, frame, splay)
        if b.trait("stretchers", b.chance(0.35)):
            zs = b.u(0.1, 0.2)
            pts = []
            for top_pt, up in legs:
                s = (bottom - zs) / up[2]
                pts.append(_v(*(np.asarray(top_pt) - np.asarray(up) * s)))
            for k, (i, j) in enumerate([(0, 2), (1, 3)]):
                b.add(f"stretcher_{k}", Capsule(pts[i], pts[j], round(leg_t * 0.3, 4)), frame)
    elif base == "pedestal":
        col_r = b.u(0.02, 0.035)
        b.add("column", Cylinder(col_r, (bottom - 0.06) / 2), frame, (0.0, 0.0, 0.06 + (bottom - 0.06) / 2))
        n = b.trait("spokes", b.pick([4, 5]))
        reach = b.u(0.2, 0.3)
        phase = b.u(0.0, 2 * math.pi / n)
        caster = b.material(b.dark())
        for k in range(n):
            a = phase + 2 * math.pi * k / n
            tip = (reach * math.cos(a), reach * math.sin(a), 0.045)
            b.add(f"spoke_{k}", Capsule((0.0, 0.0, 0.065), tip, 0.017), frame)
            b.add(f"caster_{k}", Sphere(0.028), caster, (tip[0], tip[1], 0.028))
    else:  # sled: two side runners of bent tube
        r = b.u(0.01, 0.017)
        y = width / 2 - 0.02
        for k, s in enumerate((1.0, -1.0)):
            front_top = (depth / 2 - 0.04, s * y, bottom)
            front_low = (depth / 2 + 0.03, s * y, r)
            back_low = (-depth / 2 - 0.03, s * y, r)
            back_top = (-depth / 2 + 0.04, s * y, bottom)
            b.add(f"runner_front_{k}", Capsule(front_top, front_low, r), frame)
            b.add(f"runner_{k}", Capsule(front_low, back_low, r), frame)
            b.add(f"runner_back_{k}", Capsule(back_low, back_top, r), frame)

    # Back: built in a frame hinged at the seat's back edge and tilted backwards around y.
    back_t = b.u(0.02, 0.05)
    hinge = np.array([-depth / 2 + back_t / 2, 0.0, height])
    q = ry(-tilt * DEG)
    R = S.quat_to_matrix(q)

    def put(name: str, prim: Any, mat: Material, local: Sequence[float], local_rot: Quat = S.IDENTITY) -> None:
        b.add(name, prim, mat, hinge + R @ np.asarray(local), S.quat_mul(q, local_rot))

    span = back_h + thick  # from the seat bottom to the top of the back
    if back == "solid":
        put("back", Box(_v(back_t / 2, width / 2, span / 2), round(min(back_t / 2 - 0.001, b.u(0.005, 0.04)), 4)), cushion, (0.0, 0.0, span / 2 - thick))
    else:
        post_w = b.u(0.025, 0.045)
        rail_h = b.u(0.04, 0.09)
        for k, s in enumerate((1.0, -1.0)):
            put(f"back_post_{k}", Box(_v(back_t / 2, post_w / 2, span / 2), 0.005), frame, (0.0, s * (width / 2 - post_w / 2), span / 2 - thick))
        put("back_rail", Box(_v(back_t / 2, width / 2, rail_h / 2), 0.005), frame, (0.0, 0.0, back_h - rail_h / 2))
        if back == "vertical_slats":
            n = b.trait("slats", b.integer(2, 5))
            inner = width - 2 * post_w
            slat_w = inner / (2 * n + 1)
            length = back_h - rail_h - 0.04
            for k in range(n):
                yk = -inner / 2 + slat_w * (2 * k + 1.5)
                put(f"slat_{k}", Box(_v(back_t * 0.35, slat_w / 2, length / 2), 0.003), frame, (0.0, yk, 0.04 + length / 2))
        else:
            n = b.trait("slats", b.integer(1, 3))
            for k in range(n):
                zk = (back_h - rail_h) * (k + 1) / (n + 1)
                put(f"slat_{k}", Box(_v(back_t * 0.4, width / 2 - post_w / 2, rail_h * 0.35), 0.003), frame, (0.0, 0.0, zk))

    if arms:
        arm_h = b.u(0.18, 0.26)
        arm_w = b.u(0.03, 0.06)
        for k, s in enumerate((1.0, -1.0)):
            y = s * (width / 2 + arm_w / 2 - 0.005)
            b.add(f"armrest_{k}", Box(_v(depth * 0.42, arm_w / 2, 0.015), 0.01), frame, (-depth * 0.05, y, height + arm_h))
            b.add(f"arm_post_{k}", Cylinder(0.015, arm_h / 2), frame, (depth * 0.28, y, height + arm_h / 2))
    return b.shape("chair")


def table(b: _Builder) -> Shape:
    low = b.trait("coffee_table", b.chance(0.3))
    height = b.trait("height", b.u(0.35, 0.48) if low else b.u(0.68, 0.78))
    top = b.trait("top", b.pick(["rect", "round"], p=[0.65, 0.35]))
    thick = b.trait("top_thickness", b.u(0.025, 0.06))
    wood = b.wood()
    top_mat = b.material(wood if b.chance(0.7) else b.paint(), 0.6, ("stripes", "noise"), (5.0, 16.0), (1.0, 0.0, 0.0))
    leg_mat = b.material(wood if b.chance(0.5) else b.pick([b.metal, b.paint, b.wood])())
    z_top = height - thick / 2
    if top == "rect":
        length = b.trait("length", b.u(0.9, 1.8))
        width = b.trait("width", b.u(0.5, min(1.0, length * 0.9)))
        b.add("top", Box(_v(length / 2, width / 2, thick / 2), round(b.u(0.003, thick * 0.45), 4)), top_mat, (0.0, 0.0, z_top))
        base = b.trait("base", b.pick(["four_legs", "pedestal", "trestle"], p=[0.6, 0.15, 0.25]))
    else:
        radius = b.trait("radius", b.u(0.4, 0.65))
        b.add("top", Cylinder(radius, thick / 2, round(b.u(0.003, thick * 0.45), 4)), top_mat, (0.0, 0.0, z_top))
        length = width = 2 * radius
        base = b.trait("base", b.pick(["four_legs", "three_legs", "pedestal"], p=[0.35, 0.25, 0.4]))

    under = height - thick
    if base in ("four_legs", "three_legs"):
        leg_t = b.trait("leg_thickness", b.u(0.035, 0.08))
        style = b.trait("leg_style", b.pick(["square", "round", "tapered"]))
        splay = b.u(0.0, 5.0) * DEG if style != "square" else 0.0
        if top == "rect":
            inset = b.u(0.02, 0.1)
            cx, cy = length / 2 - inset - leg_t / 2, width / 2 - inset - leg_t / 2
            corners = [(cx, cy), (cx, -cy), (-cx, cy), (-cx, -cy)]
        else:
            n = 4 if base == "four_legs" else 3
            rr = (length / 2) * b.u(0.55, 0.8)
            corners = [(rr * math.cos(2 * math.pi * k / n + math.pi / 4), rr * math.sin(2 * math.pi * k / n + math.pi / 4)) for k in range(n)]
        _legs_at(b, "leg", corners, under, leg_t, style, leg_mat, splay)
        if top == "rect" and b.trait("apron", b.chance(0.5)):
            ah = b.u(0.05, 0.1)
            cx, cy = corners[0]
            z = under - ah / 2
            b.add("apron_0", Box(_v(cx, 0.01, ah / 2)), leg_mat, (0.0, cy, z))
            b.add("apron_1", Box(_v(cx, 0.01, ah / 2)), leg_mat, (0.0, -cy, z))
            b.add("apron_2", Box(_v(0.01, cy, ah / 2)), leg_mat, (cx, 0.0, z))
            b.add("apron_3", Box(_v(0.01, cy, ah / 2)), leg_mat, (-cx, 0.0, z))
        if top == "rect" and b.trait("shelf", b.chance(0.3)) and splay == 0.0:
            cx, cy = corners[0]
            b.add("shelf", Box(_v(cx, cy, 0.012), 0.004), top_mat, (0.0, 0.0, b.u(0.08, 0.2) * height))
    elif base == "pedestal":
        col_r = b.trait("column_radius", b.u(0.035, 0.09))
        b.add("column", Cylinder(col_r, under / 2), leg_mat, (0.0, 0.0, under / 2))
        if b.chance(0.5):
            foot_r = b.u(0.22, 0.4) * (width if top == "rect" else length)
            b.add("foot", Cylinder(foot_r, 0.02, 0.01), leg_mat, (0.0, 0.0, 0.02))
        else:
            reach = b.u(0.25, 0.4) * min(length, 1.2)
            for k in range(2):
                b.add(f"foot_{k}", Box(_v(reach, 0.03, 0.025), 0.01), leg_mat, (0.0, 0.0, 0.025), rz(math.pi / 4 + k * math.pi / 2))
    else:  # trestle: two end panels, feet and a stretcher
        panel_t = b.u(0.03, 0.06)
        panel_w = width * b.u(0.45, 0.75)
        x = length / 2 - b.u(0.08, 0.2)
        for k, s in enumerate((1.0, -1.0)):
            b.add(f"panel_{k}", Box(_v(panel_t / 2, panel_w / 2, under / 2), 0.005), leg_mat, (s * x, 0.0, under / 2))
            b.add(f"foot_{k}", Box(_v(0.04, width * 0.42, 0.025), 0.012), leg_mat, (s * x, 0.0, 0.025))
        b.add("stretcher", Box(_v(x, 0.02, 0.03), 0.008), leg_mat, (0.0, 0.0, under * b.u(0.3, 0.6)))
    return b.shape("table")


def sofa(b: _Builder) -> Shape:
    length = b.trait("length", b.u(1.4, 2.4))
    depth = b.trait("depth", b.u(0.75, 0.95))
    seat_h = b.trait("seat_height", b.u(0.38, 0.46))
    leg_h = b.trait("leg_height", b.pick([0.0, b.u(0.05, 0.14)], p=[0.3, 0.7]))
    cushion_t = b.u(0.08, 0.14)
    back_t = b.u(0.14, 0.24)
    back_above = b.trait("back_height", b.u(0.3, 0.5))
    arm_style = b.trait("arms", b.pick(["square", "rolled", "none"], p=[0.5, 0.35, 0.15]))
    arm_w = b.u(0.1, 0.22) if arm_style != "none" else 0.0
    arm_above = b.u(0.12, 0.28)
    n_cushions = b.trait("cushions", b.integer(1, 3))
    r = b.u(0.02, 0.05)

    fabric = b.fabric()
    body = b.material(fabric, 0.45, frequency=(4.0, 12.0))
    cushion = b.material(fabric if b.chance(0.6) else b.second_color(fabric), 0.35, frequency=(4.0, 12.0))
    legs = b.material(b.pick([b.wood, b.metal, b.dark])())

    base_h = seat_h - cushion_t - leg_h
    b.add("base", Box(_v(depth / 2, length / 2, base_h / 2), r), body, (0.0, 0.0, leg_h + base_h / 2))
    top_back = seat_h + back_above
    b.add("back", Box(_v(back_t / 2, length / 2, (top_back - leg_h) / 2), r * 1.5), body, (-depth / 2 + back_t / 2, 0.0, (top_back + leg_h) / 2))
    inner = length - 2 * arm_w
    c_len = inner / n_cushions
    c_depth = depth - back_t
    back_cushions = b.trait("back_cushions", b.chance(0.5))
    bc_t = b.u(0.08, 0.14)
    for k in range(n_cushions):
        y = -inner / 2 + c_len * (k + 0.5)
        b.add(f"seat_cushion_{k}", Box(_v(c_depth / 2, c_len / 2 - 0.004, cushion_t / 2), cushion_t * 0.4), cushion, (back_t / 2, y, seat_h - cushion_t / 2))
        if back_cushions:
            b.add(f"back_cushion_{k}", Box(_v(bc_t / 2, c_len / 2 - 0.004, back_above * 0.42), bc_t * 0.45), cushion, (-depth / 2 + back_t + bc_t / 2 - 0.02, y, seat_h + back_above * 0.45), ry(-8 * DEG))
    if arm_style != "none":
        arm_top = seat_h + arm_above
        for k, s in enumerate((1.0, -1.0)):
            y = s * (length / 2 - arm_w / 2)
            b.add(f"arm_{k}", Box(_v(depth / 2, arm_w / 2, (arm_top - leg_h) / 2), r * 1.5), body, (0.0, y, (arm_top + leg_h) / 2))
            if arm_style == "rolled":
                b.add(f"arm_roll_{k}", Cylinder(arm_w * 0.62, depth / 2, 0.03), body, (0.0, y, arm_top), ry(math.pi / 2))
    if b.trait("chaise", b.chance(0.2)):
        ext = depth * b.u(0.5, 0.8)
        side = b.pick([1.0, -1.0])
        cw = c_len if n_cushions > 1 else inner * 0.4
        y = side * (inner / 2 - cw / 2)
        b.add("chaise_base", Box(_v(ext / 2, cw / 2, base_h / 2), r), body, (depth / 2 + ext / 2 - 0.02, y, leg_h + base_h / 2))
        b.add("chaise_cushion", Box(_v(ext / 2, cw / 2 - 0.004, cushion_t / 2), cushion_t * 0.4), cushion, (depth / 2 + ext / 2 - 0.02, y, seat_h - cushion_t / 2))
    if leg_h > 0:
        lt = b.u(0.025, 0.05)
        cx, cy = depth / 2 - 0.06, length / 2 - 0.06
        for k, (x, y) in enumerate([(cx, cy), (cx, -cy), (-cx, cy), (-cx, -cy)]):
            b.add(f"leg_{k}", Cylinder(lt, leg_h / 2 + 0.01, 0.005), legs, (x, y, leg_h / 2 + 0.01))
    return b.shape("sofa")


# ---------------------------------------------------------------------------------------------
# Lamps and tableware


def _shade_profile(r_bottom: float, r_top: float, height: float, bulge: float) -> tuple[tuple[float, float], ...]:
    pts = []
    for k in range(7):
        t = k / 6
        r = r_bottom + (r_top - r_bottom) * t + bulge * math.sin(math.pi * t)
        pts.append((round(r, 5), round(height * t, 5)))
    return tuple(pts)


def lamp(b: _Builder) -> Shape:
    style = b.trait("style", b.pick(["table", "floor", "desk"], p=[0.45, 0.25, 0.3]))
    metal = b.material(b.pick([b.metal, b.dark, b.paint, b.wood])())
    shade = b.material(b.pick([b.pale, b.fabric, b.paint], p=[0.5, 0.3, 0.2])(), 0.45, ("stripes", "noise", "checker"), (8.0, 20.0), (0.0, 0.0, 1.0))
    bulb = Material((1.0, 0.95, 0.75))
    if style in ("table", "floor"):
        floor = style == "floor"
        base_r = b.u(0.12, 0.2) if floor else b.u(0.07, 0.14)
        base_h = b.u(0.015, 0.04)
        stem_h = b.trait("stem_height", b.u(1.1, 1.5) if floor else b.u(0.2, 0.4))
        shade_h = b.trait("shade_height", b.u(0.2, 0.32) if floor else b.u(0.15, 0.28))
        r_bot = b.trait("shade_bottom_radius", b.u(0.15, 0.26) if floor else b.u(0.12, 0.22))
        r_top = b.trait("shade_top_radius", round(r_bot * b.u(0.45, 1.0), 4))
        body = b.trait("body", b.pick(["stem", "bulb_body", "cone_body"]) if not floor else "stem")
        b.add("base", Cylinder(base_r, base_h / 2, min(base_h / 2, 0.01)), metal, (0.0, 0.0, base_h / 2))
        if body == "bulb_body":
            br = b.u(0.07, 0.13)
            b.add("body", Sphere(br), b.material(b.paint(), 0.5, frequency=(6.0, 14.0)), (0.0, 0.0, base_h + br * 0.9))
            b.add("neck", Cylinder(0.012, (stem_h - br) / 2), metal, (0.0, 0.0, base_h + br + (stem_h - br) / 2))
        elif body == "cone_body":
            b.add("body", RoundCone(b.u(0.05, 0.09), b.u(0.015, 0.03), stem_h * 0.7), b.material(b.paint(), 0.5, frequency=(6.0, 14.0)), (0.0, 0.0, base_h + 0.03))
            b.add("neck", Cylinder(0.01, stem_h * 0.2), metal, (0.0, 0.0, base_h + stem_h * 0.8))
        else:
            b.add("stem", Cylinder(b.u(0.008, 0.018), stem_h / 2), metal, (0.0, 0.0, base_h + stem_h / 2))
        z0 = base_h + stem_h - shade_h * b.u(0.1, 0.4)
        prof = _shade_profile(r_bot, r_top, shade_h, b.u(-0.02, 0.03))
        b.add("shade", Revolution(prof, 0.006), shade, (0.0, 0.0, z0))
        b.add("bulb", Sphere(min(r_top, r_bot) * 0.45), bulb, (0.0, 0.0, base_h + stem_h))
    else:  # desk lamp: base, two arm segments, a cone head aimed down and forward
        base_r = b.u(0.07, 0.12)
        b.add("base", Cylinder(base_r, 0.015, 0.008), metal, (-0.1, 0.0, 0.015))
        l1 = b.trait("arm_length", b.u(0.25, 0.4))
        l2 = b.trait("forearm_length", b.u(0.22, 0.38))
        a1 = b.trait("arm_elevation_deg", b.u(55.0, 85.0)) * DEG
        a2 = b.trait("forearm_elevation_deg", b.u(-35.0, 15.0)) * DEG
        rr = b.u(0.008, 0.014)
        p0 = np.array([-0.1, 0.0, 0.03])
        p1 = p0 + l1 * np.array([math.cos(a1), 0.0, math.sin(a1)])
        p2 = p1 + l2 * np.array([math.cos(a2), 0.0, math.sin(a2)])
        b.add("arm", Capsule(_v(*p0), _v(*p1), rr), metal)
        b.add("joint", Sphere(rr * 1.8), metal, p1)
        b.add("forearm", Capsule(_v(*p1), _v(*p2), rr), metal)
        head_h = b.u(0.1, 0.18)
        r_small, r_big = b.u(0.02, 0.04), b.u(0.07, 0.12)
        prof = ((0.0, 0.0), (r_small, 0.0), (round((r_small + r_big) / 2 * 0.9, 5), round(-head_h * 0.55, 5)), (r_big, -head_h))
        aim = b.trait("head_aim_deg", b.u(15.0, 50.0)) * DEG
        b.add("head", Revolution(prof, 0.006), shade, p2, ry(aim))
        b.add("bulb", Sphere(r_small * 1.2), bulb, p2 + S.quat_to_matrix(ry(aim)) @ np.array([0.0, 0.0, -head_h * 0.45]))
    return b.shape("lamp")


def mug(b: _Builder) -> Shape:
    radius = b.trait("radius", b.u(0.3, 0.45))
    height = b.trait("height", round(radius * b.u(1.6, 2.6), 4))
    top_r = b.trait("top_radius", round(radius * b.u(0.88, 1.22), 4))
    belly = b.trait("belly", b.u(-0.03, 0.06))
    wall = b.trait("wall", round(radius * b.u(0.05, 0.085), 4))
    prof = [(0.0, 0.0), (radius * 0.96, 0.0), (radius, height * 0.04)]
    for k in range(1, 6):
        t = k / 5
        prof.append((radius + (top_r - radius) * t + belly * math.sin(math.pi * t), height * (0.04 + 0.96 * t)))
    prof = tuple((round(r, 5), round(z, 5)) for r, z in prof)
    color = b.pick([b.pale, b.paint, b.fabric], p=[0.35, 0.4, 0.25])()
    body = b.material(color, 0.65, frequency=(5.0, 14.0), axis=(0.0, 0.0, 1.0))
    b.add("body", Revolution(prof, wall / 2), body)

    major = b.trait("handle_radius", round(height * b.u(0.22, 0.32), 4))
    minor = b.trait("handle_thickness", round(radius * b.u(0.06, 0.1), 4))
    half = b.trait("handle_angle_deg", b.u(100.0, 125.0)) * DEG
    zc = height * b.u(0.45, 0.55)
    # The handle's two ends sit on the (possibly slanted) wall: its chord runs along the wall
    # line, its inner surface just inside the wall's inner face, so nothing shows in the cup.
    zs, rs = [p[1] for p in prof], [p[0] for p in prof]
    half_chord = major * math.sin(half)
    z_lo, z_hi = zc - half_chord, min(zc + half_chord, height * 0.97)
    r_lo, r_hi = float(np.interp(z_lo, zs, rs)), float(np.interp(z_hi, zs, rs))
    up = np.array([0.0, r_hi - r_lo, z_hi - z_lo])
    up /= np.linalg.norm(up)
    out = np.array([0.0, up[2], -up[1]])  # outward normal of the wall line in the yz-plane
    offset = minor - wall / 2 + 0.1 * wall
    mid = np.array([0.0, 0.5 * (r_lo + r_hi), 0.5 * (z_lo + z_hi)]) + out * offset
    center = mid - out * (major * math.cos(half))
    frame = np.stack([up, out, np.cross(up, out)], axis=1)  # local x -> up, y -> out
    handle_mat = body if b.chance(0.6) else b.material(b.second_color(color))
    b.add("handle", CappedTorus(major, minor, half), handle_mat, center, S.quat_from_matrix(frame))
    return b.shape("mug")


def _smooth_profile(radii: Sequence[float], heights: Sequence[float], samples: int) -> list[tuple[float, float]]:
    """Catmull-Rom spline through ``(radius, height)`` control points, ``samples`` points."""
    pts = np.stack([np.asarray(radii, dtype=np.float64), np.asarray(heights, dtype=np.float64)], 1)
    ext = np.concatenate([pts[:1] * 2 - pts[1:2], pts, pts[-1:] * 2 - pts[-2:-1]])
    out = []
    n_seg = len(pts) - 1
    for k in range(samples):
        s = k / (samples - 1) * n_seg
        i = min(int(s), n_seg - 1)
        t = s - i
        p0, p1, p2, p3 = ext[i], ext[i + 1], ext[i + 2], ext[i + 3]
        q = 0.5 * (2 * p1 + (-p0 + p2) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t * t + (-p0 + 3 * p1 - 3 * p2 + p3) * t ** 3)
        out.append((max(float(q[0]), 0.04), float(q[1])))
    return out


def vase(b: _Builder) -> Shape:
    height = b.trait("height", b.u(1.0, 2.0))
    r_base = b.trait("base_radius", b.u(0.15, 0.35))
    r_belly = b.trait("belly_radius", b.u(0.28, 0.6))
    r_shoulder = b.trait("shoulder_radius", b.u(0.12, 0.5))
    r_neck = b.trait("neck_radius", b.u(0.07, min(0.22, r_shoulder)))
    r_lip = b.trait("lip_radius", round(r_neck * b.u(1.0, 1.8), 4))
    belly_at = b.trait("belly_height", b.u(0.2, 0.45))
    neck_at = b.trait("neck_height", b.u(0.7, 0.88))
    heights = [0.0, belly_at * height, (belly_at + neck_at) / 2 * height, neck_at * height, height]
    curve = _smooth_profile([r_base, r_belly, r_shoulder, r_neck, r_lip], heights, 14)
    prof = tuple((round(r, 5), round(z, 5)) for r, z in [(0.0, 0.0)] + curve)
    color = b.pick([b.paint, b.pale, b.fabric, b.dark])()
    mat = b.material(color, 0.75, frequency=(3.0, 9.0), axis=(0.0, 0.0, 1.0))
    b.add("body", Revolution(prof, b.u(0.012, 0.022)), mat)
    if b.trait("foot", b.chance(0.3)):
        b.add("foot", Cylinder(r_base * b.u(1.0, 1.3), 0.03, 0.01), mat, (0.0, 0.0, 0.03))
    if b.trait("handles", b.chance(0.25)):
        zc = (heights[2] + heights[3]) / 2
        r_at = float(np.interp(zc, [p[1] for p in prof], [p[0] for p in prof]))
        major = (heights[3] - heights[2]) * 0.45
        for k, s in enumerate((1.0, -1.0)):
            b.add(f"handle_{k}", CappedTorus(major, 0.02, 100 * DEG), mat, (0.0, s * (r_at + major * 0.3), zc), S.quat_mul(rz(0.0 if s > 0 else math.pi), ry(-math.pi / 2)))
    return b.shape("vase")


# ---------------------------------------------------------------------------------------------
# Vehicles


def car(b: _Builder) -> Shape:
    style = b.trait("style", b.pick(["sedan", "hatchback", "suv", "pickup", "sports"]))
    length = b.trait("length", b.u(1.8, 2.2))
    width = b.trait("width", round(length * b.u(0.4, 0.48), 4))
    wheel_r = b.trait("wheel_radius", round(length * (b.u(0.1, 0.125) if style in ("suv", "pickup") else b.u(0.08, 0.1)), 4))
    wheel_w = round(width * b.u(0.09, 0.12), 4)
    body_h = round(length * (b.u(0.1, 0.13) if style == "sports" else b.u(0.13, 0.18)), 4)
    body_bottom = round(wheel_r * b.u(0.45, 0.8), 4)
    wheelbase = round(length * b.u(0.56, 0.66), 4)
    cabin = {
        "sedan": (b.u(0.42, 0.52), b.u(-0.08, 0.0)),
        "hatchback": (b.u(0.5, 0.6), None),
        "suv": (b.u(0.6, 0.7), None),
        "pickup": (b.u(0.26, 0.34), b.u(0.02, 0.12)),
        "sports": (b.u(0.32, 0.42), b.u(-0.1, -0.02)),
    }[style]
    cabin_l = cabin[0] * length
    cabin_x = (-length / 2 + cabin_l / 2 + 0.04 * length) if cabin[1] is None else cabin[1] * length
    cabin_h = length * (b.u(0.08, 0.1) if style == "sports" else b.u(0.15, 0.19) if style == "suv" else b.u(0.11, 0.15))
    cabin_w = width * b.u(0.8, 0.9)

    paint = b.material(b.paint(), 0.35, ("stripes", "noise", "checker"), (2.0, 6.0), b.pick([(0.0, 1.0, 0.0), (1.0, 0.0, 0.0)]))
    glass = Material(b.hsv(b.u(0.5, 0.65), b.u(0.1, 0.4), b.u(0.08, 0.22)))
    tyre = Material(b.hsv(0.0, 0.0, b.u(0.05, 0.12)))
    hub = Material(b.metal())
    z_body = body_bottom + body_h / 2
    rb = round(body_h * b.u(0.25, 0.45), 4)
    b.add("body", Box(_v(length / 2, width / 2, body_h / 2), rb), paint, (0.0, 0.0, z_body))
    rc = round(cabin_h * b.u(0.3, 0.45), 4)
    z_cab = body_bottom + body_h + cabin_h / 2 - rc * 0.5
    # Windows: a glass band around the cabin, a one-band "stripes" texture along local z (the
    # stripe period is twice the cabin height, so only one band falls on it).
    period = 2.0 * cabin_h
    lo, hi = -0.2 * cabin_h, 0.3 * cabin_h
    duty = 1.0 - (hi - lo) / period
    cabin_mat = Material(paint.color, "stripes", glass.color, round(1.0 / period, 6), (0.0, 0.0, 1.0), round(duty, 6), round(duty - lo / period, 6))
    b.add("cabin", Box(_v(cabin_l / 2, cabin_w / 2, cabin_h / 2), rc), cabin_mat, (cabin_x, 0.0, z_cab), blend=0.04 * length)
    for k, (sx, sy) in enumerate([(1, 1), (1, -1), (-1, 1), (-1, -1)]):
        pos = (sx * wheelbase / 2, sy * (width / 2 - wheel_w * 0.45), wheel_r)
        # a torus tyre around a disc hub that shows on both faces
        b.add(f"tyre_{k}", Torus(wheel_r - wheel_w / 2, wheel_w / 2), tyre, pos, rx(math.pi / 2))
        b.add(f"hub_{k}", Cylinder(wheel_r - wheel_w / 2, wheel_w * 0.3, 0.01), hub, pos, rx(math.pi / 2))
    lamp_r = length * 0.022
    z_l = z_body + body_h * 0.15
    for k, s in enumerate((1.0, -1.0)):
        b.add(f"headlight_{k}", Sphere(lamp_r), Material((1.0, 0.95, 0.7)), (length / 2 - lamp_r * 0.6, s * width * 0.33, z_l))
        b.add(f"taillight_{k}", Sphere(lamp_r), Material((0.85, 0.05, 0.05)), (-length / 2 + lamp_r * 0.6, s * width * 0.33, z_l))
    if b.trait("spoiler", b.chance(0.6 if style == "sports" else 0.1)):
        zs = body_bottom + body_h + length * 0.06
        b.add("spoiler", Box(_v(length * 0.05, width * 0.45, 0.012), 0.008), paint, (-length / 2 + length * 0.06, 0.0, zs))
        for k, s in enumerate((1.0, -1.0)):
            b.add(f"spoiler_post_{k}", Box(_v(0.02, 0.012, length * 0.03), 0.005), paint, (-length / 2 + length * 0.06, s * width * 0.3, zs - length * 0.03))
    return b.shape("car")


def _planform(root_chord: float, tip_chord: float, span: float, sweep: float, side: float) -> tuple[tuple[float, float], ...]:
    """Trapezoid (x, y) of a half wing: root chord centred at x = 0 on y = 0, tip at y = side * span;
    ``sweep`` (radians) moves the tip's leading edge back."""
    le_tip = root_chord / 2 - span * math.tan(sweep)
    pts = ((root_chord / 2, 0.0), (le_tip, side * span), (le_tip - tip_chord, side * span), (-root_chord / 2, 0.0))
    return tuple((round(x, 5), round(y, 5)) for x, y in pts)


def airplane(b: _Builder) -> Shape:
    style = b.trait("style", b.pick(["airliner", "fighter", "propeller"], p=[0.45, 0.3, 0.25]))
    length = 2.0
    fighter = style == "fighter"
    rf = b.trait("fuselage_radius", round(length * (b.u(0.035, 0.05) if fighter else b.u(0.045, 0.07)), 4))
    span = b.trait("wingspan", round(length * (b.u(0.5, 0.7) if fighter else b.u(0.85, 1.2)), 4))
    chord = b.trait("root_chord", round(length * (b.u(0.3, 0.42) if fighter else b.u(0.1, 0.17)), 4))
    taper = b.trait("taper", b.u(0.05, 0.2) if fighter else b.u(0.55, 1.0) if style == "propeller" else b.u(0.25, 0.5))
    sweep = b.trait("sweep_deg", b.u(40.0, 60.0) if fighter else b.u(0.0, 8.0) if style == "propeller" else b.u(20.0, 35.0)) * DEG
    dihedral = b.u(0.0, 6.0) * DEG
    wing_z = b.trait("wing_height", b.pick([-0.6, 0.0, 0.7])) * rf
    wing_x = b.u(-0.12, 0.0) * length if fighter else b.u(-0.02, 0.1) * length

    body_color = b.pick([b.pale, b.metal, b.paint], p=[0.5, 0.3, 0.2])()
    body = b.material(body_color, 0.5, ("stripes", "noise"), (3.0, 10.0), (0.0, 0.0, 1.0))
    accent = b.material(b.paint(), 0.2, ("stripes", "checker"), (6.0, 12.0))
    wing_mat = body if b.chance(0.6) else b.material(b.second_color(body_color))

    nose_x, tail_x = 0.36 * length, -0.3 * length
    b.add("fuselage", Capsule((tail_x, 0.0, 0.0), (nose_x, 0.0, 0.0), rf), body)
    if fighter:
        b.add("nose", RoundCone(rf, rf * 0.1, 0.16 * length), body, (nose_x, 0.0, 0.0), ry(math.pi / 2))
        b.add("canopy", Capsule((nose_x - 0.16 * length, 0.0, rf * 0.55), (nose_x - 0.03 * length, 0.0, rf * 0.55), rf * 0.6), Material(b.hsv(0.55, 0.3, 0.15)))
    tail_up = b.u(3.0, 9.0) * DEG
    tail_len = 0.2 * length
    tail_dir = (-math.cos(tail_up), 0.0, math.sin(tail_up))
    b.add("tail_cone", RoundCone(rf, rf * b.u(0.25, 0.45), tail_len), body, (tail_x, 0.0, 0.0), quat_between((0, 0, 1), tail_dir))
    tail_end = np.array([tail_x, 0.0, 0.0]) + tail_len * np.asarray(tail_dir)

    def wing(name: str, root: Sequence[float], half_span: float, c: float, tip: float, sw: float, dh: float, mat: Material) -> None:
        t = round(max(c * 0.045, 0.008), 4)
        for k, s in enumerate((1.0, -1.0)):
            b.add(f"{name}_{k}", Prism(_planform(c, tip, half_span, sw, s), t, round(t * 0.9, 4)), mat, root, rx(s * dh))

    half_span = span / 2
    wing("wing", (wing_x, 0.0, wing_z), half_span, chord, chord * taper, sweep, dihedral, wing_mat)

    fin_h = b.trait("fin_height", round(length * b.u(0.12, 0.2), 4))
    fin_c = chord * (b.u(0.35, 0.5) if fighter else b.u(0.8, 1.2))
    fin_sweep = b.u(30.0, 50.0) * DEG
    fin_tip = fin_c * b.u(0.35, 0.6)
    t_tail = b.trait("t_tail", not fighter and b.chance(0.25))
    fin_x = tail_end[0] + fin_c * 0.45
    twin = b.trait("twin_fins", fighter and b.chance(0.5))
    fin_t = round(max(fin_c * 0.04, 0.008), 4)
    fin_poly = _planform(fin_c, fin_tip, fin_h, fin_sweep, 1.0)
    cants = [(-1.0, 15 * DEG), (1.0, 15 * DEG)] if twin else [(0.0, 0.0)]
    for k, (side, cant) in enumerate(cants):
        base = (fin_x, side * rf * 0.8, tail_end[2] * 0.6)
        b.add(f"fin_{k}", Prism(fin_poly, fin_t, round(fin_t * 0.9, 4)), accent, base, S.quat_mul(rx(-side * cant), rx(math.pi / 2)))
    if not (fighter and b.trait("tailless", b.chance(0.4))):
        if t_tail:
            le_top = fin_c / 2 - fin_h * math.tan(fin_sweep)
            root = (fin_x + le_top - fin_tip / 2 + 0.0, 0.0, tail_end[2] * 0.6 + fin_h)
            stab_c = fin_tip
        else:
            root = (fin_x, 0.0, tail_end[2] * 0.6)
            stab_c = chord * b.u(0.5, 0.75)
        wing("stabilizer", root, span * b.u(0.15, 0.2), stab_c, stab_c * b.u(0.4, 0.7), sweep + 5 * DEG, 0.0, wing_mat)

    if style == "airliner":
        n = b.trait("engines", b.pick([2, 4], p=[0.7, 0.3]))
        er = rf * b.u(0.45, 0.65)
        el = chord * b.u(0.7, 1.0)
        spots = [0.33] if n == 2 else [0.28, 0.58]
        engine = b.material(b.pick([b.metal, b.paint])())
        k = 0
        for s in (1.0, -1.0):
            for f in spots:
                y = half_span * f
                le = wing_x + chord / 2 - y * math.tan(sweep)
                z = wing_z + y * math.tan(dihedral) - er - chord * 0.04
                b.add(f"engine_{k}", Cylinder(er, el / 2, er * 0.3), engine, (le + 0.1 * el, s * y, z), ry(math.pi / 2))
                k += 1
    elif style == "propeller":
        tip = np.array([nose_x + rf, 0.0, 0.0])
        b.add("spinner", Sphere(rf * 0.55), accent, tip)
        blades = b.trait("blades", b.pick([2, 3, 4]))
        blade_l = rf * b.u(2.0, 3.0)
        spin = b.u(0.0, math.pi)
        for k in range(blades):
            q = rx(spin + 2 * math.pi * k / blades)
            center = tip + S.quat_to_matrix(q) @ np.array([0.0, 0.0, blade_l / 2])
            b.add(f"blade_{k}", Box(_v(0.008, rf * 0.22, blade_l / 2), 0.006), Material(b.hsv(0.0, 0.0, 0.15)), center, q)
    return b.shape("airplane")


# ---------------------------------------------------------------------------------------------
# Registry


@dataclass(frozen=True)
class Category:
    """A named parametric family of shapes.

    Attributes:
        name: the category name used on the command line and in ``collection.json``.
        description: one line shown by ``make-collection --list-categories``.
        sampler: draws one shape's parts from a generator.
    """

    name: str
    description: str
    sampler: Callable[[_Builder], Shape]


CATEGORIES: dict[str, Category] = {
    c.name: c
    for c in (
        Category("airplane", "fuselage, swept wings, tail fin and stabilisers; airliner (2/4 engines), fighter (delta, twin fins) or propeller", airplane),
        Category("car", "rounded body, cabin with a window band, four torus tyres with hubs, lights; sedan/hatchback/SUV/pickup/sports, optional spoiler", car),
        Category("chair", "seat, four legs / office pedestal / sled runners, solid or slatted tilted back, optional arms and stretchers", chair),
        Category("lamp", "table, floor or desk lamp: base, stem or body or jointed arm, conical/drum shade with a bulb", lamp),
        Category("mug", "cylindrical or tapered shell with a bottom and a C-shaped handle", mug),
        Category("sofa", "base, back, 1-3 seat cushions, square/rolled/no arms, optional back cushions, chaise and legs", sofa),
        Category("table", "rectangular or round top; four/three legs, pedestal or trestle base; optional apron and shelf", table),
        Category("vase", "thin shell of revolution with a random belly/shoulder/neck/lip profile, optional foot and handles", vase),
    )
}


def sample_shape(category: str, rng: np.random.Generator) -> Shape:
    """Draw one normalised shape of ``category`` (z up, front +x, bounding box half-diagonal 1)."""
    if category not in CATEGORIES:
        raise KeyError(f"unknown category {category!r}; known: {', '.join(CATEGORIES)}")
    return CATEGORIES[category].sampler(_Builder(rng))
