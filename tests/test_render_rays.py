"""Camera rays and ray/box intersection."""

import torch

from nerfmeta.render.cameras import look_at
from nerfmeta.render.rays import clip_to_aabb, image_rays, intersect_aabb

BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def test_centre_pixel_looks_along_minus_z_and_top_left_is_up_left():
    c2w = torch.eye(4)
    c2w[2, 3] = 4.0
    f = 10.0
    o, d = image_rays(c2w, torch.tensor([f, f, 1.5, 1.5]), 3, 3)
    assert d[1, 1].tolist() == [0.0, 0.0, -1.0]
    assert o[1, 1].tolist() == [0.0, 0.0, 4.0]
    expected = torch.tensor([-1.0 / f, 1.0 / f, -1.0])  # pixel (0.5, 0.5): left and up
    torch.testing.assert_close(d[0, 0], expected / expected.norm())


def test_look_at_camera_centre_ray_hits_target():
    eye = torch.tensor([3.0, -2.0, 1.5], dtype=torch.float64)
    target = torch.tensor([0.2, 0.1, -0.3], dtype=torch.float64)
    c2w = look_at(eye, target, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    o, d = image_rays(c2w, torch.tensor([20.0, 20.0, 2.5, 2.5], dtype=torch.float64), 5, 5)
    to_target = (target - eye) / (target - eye).norm()
    torch.testing.assert_close(d[2, 2], to_target)


def test_axis_aligned_rays_are_exact():
    origins = torch.tensor([[0.3, 0.2, 5.0], [2.0, 0.0, 5.0], [0.0, 0.0, 0.0], [1.0, 0.5, 5.0]])
    dirs = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    t_in, t_out, hit = intersect_aabb(origins, dirs, BOX)
    assert hit.tolist() == [True, False, True, True]
    assert (t_in[0].item(), t_out[0].item()) == (4.0, 6.0)
    assert (t_in[2].item(), t_out[2].item()) == (-1.0, 1.0)  # origin inside the box
    assert (t_in[3].item(), t_out[3].item()) == (4.0, 6.0)  # grazing the x = 1 face
    assert (t_in[1].item(), t_out[1].item()) == (0.0, 0.0)


def test_intersection_agrees_with_dense_marching():
    g = torch.Generator().manual_seed(0)
    origins = torch.randn(500, 3, generator=g) * 3
    dirs = torch.randn(500, 3, generator=g)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    t_in, t_out, hit = intersect_aabb(origins, dirs, BOX)
    ts = torch.linspace(-10, 10, 20001)
    pts = origins[:, None] + ts[None, :, None] * dirs[:, None]
    inside = ((pts >= -1) & (pts <= 1)).all(-1)
    assert (inside.any(-1) == hit).float().mean() > 0.99
    for i in torch.nonzero(hit & inside.any(-1)).flatten().tolist():
        t_inside = ts[inside[i]]
        assert abs(t_inside.min() - t_in[i]) < 2e-3 and abs(t_inside.max() - t_out[i]) < 2e-3


def test_clip_gives_zero_length_interval_for_misses():
    origins = torch.tensor([[0.0, 0.0, 5.0], [5.0, 5.0, 5.0]])
    dirs = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    near, far, hit = clip_to_aabb(origins, dirs, torch.full((2,), 2.0), torch.full((2,), 6.0), BOX)
    assert hit.tolist() == [True, False]
    assert (near[0].item(), far[0].item()) == (4.0, 6.0)
    assert near[1].item() == far[1].item() == 2.0
