"""SDF primitives, smooth union and rigid transforms: exact values at hand-picked points."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nerfmeta.collection import sdf as S


def pts(*rows):
    return torch.tensor(rows, dtype=torch.float64)


def close(a, b, tol=1e-9):
    torch.testing.assert_close(a, torch.as_tensor(b, dtype=a.dtype), atol=tol, rtol=0)


def test_sphere():
    close(S.sphere(pts([2, 0, 0], [0, 0, 0], [0, 3, 4]), 1.0), [1.0, -1.0, 4.0])


def test_box_faces_corners_and_inside():
    half = (1.0, 2.0, 3.0)
    # a face centre pushed out by 1; the centre (nearest face x = 1); a corner pushed out by (1, 1, 1)
    close(S.box(pts([2, 0, 0], [0, 0, 0], [2, 3, 4], [0.5, 0, 0], [0, -2.5, 0]), half), [1.0, -1.0, math.sqrt(3), -0.5, 0.5])


def test_rounded_box_corner_is_a_circle():
    # half size 1, rounding 0.5: the edge along z is a quarter circle of radius 0.5 centred at (0.5, 0.5)
    d = S.box(pts([2, 2, 0], [1, 0, 0], [0, 0, 0]), (1.0, 1.0, 1.0), 0.5)
    close(d, [math.hypot(1.5, 1.5) - 0.5, 0.0, -1.0])


def test_cylinder():
    d = S.cylinder(pts([3, 0, 0], [0, 0, 5], [0, 0, 0], [2, 0, 3], [0, 0.5, 1.5]), 1.0, 2.0)
    close(d, [2.0, 3.0, -1.0, math.sqrt(2.0), -0.5])


def test_capsule():
    a, b = (0.0, 0.0, 0.0), (0.0, 0.0, 2.0)
    close(S.capsule(pts([1, 0, 1], [0, 0, 3], [0, 0, -1], [0, 0, 1]), a, b, 0.5), [0.5, 0.5, 0.5, -0.5])


def test_torus():
    close(S.torus(pts([2, 0, 0], [0, 0, 0], [2, 0, 1], [0, 3, 0]), 2.0, 0.5), [-0.5, 1.5, 0.5, 0.5])


def test_capped_torus_half_ring():
    # the upper half (y >= 0) of a unit circle, tube radius 0.1: ends at (+-1, 0, 0)
    d = S.capped_torus(pts([0, 1, 0], [0, -1, 0], [0, 0, 0], [1, 0, 0], [0, 0, 1]), 1.0, 0.1, math.pi / 2)
    close(d, [-0.1, math.sqrt(2.0) - 0.1, 0.9, -0.1, math.sqrt(2.0) - 0.1])


def test_round_cone():
    # spheres of radius 1 at the origin and 0.5 at z = 2
    d = S.round_cone(pts([0, 0, -2], [0, 0, 3], [0, 0, 0], [0, 0, 2]), 1.0, 0.5, 2.0)
    close(d, [1.0, 0.5, -1.0, -0.5])


def test_revolution_tube_and_bottom():
    wall = ((1.0, 0.0), (1.0, 2.0))
    close(S.revolution(pts([0, 0, 1], [1, 0, 1], [0, 1, 3], [2, 0, 1]), wall, 0.1), [0.9, -0.1, 0.9, 0.9])
    cup = ((0.0, 0.0), (1.0, 0.0), (1.0, 2.0))
    close(S.revolution(pts([0, 0, 1], [0.5, 0, -0.5], [0, 0.5, 0]), cup, 0.1), [0.9, 0.4, -0.1])


def test_prism_triangle_and_square_equals_box():
    tri = ((0.0, 0.0), (2.0, 0.0), (0.0, 2.0))
    d = S.prism(pts([0.5, 0.5, 0], [2, 2, 0], [0.5, 0.5, 3], [-1, 0, 0]), tri, 1.0)
    close(d, [-0.5, math.sqrt(2.0), 2.0, 1.0])
    g = torch.Generator().manual_seed(0)
    p = torch.randn(2000, 3, generator=g, dtype=torch.float64)
    square = ((-0.5, -0.3), (0.5, -0.3), (0.5, 0.3), (-0.5, 0.3))
    close(S.prism(p, square, 0.2), S.box(p, (0.5, 0.3, 0.2)), 1e-12)
    close(S.prism(p, square[::-1], 0.2), S.box(p, (0.5, 0.3, 0.2)), 1e-12)  # orientation does not matter


def test_prism_refuses_non_convex_polygons():
    ell = ((0.0, 0.0), (2.0, 0.0), (2.0, 1.0), (1.0, 1.0), (1.0, 2.0), (0.0, 2.0))
    assert not S.is_convex(ell)
    assert S.is_convex(((0.0, 0.0), (2.0, 0.0), (0.0, 2.0))) and S.is_convex(((0.0, 0.0), (0.0, 2.0), (2.0, 0.0)))
    from nerfmeta.collection.shapes import Prism

    with pytest.raises(ValueError, match="convex"):
        Prism(ell, 0.1)


def test_smooth_union():
    a = torch.tensor([0.3, 1.0, -0.2], dtype=torch.float64)
    b = torch.tensor([0.3, 2.0, 0.5], dtype=torch.float64)
    close(S.smooth_union(a, b, 0.0), torch.minimum(a, b))
    # equal distances dip by k / 4; distances k or more apart give the plain minimum
    close(S.smooth_union(a, b, 0.4), [0.3 - 0.1, 1.0, -0.2])


@pytest.mark.parametrize(
    "fn",
    [
        lambda p: S.box(p, (0.5, 0.3, 0.2), 0.05),
        lambda p: S.cylinder(p, 0.4, 0.3, 0.05),
        lambda p: S.capsule(p, (0.1, 0.0, -0.3), (-0.2, 0.3, 0.4), 0.2),
        lambda p: S.torus(p, 0.5, 0.1),
        lambda p: S.capped_torus(p, 0.5, 0.1, 2.0),
        lambda p: S.round_cone(p, 0.3, 0.1, 0.6),
        lambda p: S.revolution(p, ((0.0, 0.0), (0.4, 0.0), (0.5, 0.5), (0.3, 0.8)), 0.02),
        lambda p: S.prism(p, ((0.0, 0.0), (0.6, 0.1), (0.2, 0.5)), 0.05),
    ],
)
def test_primitives_are_distance_fields(fn):
    """|grad sdf| = 1 almost everywhere (an exact Euclidean distance), checked with autograd."""
    g = torch.Generator().manual_seed(1)
    p = (torch.rand(500, 3, generator=g, dtype=torch.float64) * 2 - 1).requires_grad_(True)
    d = fn(p)
    (grad,) = torch.autograd.grad(d.sum(), p)
    norm = grad.norm(dim=-1)
    assert ((norm - 1).abs() < 1e-6).float().mean() > 0.97


def test_quaternions_compose_like_matrices():
    q = S.quat_from_axis_angle((1.0, 2.0, 3.0), 0.7)
    r = S.quat_from_axis_angle((0.0, 1.0, -1.0), -1.3)
    np.testing.assert_allclose(S.quat_to_matrix(S.quat_mul(q, r)), S.quat_to_matrix(q) @ S.quat_to_matrix(r), atol=1e-12)
    np.testing.assert_allclose(S.quat_to_matrix(S.quat_from_matrix(S.quat_to_matrix(q))), S.quat_to_matrix(q), atol=1e-12)
    np.testing.assert_allclose(S.quat_to_matrix(S.quat_from_axis_angle((0, 0, 1), math.pi / 2)), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)


def test_to_local_inverts_the_placement():
    q = S.quat_from_axis_angle((0.0, 0.0, 1.0), math.pi / 2)  # local x -> world y
    local = S.to_local(pts([1, 3, 3], [1, 2, 3]), (1.0, 2.0, 3.0), q)
    close(local, [[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]], 1e-12)
