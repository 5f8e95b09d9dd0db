"""Shapes, category samplers and their JSON record."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from nerfmeta.collection.categories import CATEGORIES, sample_shape
from nerfmeta.collection.shapes import (
    Box,
    Material,
    Part,
    Shape,
    Sphere,
    material_albedo,
    normalized,
    shape_albedo,
    shape_bounds,
    shape_from_json,
    shape_sdf,
    shape_to_json,
    value_noise,
)


SEEDS = (0, 1, 2)


def random_points(n: int, scale: float = 1.2, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1) * scale


def test_registry_has_eight_distinct_categories_with_descriptions():
    assert len(CATEGORIES) >= 8
    for name, cat in CATEGORIES.items():
        assert cat.name == name and cat.description and "\n" not in cat.description


def test_two_part_shape_by_hand():
    # a unit sphere at the origin and a box around (3, 0, 0), hard union, unit scale
    red, blue = Material((1.0, 0.0, 0.0)), Material((0.0, 0.0, 1.0))
    shape = Shape("test", (Part("ball", Sphere(1.0), red), Part("block", Box((0.5, 0.5, 0.5)), blue, (3.0, 0.0, 0.0))))
    p = torch.tensor([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [3.0, 0.0, 0.0], [1.5, 0.0, 0.0]], dtype=torch.float64)
    torch.testing.assert_close(shape_sdf(shape, p), torch.tensor([-1.0, 0.5, -0.5, 0.5], dtype=torch.float64))
    colours = shape_albedo(shape, torch.tensor([[1.0, 0.0, 0.0], [2.5, 0.0, 0.0]], dtype=torch.float64))
    torch.testing.assert_close(colours, torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64))


def test_normalization_fits_unit_sphere_and_keeps_distances_scaled():
    part = Part("block", Box((2.0, 1.0, 0.5)), Material((0.5, 0.5, 0.5)), (10.0, 0.0, 0.0))
    shape = normalized("test", (part,), {})
    np.testing.assert_allclose(shape_bounds(shape), [[-2 / 2.29128784747792, -1 / 2.29128784747792, -0.5 / 2.29128784747792], [2 / 2.29128784747792, 1 / 2.29128784747792, 0.5 / 2.29128784747792]])
    # the world distance is the shape-frame distance times the scale
    d = shape_sdf(shape, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))
    torch.testing.assert_close(d, torch.tensor([1.0 - 0.5 / 2.29128784747792], dtype=torch.float64))


@pytest.mark.parametrize("category", sorted(CATEGORIES))
def test_samplers_are_seeded_and_vary(category):
    a = sample_shape(category, np.random.default_rng(0))
    b = sample_shape(category, np.random.default_rng(0))
    c = sample_shape(category, np.random.default_rng(1))
    assert a == b
    assert shape_to_json(a) != shape_to_json(c)
    assert a.category == category


@pytest.mark.parametrize("category", sorted(CATEGORIES))
def test_json_round_trip_is_exact(category):
    for seed in SEEDS:
        shape = sample_shape(category, np.random.default_rng(seed))
        doc = json.loads(json.dumps(shape_to_json(shape)))
        rebuilt = shape_from_json(doc)
        assert rebuilt == shape
        p = random_points(4000, seed=seed)
        assert torch.equal(shape_sdf(rebuilt, p), shape_sdf(shape, p))
        assert torch.equal(shape_albedo(rebuilt, p[:500]), shape_albedo(shape, p[:500]))


@pytest.mark.parametrize("category", sorted(CATEGORIES))
def test_shapes_are_canonical_and_signed(category):
    for seed in SEEDS:
        shape = sample_shape(category, np.random.default_rng(seed))
        lo, hi = shape_bounds(shape)
        np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-9)
        assert np.linalg.norm((hi - lo) / 2) == pytest.approx(1.0, abs=1e-3)  # ShapeNet-style: half-diagonal 1
        # outside the unit sphere everything is at least |p| - 1 away
        p = random_points(4000, scale=3.0, seed=seed)
        r = p.norm(dim=-1)
        far = r > 1.01
        d = shape_sdf(shape, p)
        assert bool((d[far] >= r[far] - 1.0 - 1e-9).all())
        # the first part's local origin is inside the solid (every sampler starts with a solid part
        # centred there: seat, body, top, base, fuselage, or the bottom of a shell)
        first = shape.parts[0]
        inside = (torch.tensor(first.position, dtype=torch.float64) - torch.tensor(shape.center, dtype=torch.float64)) * shape.scale
        assert float(shape_sdf(shape, inside[None])) < 0
        # some of the box is inside, most is outside
        grid = random_points(4000, scale=1.0, seed=seed + 10)
        dg = shape_sdf(shape, grid)
        assert 0 < int((dg < 0).sum()) < 4000


@pytest.mark.parametrize("category", sorted(CATEGORIES))
def test_shape_sdf_is_one_lipschitz(category):
    """Sphere tracing relies on |sdf(p) - sdf(q)| <= |p - q| (smooth unions included)."""
    shape = sample_shape(category, np.random.default_rng(3))
    p = random_points(3000, seed=4)
    q = p + random_points(3000, scale=0.05, seed=5)
    gap = (shape_sdf(shape, p) - shape_sdf(shape, q)).abs()
    assert bool((gap <= (p - q).norm(dim=-1) + 1e-9).all())


def test_textures_mix_two_colours_within_range():
    local = random_points(3000, scale=2.0)
    for texture in ("stripes", "checker", "noise"):
        m = Material((0.9, 0.1, 0.1), texture, (0.1, 0.2, 0.9), frequency=3.0, axis=(0.0, 0.0, 1.0), duty=0.5, phase=0.25, seed=7)
        rgb = material_albedo(m, local)
        assert bool(((rgb >= 0) & (rgb <= 1)).all())
        # both colours appear
        assert float(rgb[:, 0].max()) == pytest.approx(0.9) and float(rgb[:, 0].min()) == pytest.approx(0.1)
    stripes = Material((1.0, 1.0, 1.0), "stripes", (0.0, 0.0, 0.0), frequency=1.0, axis=(0.0, 0.0, 1.0), duty=0.5, phase=0.0)
    z = torch.tensor([[0.0, 0.0, 0.25], [0.0, 0.0, 0.75], [5.0, -3.0, 1.25]], dtype=torch.float64)
    torch.testing.assert_close(material_albedo(stripes, z)[:, 0], torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64))


def test_value_noise_range_and_lattice_values():
    p = random_points(5000, scale=10.0)
    n = value_noise(p, seed=3)
    assert float(n.min()) >= 0.0 and float(n.max()) <= 1.0
    assert torch.equal(n, value_noise(p, seed=3))
    assert not torch.equal(n, value_noise(p, seed=4))
