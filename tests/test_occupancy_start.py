"""The learned occupancy start (nerfmeta.priors.occupancy): its multi-view features, its network, and the start."""

from __future__ import annotations

import math

import pytest
import torch

import nerfmeta.priors.occupancy as occupancy
from nerfmeta.errors import ConfigError
from nerfmeta.fields.grid_ops import grid_points
from nerfmeta.io import save_tensors
from nerfmeta.priors.carve import visual_hull
from nerfmeta.priors.start import EMPTY_ALPHA, HULL_ALPHA, sigma_for_alpha
from test_carve import composite, grid_model, sphere_views, tiny_scene


def test_point_features_of_a_point_two_views_see_in_two_colours() -> None:
    # Two identical cameras at z = 4 looking down -z (OpenGL), 8 x 8 pixels, f = 10: the origin projects to pixel
    # (4, 4), which view 0 shows red on foreground and view 1 blue on background; (10, 0, 0) falls outside both.
    poses = torch.eye(4).repeat(2, 1, 1)
    poses[:, 2, 3] = 4.0
    intrinsics = torch.tensor([[10.0, 10.0, 4.0, 4.0]] * 2)
    masks = torch.zeros(2, 8, 8, dtype=torch.bool)
    masks[0, 4, 4] = True
    masks[1, 0, 0] = True  # elsewhere: a pixel away from (4, 4) stays background when dilated
    images = torch.zeros(2, 8, 8, 3)
    images[0, 4, 4] = torch.tensor([1.0, 0.0, 0.0])
    images[1, 4, 4] = torch.tensor([0.0, 0.0, 1.0])
    feats = occupancy.point_features(torch.tensor([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]]), masks, images, poses, intrinsics)
    assert feats.shape == (occupancy.N_FEATURES, 2)
    origin, outside = feats[:, 0], feats[:, 1]
    # seen by 2 of 2; on foreground in 1 of 2 (dilated too); one view shows background; red only (the foreground view)
    torch.testing.assert_close(origin, torch.tensor([1.0, 0.5, 0.5, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.5]))
    masks[1, 4, 4] = True  # both views on foreground: the mean of red and blue, spread sqrt((1/4 + 0 + 1/4) / 3)
    origin = occupancy.point_features(torch.zeros(1, 3), masks, images, poses, intrinsics)[:, 0]
    torch.testing.assert_close(origin[5:9], torch.tensor([0.5, 0.0, 0.5, math.sqrt(1 / 6)]))
    torch.testing.assert_close(origin[[0, 1, 2, 3, 4, 9]], torch.ones(6))
    # seen by no view: no view shows it on background either (the two flags), every other feature zero
    torch.testing.assert_close(outside, torch.tensor([0.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0]))


def test_occupancy_net_keeps_the_grid_shape_and_reloads_its_width() -> None:
    net = occupancy.OccupancyNet(width=4)
    x = torch.rand(occupancy.N_FEATURES, 5, 6, 7)
    assert net(x).shape == (5, 6, 7)
    again = occupancy.OccupancyNet.from_state(net.state_dict())
    assert torch.equal(again(x), net(x)) and not again.training


def constant_net(logit: float) -> occupancy.OccupancyNet:
    """A network that gives every point the same occupancy logit."""
    net = occupancy.OccupancyNet(width=2)
    with torch.no_grad():
        for p in net.parameters():
            p.zero_()
        net.net[-1].bias.fill_(logit)
    return net.eval()


def sphere_scene():
    poses, k, alphas = sphere_views()
    return tiny_scene(composite(alphas, torch.tensor([0.8, 0.2, 0.1]), torch.ones(3)), alphas, poses, k)


def test_the_start_fills_what_the_network_says_within_the_hull_it_may_keep() -> None:
    scene = sphere_scene()
    model = grid_model()
    report = occupancy.learned_grid_start(model, scene, torch.ones(3), constant_net(10.0))  # "everything is occupied"
    assert report.applied and report.kind == "occupancy"
    pts = grid_points(model.bounds, model.size).reshape(-1, 3)
    sigma = model.get_density(pts)[0].detach()
    step = model.config.stepsize * model.voxel
    full = torch.isclose(sigma, torch.tensor(sigma_for_alpha(HULL_ALPHA, step)), rtol=1e-3)
    # ... but only inside the allowed region (the 2-pixel hull grown a voxel), which leaves the box's corners empty
    _, allowed = occupancy.occupancy_inputs(occupancy.grid_views(model, scene), model.size)
    assert torch.equal(full, allowed.reshape(-1)) and not bool(allowed.all())
    assert math.isclose(report.figures["occupied_fraction"], float(allowed.float().mean()), abs_tol=1e-4)
    inside, _ = visual_hull(pts, scene.subset("train").alphas > 0.5, scene.subset("train").poses, scene.subset("train").intrinsics)
    assert bool(allowed.reshape(-1)[inside].all())  # the exact hull is always allowed
    centre = torch.linalg.vector_norm(pts, dim=-1).argmin()
    assert torch.allclose(torch.sigmoid(model.color_coarse.reshape(3, -1)[:, centre]), torch.tensor([0.8, 0.2, 0.1]), atol=1e-4)


def test_a_network_that_sees_nothing_leaves_the_grid_empty() -> None:
    model = grid_model()
    report = occupancy.learned_grid_start(model, sphere_scene(), torch.ones(3), constant_net(-10.0))
    assert report.applied and report.figures["occupied_fraction"] == 0.0
    sigma = model.get_density(grid_points(model.bounds, model.size).reshape(-1, 3))[0].detach()
    step = model.config.stepsize * model.voxel
    assert torch.allclose(sigma, torch.full_like(sigma, sigma_for_alpha(EMPTY_ALPHA, step)), rtol=1e-2)


def test_a_busy_scene_gets_no_start_and_says_why() -> None:
    poses, k, alphas = sphere_views()
    scene = tiny_scene(torch.rand(*alphas.shape, 3, generator=torch.Generator().manual_seed(1)), None, poses, k)
    model = grid_model()
    before = {n: p.detach().clone() for n, p in model.named_parameters()}
    report = occupancy.learned_grid_start(model, scene, torch.ones(3), constant_net(10.0))
    assert not report.applied and report.reason.startswith("no learned start:") and "not a uniform background" in report.reason
    assert all(torch.equal(before[n], p) for n, p in model.named_parameters())


def test_a_saved_network_reloads_and_a_bad_file_is_one_line_naming_it(tmp_path) -> None:
    net = occupancy.OccupancyNet(width=3)
    save_tensors(tmp_path / "net.safetensors", net.state_dict())
    x = torch.rand(occupancy.N_FEATURES, 4, 4, 4)
    assert torch.equal(occupancy.load_occupancy_net(tmp_path / "net.safetensors")(x), net(x))
    (tmp_path / "garbage.safetensors").write_text("not tensors")
    save_tensors(tmp_path / "other.safetensors", {"weight": torch.zeros(2)})
    for name, why in (("absent.safetensors", "no such occupancy network file"),
                      ("garbage.safetensors", "not readable as safetensors"),
                      ("other.safetensors", "not an occupancy network")):
        with pytest.raises(ConfigError) as err:
            occupancy.load_occupancy_net(tmp_path / name)
        assert str(err.value).startswith(f"{tmp_path / name}: {why}") and "\n" not in str(err.value)


def test_a_box_much_larger_than_the_object_is_tightened_to_what_the_silhouettes_allow() -> None:
    import dataclasses

    from nerfmeta.fields.registry import build_model
    from nerfmeta.fields.voxel_grid import VoxelGridConfig
    from test_carve import RADIUS

    config = VoxelGridConfig(num_voxels=16**3, coarse_num_voxels=12**3)
    built = []

    def build(bounds):
        built.append(bounds.clone())
        return build_model("grid", config, bounds, seed=0)

    big = dataclasses.replace(sphere_scene(), bounds=torch.tensor([[-1.8] * 3, [1.8] * 3]))  # 3x the sphere's box
    model, report = occupancy.learned_start(build, big, torch.ones(3), constant_net(10.0))
    box = model.bounds
    assert len(built) == 2 and report.figures["box_from_silhouettes"] and report.applied
    assert bool((box[0] > -1.8).all() and (box[1] < 1.8).all())  # inside the scene's box ...
    assert bool((box[0] <= -RADIUS).all() and (box[1] >= RADIUS).all())  # ... holding the sphere
    assert report.figures["box"] == [[round(float(v), 4) for v in row] for row in box.tolist()]
    assert model.voxel < 0.6 * build(big.bounds).voxel  # the same voxel count on the object: smaller voxels
    # a box the silhouettes reach on every face is kept: one build, the scene's own box
    built.clear()
    fitted = dataclasses.replace(big, bounds=torch.tensor([[-0.6] * 3, [0.6] * 3]))
    model, report = occupancy.learned_start(build, fitted, torch.ones(3), constant_net(10.0))
    assert len(built) == 1 and torch.equal(model.bounds, fitted.bounds) and not report.figures["box_from_silhouettes"]
    # a start that does not apply in the tightened box: the grid goes back to the scene's box
    built.clear()
    refused = occupancy.StartReport(False, "test", "not here", 0.0, {})
    model, report = occupancy.boxed_start(build, big, occupancy.hull_inputs, lambda m, inputs: refused)
    assert len(built) == 3 and torch.equal(model.bounds, big.bounds) and not report.figures["box_from_silhouettes"]
    # views that cannot be carved: the scene's box, no start, the reason
    poses, k, alphas = sphere_views()
    busy = tiny_scene(torch.rand(*alphas.shape, 3, generator=torch.Generator().manual_seed(1)), None, poses, k)
    built.clear()
    model, report = occupancy.learned_start(build, busy, torch.ones(3), constant_net(10.0))
    assert len(built) == 1 and not report.applied and "not a uniform background" in report.reason
