"""A DirectVoxGO-style voxel-grid backbone in pure PyTorch (CPU and CUDA).

Two stages, as in DirectVoxGO (Sun et al., CVPR 2022):

1. **Coarse**: a density grid and a direct RGB grid over the scene box, trained for
   ``coarse_iters`` steps. It finds the occupied region: the fine box is the bounding box of
   voxels whose alpha exceeds ``bbox_thres``, and the fine stage's occupancy (mask) cache starts
   as the dilated set of voxels whose coarse alpha exceeds ``mask_cache_thres``.
2. **Fine**: a higher-resolution density grid and a feature grid in the tightened box, the
   features decoded with the view direction by a shallow MLP. Samples whose occupancy bit is
   off are skipped (never evaluated); colour is only decoded where a sample's compositing
   weight exceeds ``fast_color_thres``. The occupancy cache is pruned from the fine density
   every ``occupancy_every`` steps, and the grids grow progressively (voxel count doubling at
   ``growth_steps``, starting from ``num_voxels / 2**len(growth_steps)``).

Density is *post-activated*: the raw grid is interpolated first and only then passed through
``softplus(raw + shift)``, which lets a trilinear grid represent sharp surfaces inside a voxel.
``shift`` is chosen so that raw 0 gives alpha ``alpha_init`` over one step (the shifted
softplus of DirectVoxGO). Densities are in units of 1/``unit`` where ``unit`` is the voxel side
of the fully grown grid of the current stage (``tau = sigma * delta / unit``), so growing the grid
does not change what a raw value means.

Colour in the fine stage is ``sigmoid(diffuse + mlp(features, view))`` (DirectVoxGO's
non-direct colour head): the feature grid holds 3 diffuse logits plus ``feature_dim`` channels for
the MLP, whose last layer starts at zero. The fine stage is initialised from the coarse one
(density converted through world units, diffuse logits copied), so switching stages does not
throw away what the coarse stage learned.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from nerfmeta.data.scene import RayBatch
from nerfmeta.fields.base import Layer, ParamGroup, RadianceModel, RenderOutput, StepEvent
from nerfmeta.fields.encoding import encoding_dim, positional_encoding
from nerfmeta.fields.grid_ops import (
    grid_points,
    interp_cf,
    interp_cl,
    nearest_lookup,
    resample_cf,
    total_variation,
    voxel_layout,
)
from nerfmeta.render.rays import clip_to_aabb
from nerfmeta.render.sampling import fixed_step_samples
from nerfmeta.render.volume import render_weights, softplus_shift_for_alpha


@dataclass(frozen=True)
class VoxelGridConfig:
    """Voxel-grid backbone settings (defaults tuned for ~100x100 views on a 2-core CPU)."""

    coarse_iters: int = 300
    """Steps of the coarse stage before the fine stage starts (0 skips the coarse stage: the fine stage uses the scene box and no mask)."""
    coarse_num_voxels: int = 48**3
    """Voxels in the coarse grids."""
    coarse_alpha_init: float = 1e-4
    """Alpha of one coarse step at raw density 0."""
    num_voxels: int = 88**3
    """Voxels in the fine grids once fully grown."""
    alpha_init: float = 1e-2
    """Alpha of one fine step at raw density 0."""
    feature_dim: int = 6
    """Channels of the fine feature grid fed to the MLP (3 diffuse-colour channels come on top)."""
    mlp_width: int = 64
    """Width of the colour MLP."""
    mlp_depth: int = 3
    """Linear layers in the colour MLP."""
    view_dependent: bool = True
    """Decode view-dependent colour with the MLP; False keeps the diffuse colour alone (no MLP)."""
    dir_freqs: int = 4
    """Frequencies of the view-direction encoding."""
    stepsize: float = 0.5
    """Distance between samples along a ray, in voxels."""
    bbox_thres: float = 1e-3
    """Coarse alpha above which a voxel counts as occupied when tightening the fine box."""
    mask_cache_thres: float = 1e-3
    """Alpha above which a voxel stays in the occupancy cache."""
    fast_color_thres: float = 1e-4
    """Samples with a smaller compositing weight are not colour-decoded."""
    empty_space_skipping: bool = True
    """Skip samples in voxels the occupancy cache marks empty (switch off to compare)."""
    occupancy_every: int = 100
    """Fine steps between occupancy-cache pruning (0: never prune)."""
    growth_steps: tuple[int, ...] = (100, 200, 300)
    """Fine-stage steps at which the grids double their voxel count."""
    world_bound_scale: float = 1.05
    """Scale of the tightened fine box about its centre."""
    lr_density: float = 0.1
    """Learning rate of the density grids."""
    lr_features: float = 0.1
    """Learning rate of the colour/feature grids."""
    lr_mlp: float = 1e-3
    """Learning rate of the colour MLP."""
    tv_weight: float = 0.0
    """Weight of a total-variation loss on the fine density grid (0: off)."""


class ColorMLP(nn.Module):
    """Shallow MLP mapping grid features (+ encoded view direction) to RGB logits; last layer zero."""

    def __init__(self, in_dim: int, width: int, depth: int):
        super().__init__()
        dims = [in_dim] + [width] * (depth - 1) + [3]
        self.linears = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))
        nn.init.zeros_(self.linears[-1].weight)
        nn.init.zeros_(self.linears[-1].bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for i, lin in enumerate(self.linears):
            x = lin(x)
            if i < len(self.linears) - 1:
                x = F.relu(x)
        return x


def softplus_inverse(y: torch.Tensor) -> torch.Tensor:
    """``x`` with ``softplus(x) == y`` for ``y > 0`` (clamped at 1e-12), computed stably."""
    y = y.clamp(min=1e-12)
    return y + torch.log(-torch.expm1(-y))


class VoxelGrid(RadianceModel):
    """DirectVoxGO-style backbone; see the module docstring.

    Layers, input to output: coarse stage ``density_coarse``, ``color_coarse``; fine stage
    ``density``, ``features``, ``mlp.0`` ... ``mlp.{depth-1}`` (no MLP layers when
    ``view_dependent`` is False). ``freeze_first(1)`` freezes the density grid (geometry),
    ``freeze_first(2)`` also the feature grid, leaving only the decoder to adapt.
    """

    backbone = "grid"

    def __init__(self, config: VoxelGridConfig, bounds: torch.Tensor):
        super().__init__()
        self.config = config
        self.register_buffer("scene_bounds", bounds.detach().clone().float())
        self.register_buffer("bounds", self.scene_bounds.clone())
        self.register_buffer("mask", torch.ones(1, 1, 1, dtype=torch.bool, device=bounds.device))
        self.level = 0
        self.fine_step0 = config.coarse_iters
        # The colour MLP is created now (with the caller's RNG state, so a seeded build is
        # reproducible) but only registered when the fine stage starts.
        in_dim = config.feature_dim + encoding_dim(3, config.dir_freqs)
        object.__setattr__(self, "_pending_mlp", ColorMLP(in_dim, config.mlp_width, config.mlp_depth))
        if config.coarse_iters > 0:
            self.stage = "coarse"
            self.size, self.voxel = voxel_layout(self.bounds, config.coarse_num_voxels)
            self.unit = self.voxel
            self.shift = softplus_shift_for_alpha(config.coarse_alpha_init, config.stepsize)
            self.density_coarse = nn.Parameter(torch.zeros(1, *self.size, device=bounds.device))
            self.color_coarse = nn.Parameter(torch.zeros(3, *self.size, device=bounds.device))
        else:
            self._init_fine(self.scene_bounds.clone(), None, None)

    # ----- structure -------------------------------------------------------------------------
    def _fine_num_voxels(self) -> int:
        return max(8, int(self.config.num_voxels / 2 ** (len(self.config.growth_steps) - self.level)))

    def _init_fine(self, bounds: torch.Tensor, mask: torch.Tensor | None, coarse: tuple | None) -> None:
        """Switch to the fine stage in ``bounds``; ``coarse`` = (density, color, bounds, unit, shift) to start from."""
        cfg = self.config
        device = bounds.device
        self.stage = "fine"
        self.bounds = bounds
        self.mask = mask if mask is not None else torch.ones(1, 1, 1, dtype=torch.bool, device=device)
        _, self.unit = voxel_layout(bounds, cfg.num_voxels)
        self.size, self.voxel = voxel_layout(bounds, self._fine_num_voxels())
        self.shift = softplus_shift_for_alpha(cfg.alpha_init, cfg.stepsize)
        density = torch.zeros(1, *self.size, device=device)
        feats = torch.zeros(self._channels(), *self.size, device=device)
        if coarse is not None:
            c_density, c_color, c_bounds, c_unit, c_shift = coarse
            pts = grid_points(bounds, self.size).reshape(-1, 3)
            sigma_world = F.softplus(interp_cf(c_density, pts, c_bounds)[:, 0] + c_shift) / c_unit
            density = (softplus_inverse(sigma_world * self.unit) - self.shift).view(1, *self.size)
            feats[:3] = interp_cf(c_color, pts, c_bounds).t().reshape(3, *self.size)
        for name in ("density_coarse", "color_coarse"):
            if name in self._parameters:
                delattr(self, name)
        self.density = nn.Parameter(density)
        self.features = nn.Parameter(feats.reshape(self._channels(), -1).t().contiguous())
        if cfg.view_dependent and "mlp" not in self._modules:
            self.mlp = self._pending_mlp.to(device)

    def _channels(self) -> int:
        """Feature-grid channels: 3 diffuse logits, plus the MLP's inputs when view-dependent."""
        return 3 + (self.config.feature_dim if self.config.view_dependent else 0)

    def structure(self) -> dict[str, Any]:
        return {
            "stage": self.stage,
            "level": self.level,
            "fine_step0": self.fine_step0,
            "bounds": self.bounds.tolist(),
            "size": list(self.size),
            "mask_shape": list(self.mask.shape),
        }

    def load_structure(self, structure: dict[str, Any]) -> None:
        if structure["stage"] == "fine":
            device = self.scene_bounds.device
            bounds = torch.tensor(structure["bounds"], dtype=torch.float32, device=device)
            mask = torch.zeros(structure["mask_shape"], dtype=torch.bool, device=device)
            self.level = int(structure["level"])
            self.fine_step0 = int(structure["fine_step0"])
            self._init_fine(bounds, mask, None)
        if list(self.size) != list(structure["size"]):
            raise ValueError(f"grid size {self.size} does not match the checkpoint's {structure['size']}")

    # ----- interface ---------------------------------------------------------------------------
    def layers(self) -> list[Layer]:
        if self.stage == "coarse":
            return [Layer("density_coarse", ("density_coarse",)), Layer("color_coarse", ("color_coarse",))]
        out = [Layer("density", ("density",)), Layer("features", ("features",))]
        if self.config.view_dependent:
            out += [Layer(f"mlp.{i}", (f"mlp.linears.{i}.weight", f"mlp.linears.{i}.bias")) for i in range(len(self.mlp.linears))]
        return out

    def param_groups(self) -> list[ParamGroup]:
        cfg = self.config
        if self.stage == "coarse":
            return [
                ParamGroup("density", ("density_coarse",), cfg.lr_density),
                ParamGroup("features", ("color_coarse",), cfg.lr_features),
            ]
        groups = [
            ParamGroup("density", ("density",), cfg.lr_density),
            ParamGroup("features", ("features",), cfg.lr_features),
        ]
        if cfg.view_dependent:
            groups.append(ParamGroup("mlp", tuple(f"mlp.{n}" for n, _ in self.mlp.named_parameters()), cfg.lr_mlp))
        return groups

    def regularization(self) -> torch.Tensor | None:
        if self.config.tv_weight > 0 and self.stage == "fine":
            return self.config.tv_weight * total_variation(self.density)
        return None

    # ----- schedule ----------------------------------------------------------------------------
    def begin_step(self, step: int, total_steps: int | None) -> StepEvent:
        cfg = self.config
        if self.stage == "coarse" and step >= cfg.coarse_iters:
            bounds, mask = self._fine_box_and_mask()
            coarse = (self.density_coarse.data, self.color_coarse.data, self.bounds.clone(), self.unit, self.shift)
            self.fine_step0 = step
            self._init_fine(bounds, mask, coarse)
            lo, hi = bounds.tolist()
            occupied = 100 * self.mask.float().mean()
            return StepEvent(True, f"fine stage: box {[round(v, 3) for v in lo]}..{[round(v, 3) for v in hi]}, "
                                   f"grid {self.size}, {occupied:.1f}% occupied")
        if self.stage != "fine":
            return StepEvent()
        fine_step = step - self.fine_step0
        if self.level < len(cfg.growth_steps) and fine_step >= cfg.growth_steps[self.level]:
            self._grow()
            return StepEvent(True, f"grid grown to {self.size}")
        if cfg.occupancy_every > 0 and fine_step > 0 and fine_step % cfg.occupancy_every == 0 and cfg.empty_space_skipping:
            self._prune_mask()
        return StepEvent()

    def _density_grid(self) -> torch.Tensor:
        return self.density_coarse if self.stage == "coarse" else self.density

    @torch.no_grad()
    def _alpha_on(self, points: torch.Tensor, chunk: int = 1 << 18) -> torch.Tensor:
        """Alpha of one step (``stepsize`` units) at (N, 3) points, from the current density grid."""
        out = []
        for p in points.split(chunk):
            raw = interp_cf(self._density_grid(), p, self.bounds)[:, 0]
            out.append(-torch.expm1(-F.softplus(raw + self.shift) * self.config.stepsize))
        return torch.cat(out)

    @torch.no_grad()
    def _fine_box_and_mask(self) -> tuple[torch.Tensor, torch.Tensor | None]:
        cfg = self.config
        pts = grid_points(self.bounds, self.size)
        alpha = self._alpha_on(pts.reshape(-1, 3)).view(self.size)
        occupied = alpha > cfg.bbox_thres
        if not bool(occupied.any()):
            bounds = self.bounds.clone()
        else:
            occ_pts = pts[occupied]
            lo, hi = occ_pts.amin(0) - self.voxel, occ_pts.amax(0) + self.voxel
            centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo) * cfg.world_bound_scale
            bounds = torch.stack([torch.maximum(centre - half, self.bounds[0]), torch.minimum(centre + half, self.bounds[1])])
        if not cfg.empty_space_skipping:
            return bounds, None
        full_size, _ = voxel_layout(bounds, cfg.num_voxels)
        alpha = self._alpha_on(grid_points(bounds, full_size).reshape(-1, 3)).view(full_size)
        return bounds, _dilate(alpha > cfg.mask_cache_thres, radius=2)

    @torch.no_grad()
    def _grow(self) -> None:
        self.level += 1
        old = self.size
        self.size, self.voxel = voxel_layout(self.bounds, self._fine_num_voxels())
        channels = self.features.shape[1]
        feats = resample_cf(self.features.data.t().reshape(channels, *old), self.size)
        self.density = nn.Parameter(resample_cf(self.density.data, self.size))
        self.features = nn.Parameter(feats.reshape(channels, -1).t().contiguous())

    @torch.no_grad()
    def _prune_mask(self) -> None:
        if self.mask.numel() == 1:
            return
        size = tuple(self.mask.shape)
        alpha = self._alpha_on(grid_points(self.bounds, size).reshape(-1, 3)).view(size)  # type: ignore[arg-type]
        self.mask &= _dilate(alpha > self.config.mask_cache_thres, radius=1)

    # ----- rendering ---------------------------------------------------------------------------
    def forward(
        self,
        rays: RayBatch,
        *,
        background: torch.Tensor,
        train: bool = False,
        generator: torch.Generator | None = None,
    ) -> RenderOutput:
        cfg = self.config
        n = len(rays)
        near, far, _ = clip_to_aabb(rays.origins, rays.directions, rays.near, rays.far, self.bounds)
        step = cfg.stepsize * self.voxel
        max_samples = max(1, int(math.ceil(float((far - near).max()) / step))) if n else 1
        t, delta, valid = fixed_step_samples(near, far, step, max_samples, generator=generator, perturb=train)
        if self.stage == "coarse":
            return self._render_coarse(rays, t, delta, far, background)
        ray_idx, sample_idx = torch.nonzero(valid, as_tuple=True)
        pts = torch.addcmul(rays.origins[ray_idx], t[ray_idx, sample_idx, None], rays.directions[ray_idx])
        if cfg.empty_space_skipping and self.mask.numel() > 1:
            keep = nearest_lookup(self.mask, pts, self.bounds)
            ray_idx, sample_idx, pts = ray_idx[keep], sample_idx[keep], pts[keep]
        raw = interp_cf(self.density, pts, self.bounds)[:, 0]
        sigma = F.softplus(raw + self.shift)
        tau = torch.zeros_like(t).index_put((ray_idx, sample_idx), sigma * (delta[ray_idx, sample_idx] / self.unit))
        weights, t_final = render_weights(tau)
        w = weights[ray_idx, sample_idx]
        sel = w > cfg.fast_color_thres
        ray_c, w_c, pts_c = ray_idx[sel], w[sel], pts[sel]
        feats = interp_cl(self.features, pts_c, self.bounds, self.size)
        logits = feats[:, :3]
        if cfg.view_dependent:
            view = positional_encoding(rays.directions[ray_c], cfg.dir_freqs)
            logits = logits + self.mlp(torch.cat([feats[:, 3:], view], -1))
        rgb = torch.zeros(n, 3, dtype=logits.dtype, device=logits.device)
        rgb = rgb.index_add(0, ray_c, w_c[:, None] * torch.sigmoid(logits)) + t_final[:, None] * background
        depth = (weights * t).sum(-1) + t_final * far
        return RenderOutput(rgb=rgb, acc=1.0 - t_final, depth=depth, samples_evaluated=int(pts.shape[0]))

    def _render_coarse(
        self, rays: RayBatch, t: torch.Tensor, delta: torch.Tensor, far: torch.Tensor, background: torch.Tensor
    ) -> RenderOutput:
        """Dense rendering of every sample (no cache yet): samples past ``far`` have ``delta = 0``."""
        n, s = t.shape
        pts = (rays.origins[:, None] + t[..., None] * rays.directions[:, None]).reshape(-1, 3)
        values = interp_cf(torch.cat([self.density_coarse, self.color_coarse]), pts, self.bounds).view(n, s, 4)
        tau = F.softplus(values[..., 0] + self.shift) * (delta / self.unit)
        weights, t_final = render_weights(tau)
        rgb = torch.einsum("rs,rsc->rc", weights, torch.sigmoid(values[..., 1:])) + t_final[:, None] * background
        depth = (weights * t).sum(-1) + t_final * far
        return RenderOutput(rgb=rgb, acc=1.0 - t_final, depth=depth, samples_evaluated=int((delta > 0).sum()))


def _dilate(mask: torch.Tensor, radius: int) -> torch.Tensor:
    """Grow a (X, Y, Z) boolean mask by ``radius`` voxels (max pooling)."""
    k = 2 * radius + 1
    return F.max_pool3d(mask[None, None].float(), k, stride=1, padding=radius)[0, 0] > 0
