"""scripts/probe_occupancy_start.py: the multi-view features its learned start reads, on a case worked by hand."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import pytest
import torch

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "probe_occupancy_start.py"


@pytest.fixture(scope="module")
def probe():
    spec = importlib.util.spec_from_file_location("probe_occupancy_start", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_point_features_of_a_point_two_views_see_in_two_colours(probe) -> None:
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
    feats = probe.point_features(torch.tensor([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]]), masks, images, poses, intrinsics)
    assert feats.shape == (probe.N_FEATURES, 2)
    origin, outside = feats[:, 0], feats[:, 1]
    # seen by 2 of 2; on foreground in 1 of 2 (dilated too); one view shows background; red only (the foreground view)
    torch.testing.assert_close(origin, torch.tensor([1.0, 0.5, 0.5, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.5]))
    masks[1, 4, 4] = True  # both views on foreground: the mean of red and blue, spread sqrt((1/4 + 0 + 1/4) / 3)
    origin = probe.point_features(torch.zeros(1, 3), masks, images, poses, intrinsics)[:, 0]
    torch.testing.assert_close(origin[5:9], torch.tensor([0.5, 0.0, 0.5, math.sqrt(1 / 6)]))
    torch.testing.assert_close(origin[[0, 1, 2, 3, 4, 9]], torch.ones(6))
    # seen by no view: no view shows it on background either (the two flags), every other feature zero
    torch.testing.assert_close(outside, torch.tensor([0.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0]))


def test_occupancy_net_keeps_the_grid_shape(probe) -> None:
    net = probe.OccupancyNet(width=4)
    assert net(torch.rand(probe.N_FEATURES, 5, 6, 7)).shape == (5, 6, 7)
