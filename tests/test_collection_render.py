"""Sphere-tracing renderer: analytic sphere, shading, anti-aliasing, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nerfmeta.collection import sdf as S
from nerfmeta.collection.categories import sample_shape
from nerfmeta.collection.render import LIGHTS, RenderConfig, pixel_rays, render_shape, render_views, sphere_trace
from nerfmeta.render.cameras import look_at
from nerfmeta.render.rays import camera_rays, pixel_grid


RADIUS = 0.5
AABB = torch.tensor([[-0.6] * 3, [0.6] * 3])


def sphere_sdf(p):
    return S.sphere(p, RADIUS)


def white(p):
    return torch.ones(p.shape[0], 3, dtype=p.dtype)


def top_camera(distance: float = 4.0) -> torch.Tensor:
    eye = torch.tensor([[0.0, 0.0, distance]], dtype=torch.float64)
    return look_at(eye, torch.zeros(1, 3, dtype=torch.float64), torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64))


def test_pixel_rays_follow_the_project_camera_convention():
    pose = look_at(torch.tensor([[1.0, -3.0, 2.0]], dtype=torch.float64), torch.zeros(1, 3, dtype=torch.float64), torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))
    h, w, f = 6, 8, 7.5
    pix = pixel_grid(h, w, dtype=torch.float64).reshape(-1, 2)
    o, d = pixel_rays(pose, f, h, w, torch.zeros(len(pix), dtype=torch.long), pix[:, 0], pix[:, 1])
    o2, d2 = camera_rays(pose[0], torch.tensor([f, f, w / 2, h / 2], dtype=torch.float64), pix)
    torch.testing.assert_close(o, o2)
    torch.testing.assert_close(d, d2)


def test_sphere_trace_finds_the_analytic_hit():
    o = torch.tensor([[0.0, 0.0, 4.0], [0.3, 0.0, 4.0], [0.0, 2.0, 4.0]], dtype=torch.float64)
    d = torch.tensor([[0.0, 0.0, -1.0]] * 3, dtype=torch.float64)
    tr = sphere_trace(sphere_sdf, o, d, torch.full((3,), 3.0, dtype=torch.float64), torch.full((3,), 5.0, dtype=torch.float64), 1e-7, 200)
    t, hit, closest, last = tr.t, tr.hit, tr.closest, tr.last
    assert hit.tolist() == [True, True, False]
    torch.testing.assert_close(t[:2], torch.tensor([3.5, 4.0 - math.sqrt(RADIUS**2 - 0.09)], dtype=torch.float64), atol=1e-6, rtol=0)
    torch.testing.assert_close(last[:2], sphere_sdf(o[:2] + d[:2] * t[:2, None]))  # the field where each hit stopped
    assert bool((last[:2].abs() < 1e-6).all())
    # the miss is sampled at t = 3 and t = 3 + d(3) (the next step leaves [3, 5]); closest = min sdf / t
    d0 = math.sqrt(4.0 + 1.0) - RADIUS
    t1 = 3.0 + d0
    d1 = math.sqrt(4.0 + (4.0 - t1) ** 2) - RADIUS
    assert float(closest[2]) == pytest.approx(min(d0 / 3.0, d1 / t1), abs=1e-12)


def test_cone_free_distance_is_safe_and_useful():
    """Every ray inside the cone meets nothing before ``free``, and ``free`` gets close to the hit."""
    cone = 0.01
    o = torch.tensor([[0.0, 0.0, 4.0], [0.3, 0.1, 4.0]], dtype=torch.float64)
    d = torch.tensor([[0.0, 0.0, -1.0]] * 2, dtype=torch.float64)
    tr = sphere_trace(sphere_sdf, o, d, torch.full((2,), 3.0, dtype=torch.float64), torch.full((2,), 5.0, dtype=torch.float64), 1e-7, 200, cone)
    g = torch.Generator().manual_seed(0)
    for i in range(2):
        # random directions within the cone around ray i, sampled densely up to free[i]
        jitter = (torch.rand(200, 2, generator=g, dtype=torch.float64) * 2 - 1) * cone * 0.7
        dirs = torch.cat([jitter, -torch.ones(200, 1, dtype=torch.float64)], dim=1)
        dirs = dirs / dirs.norm(dim=-1, keepdim=True)
        ts = torch.linspace(3.0, float(tr.free[i]), 300, dtype=torch.float64)
        pts = o[i] + dirs[:, None, :] * ts[None, :, None]
        assert float(sphere_sdf(pts.reshape(-1, 3)).min()) > 0
        assert float(tr.free[i]) > 3.0 + 0.8 * (float(tr.t[i]) - 3.0) - 0.1


def test_sphere_alpha_is_its_disk_and_coverage_is_antialiased():
    res, focal = 32, 64.0
    img = render_views(sphere_sdf, white, top_camera(), focal, res, res, AABB, RenderConfig(supersample=4))[0]
    alpha = img[..., 3]
    # projected radius of a sphere seen from distance 4: f * tan(asin(r / 4))
    rp = focal * math.tan(math.asin(RADIUS / 4.0))
    ys, xs = torch.meshgrid(torch.arange(res) + 0.5, torch.arange(res) + 0.5, indexing="ij")
    r = torch.sqrt((xs - res / 2) ** 2 + (ys - res / 2) ** 2)
    assert bool((alpha[r < rp - 1.0] == 1).all())
    assert bool((alpha[r > rp + 1.0] == 0).all())
    ring = alpha[(r > rp - 0.5) & (r < rp + 0.5)]
    assert bool(((ring > 0) & (ring < 1)).any())  # partial coverage on the silhouette
    assert float(alpha.sum()) == pytest.approx(math.pi * rp * rp, rel=0.01)
    # background is transparent black
    assert bool((img[..., :3][alpha == 0] == 0).all())


def test_top_of_a_white_sphere_has_the_lambert_plus_ambient_value():
    config = RenderConfig()
    img = render_views(sphere_sdf, white, top_camera(), 64.0, 32, 32, AABB, config)[0]
    centre = img[15:17, 15:17, :3].mean(dim=(0, 1))
    # normal (0, 0, 1): sky ambient (no occlusion on a convex shape) + both lights' z components
    expected = config.ambient * 1.0 + sum(i * max(l[2], 0.0) for l, i in LIGHTS)
    torch.testing.assert_close(centre, torch.full((3,), min(expected, 1.0)), atol=0.02, rtol=0)


def test_specular_adds_a_highlight():
    base = render_views(sphere_sdf, lambda p: 0.3 * white(p), top_camera(), 64.0, 24, 24, AABB, RenderConfig())[0]
    shiny = render_views(sphere_sdf, lambda p: 0.3 * white(p), top_camera(), 64.0, 24, 24, AABB, RenderConfig(specular=0.5))[0]
    assert bool((shiny[..., :3] >= base[..., :3] - 1e-6).all())
    assert float((shiny[..., :3] - base[..., :3]).max()) > 0.1
    assert torch.equal(shiny[..., 3], base[..., 3])


def test_adaptive_supersampling_matches_full_supersampling():
    shape = sample_shape("chair", np.random.default_rng(0))  # thin legs and slats
    eyes = torch.tensor([[3.0, -2.0, 1.6], [-2.5, -2.0, 2.2]], dtype=torch.float64)
    poses = look_at(eyes, torch.zeros_like(eyes), torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64).expand_as(eyes))
    focal = 0.5 * 32 / math.tan(math.radians(15))
    adaptive = render_shape(shape, poses, focal, 32, 32, RenderConfig(adaptive=True))
    full = render_shape(shape, poses, focal, 32, 32, RenderConfig(adaptive=False))
    diff = (adaptive[..., 3] - full[..., 3]).abs()
    assert float(diff.mean()) < 2e-3
    assert float(diff.max()) <= 0.5 + 1e-6  # at most 2 of the 4 subsamples differ anywhere


def test_rendering_is_bitwise_independent_of_thread_count():
    shape = sample_shape("lamp", np.random.default_rng(1))
    eyes = torch.tensor([[3.0, -2.0, 1.6]], dtype=torch.float64)
    poses = look_at(eyes, torch.zeros_like(eyes), torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = render_shape(shape, poses, 60.0, 32, 32)
        torch.set_num_threads(2)
        two = render_shape(shape, poses, 60.0, 32, 32)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(one, two)
