"""A dense RGB-sigma voxel grid: the example backbone of docs/new_field.md (one file plus a registry line)."""

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from nerfmeta.fields.base import Layer, ParamGroup, RadianceModel, SamplingPlan
from nerfmeta.fields.grid_ops import interp_gather
from nerfmeta.render.estimators import OccupancyGrid


@dataclass(frozen=True)
class DenseGridConfig:
    """Settings of :class:`DenseGrid`."""

    side: int = 32
    """Grid corners per axis."""
    lr: float = 0.1
    """Adam learning rate of the grid."""


class DenseGrid(RadianceModel):
    """Density ``softplus(v0 - 4)`` per voxel and colour ``sigmoid(v1..v3)``, trilinear from one (4, S, S, S) grid."""

    backbone = "dense"

    def __init__(self, config: DenseGridConfig, bounds: torch.Tensor):
        super().__init__()
        self.config = config
        self.grid = nn.Parameter(torch.zeros(4, config.side, config.side, config.side, device=bounds.device))
        self.occupancy = OccupancyGrid(bounds)  # the shared estimator; its (1, 1, 1) grid skips nothing
        self.voxel = float((bounds[1] - bounds[0]).max()) / (config.side - 1)

    def sample(self, rays, *, train, generator):
        n = len(rays)
        jitter = torch.rand(n, generator=generator) if train else torch.full((n,), 0.5)
        return SamplingPlan(self.occupancy.sampling(rays.origins, rays.directions, rays.near, rays.far,
                                                    step=0.5 * self.voxel, jitter=jitter.to(rays.origins)))

    def get_density(self, points):
        values = interp_gather(self.grid, points, self.occupancy.aabb)  # (N, 4)
        return F.softplus(values[:, 0] - 4.0) / self.voxel, values

    def get_outputs(self, embedding, sel, directions, ray_idx):
        values = embedding if sel is None else embedding[sel]
        return torch.sigmoid(values[:, 1:])

    def layers(self):
        return [Layer("grid", ("grid",))]

    def param_groups(self):
        return [ParamGroup("grid", ("grid",), self.config.lr)]
