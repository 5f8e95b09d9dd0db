"""The NeRF MLP backbone: a positional-encoded MLP field, sampled by the occupancy-grid estimator or stratified.

Two estimators (``NerfMLPConfig.estimator``): ``stratified`` (NeRF's: ``n_samples`` per ray in
``[near, far]``, optionally ``n_importance`` more from the first pass's weights; the field needs no
estimator state, which meta-learning relies on) or ``occupancy``: the shared
:class:`~nerfmeta.render.estimators.OccupancyGrid` marches the box every ``2 / n_samples`` box units,
skips the cells the grid marks empty and stops rays behind an opaque layer (``early_stop_eps``). Its
grid is refreshed from the field's own density every ``occupancy_every`` steps after an
``occupancy_warmup`` during which nothing is skipped (as Instant-NGP and nerfacc do).

The field lives in the box-normalised frame: sample points are mapped to [-1, 1]^3 with
:func:`~nerfmeta.fields.encoding.normalize_to_box` before encoding, and densities are per
*box unit* (world lengths divided by the mean half-side of ``bounds``; exact for a cube). So the
same weights mean the same geometry in scenes of different scale, which transfer and
meta-learning across scenes rely on, and the initial-alpha shift below needs no scene size.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from nerfmeta.config import check_fields
from nerfmeta.data.scene import RayBatch
from nerfmeta.errors import ConfigError
from nerfmeta.fields.base import Layer, MetaHints, ParamGroup, RadianceModel, RenderOutput, SamplingPlan, StepEvent
from nerfmeta.fields.encoding import encoding_dim, normalize_to_box, positional_encoding
from nerfmeta.fields.encodings import EncodingChoice, build_encoding, encoding_config
from nerfmeta.render.estimators import OccupancyGrid
from nerfmeta.render.sampling import importance_samples, intervals_from_points, stratified_samples
from nerfmeta.render.volume import alpha_from_tau, render_packed, softplus_shift_for_alpha

DENSITY_ACTIVATIONS = ("softplus", "relu")
ESTIMATORS = ("stratified", "occupancy")


@dataclass(frozen=True)
class NerfMLPConfig(EncodingChoice):
    """Architecture, sampling and learning rate of :class:`NerfMLP` (saved as JSON with every run); ``encoding`` picks the position encoding."""

    pos_freqs: int = 10
    """Octaves of the positional encoding of the (box-normalised) sample position."""
    dir_freqs: int = 4
    """Octaves of the positional encoding of the view direction (unused when not view-dependent)."""
    depth: int = 8
    """Number of linear+ReLU layers in the trunk that maps the encoded position to features."""
    width: int = 256
    """Width of the trunk (the view branch is ``width // 2`` wide)."""
    skips: tuple[int, ...] = (4,)
    """Trunk layers whose input is ``[features, encoded position]`` (0-based; 1..depth-1)."""
    view_dependent: bool = True
    """Colour depends on the view direction through a feature layer and a width/2 layer."""
    n_samples: int = 64
    """Stratified samples per ray (jittered in training, bin midpoints otherwise)."""
    n_importance: int = 0
    """Extra samples per ray drawn from the first pass's weights (0 disables the second pass)."""
    density_activation: str = "softplus"
    """``softplus`` (shifted so raw 0 gives ``alpha_init``, as DirectVoxGO) or ``relu`` (NeRF)."""
    alpha_init: float = 1e-2
    """Alpha of one sample spacing (``2 / n_samples`` box units) for raw 0; softplus only."""
    lr: float = 5e-4
    """Adam learning rate of all the MLP's parameters."""
    raw_noise_std: float = 0.0
    """Std of Gaussian noise added to the raw density in training (NeRF's regulariser; 0 = off; stratified only)."""
    estimator: str = "stratified"
    """Where to sample: ``stratified`` (``n_samples`` (+ ``n_importance``) per ray, no state) or ``occupancy`` (march every ``2 / n_samples`` box units, skipping empty cells of an occupancy grid and samples behind opaque ones)."""
    occupancy_resolution: int = 64
    """``occupancy``: grid corners per axis over the box."""
    occupancy_warmup: int = 20
    """``occupancy``: steps before the first grid refresh (nothing is skipped until then; on lego 100x100 20 steps at lr 5e-3 already carve the empty space: 1296 steps at 3.4 samples/ray in 90 s, against 50 steps at 34 with a 256-step warm-up)."""
    occupancy_every: int = 32
    """``occupancy``: steps between grid refreshes (each evaluates the density at every corner, without gradient)."""
    occupancy_thres: float = 0.01
    """``occupancy``: alpha over one marching step above which a corner stays occupied (nerfacc's ``occ_thre``)."""
    early_stop_eps: float = 1e-4
    """``occupancy``: drop samples whose transmittance in front is below this (0: off)."""

    def __post_init__(self) -> None:
        check_fields(self, "nerf config")  # types first, then the ranges below
        # JSON has no tuples: accept a list for ``skips`` so a saved config loads back equal.
        object.__setattr__(self, "skips", tuple(int(s) for s in self.skips))
        checks = (
            ("pos_freqs", self.pos_freqs >= 0, "use 0 or more"),
            ("dir_freqs", self.dir_freqs >= 0, "use 0 or more"),
            ("depth", self.depth >= 1, "use 1 or more"),
            ("width", self.width >= 2, "use 2 or more"),
            ("skips", all(1 <= s < self.depth for s in self.skips), f"use layer indices in 1..{self.depth - 1}"),
            ("n_samples", self.n_samples >= 1, "use 1 or more"),
            ("n_importance", self.n_importance >= 0, "use 0 (off) or more"),
            ("density_activation", self.density_activation in DENSITY_ACTIVATIONS,
             f"use one of {', '.join(DENSITY_ACTIVATIONS)}"),
            ("alpha_init", 0.0 < self.alpha_init < 1.0, "use a value in (0, 1), e.g. 1e-2"),
            ("lr", 0.0 < self.lr < math.inf, "use a positive finite learning rate"),
            ("raw_noise_std", self.raw_noise_std >= 0.0, "use 0 (off) or more"),
            ("estimator", self.estimator in ESTIMATORS, f"use one of {', '.join(ESTIMATORS)}"),
            ("n_importance", self.n_importance == 0 or self.estimator == "stratified", "importance sampling needs estimator=stratified"),
            ("occupancy_resolution", self.occupancy_resolution >= 2, "use 2 or more"),
            ("occupancy_warmup", self.occupancy_warmup >= 0, "use 0 or more"),
            ("occupancy_every", self.occupancy_every >= 1, "use 1 or more"),
            ("occupancy_thres", 0.0 <= self.occupancy_thres < 1.0, "use a value in [0, 1), e.g. 0.01"),
            ("early_stop_eps", 0.0 <= self.early_stop_eps < 1.0, "use a value in [0, 1), e.g. 1e-4"),
        )
        for name, ok, hint in checks:
            if not ok:
                raise ConfigError(f"nerf config {name}={getattr(self, name)!r} is not allowed: {hint}")

    @property
    def density_shift(self) -> float:
        """Added to the raw density before softplus: raw 0 gives ``alpha_init`` per sample spacing.

        The spacing is taken as ``2 / n_samples`` box units, i.e. the stratified spacing of a
        ray whose ``[near, far]`` is as long as the box is wide (DirectVoxGO's ``act_shift``
        with this interval). ``relu`` has no shift (0).
        """
        if self.density_activation != "softplus":
            return 0.0
        return softplus_shift_for_alpha(self.alpha_init, 2.0 / self.n_samples)


NERF_PAPER = NerfMLPConfig()
"""The NeRF paper's network (8x256, skip at the middle, view branch) with 64 stratified samples."""

NERF_SMALL = NerfMLPConfig(pos_freqs=8, depth=4, width=128, skips=(2,), n_samples=48)
"""A 4x128 network with 48 samples: the CLI's default, sized for a 2-core CPU machine."""

NERF_META_HINTS = MetaHints(
    model_defaults={"pos_freqs": 6, "depth": 4, "width": 64, "skips": (2,), "n_samples": 32},
    # One initialisation for many scenes: no per-scene estimator state.
    fixed={"estimator": "stratified"},
    fixed_reason="one initialisation serves many scenes, so it keeps no per-scene occupancy grid",
    # 30 gave the best held-out adaptation with Reptile on a 6-category 32 px collection (+3.2 dB in
    # 3 steps after 300 meta-steps; 10 learned more slowly) and stayed finite with MAML and FOMAML.
    inner_lr=30.0,
)
"""Meta-learning the MLP: every algorithm (its forward is smooth, so second order is exact; tested)."""

PRESETS: dict[str, NerfMLPConfig] = {"paper": NERF_PAPER, "small": NERF_SMALL}
"""Named presets, for ``--preset`` style choices."""


class NerfMLP(RadianceModel):
    """NeRF: a positional-encoded MLP mapping a point (and view direction) to density and colour.

    Architecture (``W = width``, ``P``/``V`` the encoded position/direction widths)::

        trunk.0 .. trunk.{depth-1}   Linear + ReLU; trunk.i takes [h, P] for i in skips
        density                      Linear(W, 1) on the trunk output -> raw density
        feature                      Linear(W, W), no activation         (view_dependent only)
        view.0                       Linear(W + V, W/2) + ReLU           (view_dependent only)
        rgb                          Linear(W/2, 3) (or Linear(W, 3) without the view branch) -> sigmoid

    Note ``skips=(4,)`` concatenates the input before the fifth trunk layer (``trunk.4``); the
    official NeRF code's ``skips=[4]`` concatenates it one layer later (before ``trunk.5``).

    Rendering (one pass over all given rays; the caller chunks), ``estimator="stratified"``:
    ``n_samples`` stratified samples in ``[near, far]`` (jittered with ``generator`` when
    ``train``, bin midpoints otherwise), ``tau = sigma * delta`` with ``delta`` in box units, then
    the shared compositor on the background. With ``n_importance > 0`` a second pass draws ``n_importance`` samples from the
    first pass's weights and renders the sorted union of both sets, re-using the first pass's
    evaluations. Both passes use the *same* network (a common lightweight variant; the NeRF paper
    trains a separate coarse network); the first pass's colour is in ``extras["rgb_coarse"]`` so
    a loss may supervise it too. ``estimator="occupancy"``: the shared occupancy-grid estimator
    picks the samples (see the module docstring) and the base class renders them.

    Layers for ``freeze_first(k)``, input to output: ``trunk.0 .. trunk.{depth-1}, density``
    and, with the view branch, ``feature, view.0``, then ``rgb``. So ``k <= depth`` freezes the
    first ``k`` trunk layers (``k = depth // 2``: the first half of the trunk; ``k = depth``:
    the whole trunk), ``k = depth + 1`` also the density head, i.e. all of the geometry, so only
    the colour layers adapt; ``k = len(layers())`` freezes everything. For ``NERF_PAPER`` that is
    12 layers (4 = half the trunk, 9 = geometry); for ``NERF_SMALL`` 8 (2 = half, 5 = geometry).

    Parameters are created on ``bounds``' device and dtype; ``forward`` follows its inputs and
    changes no state, so ``torch.func.functional_call`` and second-order gradients work.
    """

    backbone = "nerf"
    meta_hints = NERF_META_HINTS

    def __init__(self, config: NerfMLPConfig, bounds: torch.Tensor, *, generator: torch.Generator | None = None):
        """Build the network.

        Args:
            config: architecture and sampling.
            bounds: (2, 3) ``[min_xyz, max_xyz]`` box holding the content (kept as a buffer).
            generator: random source for the initial weights (PyTorch's default ``nn.Linear``
                initialisation); None uses the global generator.
        """
        super().__init__()
        if tuple(bounds.shape) != (2, 3) or not bool((bounds[1] > bounds[0]).all()):
            raise ConfigError(f"nerf bounds {bounds.tolist()} must be [min_xyz, max_xyz] with min < max on every axis")
        self.config = config
        self.register_buffer("bounds", bounds.detach().clone())
        kw = {"device": bounds.device, "dtype": bounds.dtype}
        self.encoder = build_encoding(encoding_config(config, config.pos_freqs))  # pe: parameter-free, as before
        w, pos_dim = config.width, self.encoder.out_dim
        self.trunk = nn.ModuleList(
            nn.Linear((pos_dim if i == 0 else w) + (pos_dim if i in config.skips else 0), w, **kw)
            for i in range(config.depth)
        )
        self.density = nn.Linear(w, 1, **kw)
        if config.view_dependent:
            self.feature = nn.Linear(w, w, **kw)
            self.view = nn.ModuleList([nn.Linear(w + encoding_dim(3, config.dir_freqs), w // 2, **kw)])
            self.rgb = nn.Linear(w // 2, 3, **kw)
        else:
            self.rgb = nn.Linear(w, 3, **kw)
        if generator is not None:
            self._init_weights(generator)
        if config.estimator == "occupancy":  # a (1, 1, 1) grid until the warm-up ends: nothing skipped
            self.occupancy = OccupancyGrid(bounds)

    def _init_weights(self, generator: torch.Generator) -> None:
        """``nn.Linear``'s default init, U(-1/sqrt(fan_in), 1/sqrt(fan_in)), drawn from ``generator``."""
        with torch.no_grad():
            for module in self.modules():
                if isinstance(module, nn.Linear):
                    bound = 1.0 / math.sqrt(module.in_features)
                    for p in (module.weight, module.bias):
                        u = torch.rand(p.shape, generator=generator, dtype=p.dtype, device="cpu")
                        p.copy_((2.0 * u - 1.0) * bound)

    # -- the field -------------------------------------------------------------------------

    def _raw(self, points: torch.Tensor, directions: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw density (...,) before activation and colour (..., 3) in [0, 1]; see :meth:`query`."""
        raw_sigma, h = self._raw_density(points)
        return raw_sigma, self._color(h, directions)

    def _raw_density(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw density (...,) and the trunk's output features (..., width) at world points (..., 3)."""
        x = self.encoder(normalize_to_box(points, self.bounds))
        k = self._frozen_prefix(x)
        with torch.no_grad():  # frozen leading layers: their outputs need no graph
            h = self._trunk(x, x, 0, k)
        h = self._trunk(h, x, k, self.config.depth)
        return self.density(h)[..., 0], h

    def _color(self, h: torch.Tensor, directions: torch.Tensor | None) -> torch.Tensor:
        """Colour (..., 3) from trunk features (..., width) and directions broadcastable to them."""
        if self.config.view_dependent:
            if directions is None:
                raise ValueError("this NerfMLP is view-dependent: query() needs directions")
            d = positional_encoding(directions, self.config.dir_freqs)
            d = d.expand(*h.shape[:-1], d.shape[-1])
            h = F.relu(self.view[0](torch.cat([self.feature(h), d], dim=-1)))
        return torch.sigmoid(self.rgb(h))

    def _trunk(self, h: torch.Tensor, x: torch.Tensor, start: int, stop: int) -> torch.Tensor:
        """Trunk layers ``start .. stop - 1`` applied to ``h`` (``x``: the encoded position, for the skips)."""
        for i in range(start, stop):
            if i in self.config.skips:
                h = torch.cat([h, x], dim=-1)
            h = F.relu(self.trunk[i](h))
        return h

    def _frozen_prefix(self, x: torch.Tensor) -> int:
        """How many leading trunk layers can run without autograd: frozen parameters, an input needing no gradient.

        Frozen layers (``freeze_first``) on an input without gradient already build no graph (autograd
        records nothing when no input needs a gradient); running them under ``no_grad`` makes that explicit.
        Parameters passed through ``torch.func.functional_call`` (meta-learning) count as they are passed.
        """
        if not torch.is_grad_enabled() or x.requires_grad:
            return 0
        k = 0
        for layer in self.trunk:
            if layer.weight.requires_grad or layer.bias.requires_grad:
                break
            k += 1
        return k

    def _activate(self, raw_sigma: torch.Tensor) -> torch.Tensor:
        if self.config.density_activation == "softplus":
            return F.softplus(raw_sigma + self.config.density_shift)
        return F.relu(raw_sigma)

    def query(
        self, points: torch.Tensor, directions: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Density and colour at world-space points.

        Args:
            points: (..., 3) world positions.
            directions: (..., 3) unit view directions, broadcastable to ``points`` (e.g.
                (n_rays, 1, 3) for points (n_rays, n_samples, 3)); ignored, and may be None,
                when the model is not view-dependent.

        Returns:
            sigma (...,) non-negative density per box unit of length, and rgb (..., 3) in [0, 1].
        """
        raw_sigma, rgb = self._raw(points, directions)
        return self._activate(raw_sigma), rgb

    # -- the field -------------------------------------------------------------------------

    def box_unit(self) -> torch.Tensor:
        """World length of one box unit (the mean half-side of ``bounds``)."""
        return 0.5 * (self.bounds[1] - self.bounds[0]).mean()

    def get_density(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Density per world unit at (N, 3) points; the embedding is the trunk's output (N, width)."""
        raw_sigma, h = self._raw_density(points)
        return self._activate(raw_sigma) / self.box_unit(), h

    def get_outputs(self, embedding: torch.Tensor, sel: torch.Tensor | None, directions: torch.Tensor,
                    ray_idx: torch.Tensor) -> torch.Tensor:
        """Colour (K, 3) of the points ``sel`` from their trunk features and their rays' directions."""
        h = embedding if sel is None else embedding.index_select(0, sel)
        return self._color(h, directions.index_select(0, ray_idx) if self.config.view_dependent else None)

    # -- the estimator -----------------------------------------------------------------------

    def march_step(self) -> float:
        """Marching step of the ``occupancy`` estimator: ``2 / n_samples`` box units, in world units."""
        return float(2.0 / self.config.n_samples * self.box_unit())

    def sample(self, rays: RayBatch, *, train: bool, generator: torch.Generator | None) -> SamplingPlan:
        """``occupancy``: march the box, skip empty cells and samples behind opaque ones (see the module docstring)."""
        n, dtype, device = len(rays), rays.origins.dtype, rays.origins.device
        if train:
            jitter = torch.rand(n, generator=generator, dtype=dtype, device="cpu").to(device)
        else:
            jitter = torch.full((n,), 0.5, dtype=dtype, device=device)
        samples = self.occupancy.sampling(
            rays.origins, rays.directions, rays.near, rays.far, step=self.march_step(), jitter=jitter,
            sigma_fn=lambda points, _: self.get_density(points)[0], early_stop_eps=self.config.early_stop_eps)
        return SamplingPlan(samples)

    def begin_step(self, step: int, progress: float | None) -> StepEvent:
        """``occupancy``: refresh the grid from the density every ``occupancy_every`` steps after the warm-up."""
        cfg = self.config
        if cfg.estimator != "occupancy" or step < cfg.occupancy_warmup or (step - cfg.occupancy_warmup) % cfg.occupancy_every:
            return StepEvent()
        size = (cfg.occupancy_resolution,) * 3
        step_len = self.march_step()
        self.occupancy.refresh(lambda p: alpha_from_tau(self.get_density(p)[0] * step_len), size, cfg.occupancy_thres)
        message = f"occupancy grid refreshed: {100 * self.occupancy.occupied_fraction():.1f}% occupied" \
            if step == cfg.occupancy_warmup else ""
        return StepEvent(False, message)

    def structure(self) -> dict:
        return {"occupancy_shape": list(self.occupancy.size)} if self.config.estimator == "occupancy" else {}

    def load_structure(self, structure: dict) -> None:
        if "occupancy_shape" in structure:
            self.occupancy.binaries = torch.zeros(structure["occupancy_shape"], dtype=torch.bool, device=self.bounds.device)

    # -- rendering -------------------------------------------------------------------------

    def render(self, rays: RayBatch, **kwargs: Any) -> RenderOutput:
        """:meth:`RadianceModel.render <nerfmeta.fields.base.RadianceModel.render>` with the ``occupancy`` estimator, else stratified."""
        if self.config.estimator == "occupancy":
            return super().render(rays, **kwargs)
        return self._render_stratified(rays, **kwargs)

    def _render_stratified(self, rays: RayBatch, *, background: torch.Tensor, train: bool = False,
                           generator: torch.Generator | None = None, view_dirs: torch.Tensor | None = None) -> RenderOutput:
        """Render ``rays`` (n_rays of them) in one pass.

        Args:
            rays: origins (n_rays, 3), unit directions (n_rays, 3), near/far (n_rays,).
            background: (3,) or (n_rays, 3) RGB behind the content.
            train: jitter the samples (and add ``raw_noise_std`` noise) using ``generator``.
            generator: random source for training; None uses the global generator.
            view_dirs: (n_rays, 3) directions to colour with instead of the rays' own.

        Returns:
            rgb (n_rays, 3), acc (n_rays,), depth (n_rays,) in world units and
            ``samples_evaluated``: with ``occupancy``, the samples kept by the estimator; with
            ``stratified``, ``n_rays * (n_samples + n_importance)``, and extras ``t`` (n_rays, n)
            the sorted sample distances, ``weights`` (n_rays, n) their compositing weights (``n``
            all samples of the final pass) and, with importance sampling, ``rgb_coarse`` (n_rays,
            3) of the first pass.
        """
        cfg = self.config
        directions = rays.directions if view_dirs is None else view_dirs
        t, delta, edges = stratified_samples(rays.near, rays.far, cfg.n_samples, generator=generator, perturb=train)
        h, sigma = self._evaluate(rays, t, train, generator)
        extras: dict[str, torch.Tensor] = {}
        if cfg.n_importance > 0:
            coarse = self._composite(t, delta, sigma, h, directions, rays.far, background)
            extras["rgb_coarse"] = coarse.rgb
            t_fine = importance_samples(edges, coarse.weights.view(t.shape), cfg.n_importance, generator=generator, perturb=train)
            h_fine, sigma_fine = self._evaluate(rays, t_fine, train, generator)
            t, order = torch.sort(torch.cat([t, t_fine], dim=-1), dim=-1)
            sigma = torch.cat([sigma, sigma_fine], dim=-1).gather(-1, order)
            h = torch.cat([h, h_fine], dim=-2).gather(-2, order[..., None].expand(-1, -1, h.shape[-1]))
            delta = intervals_from_points(t, rays.near, rays.far)
        comp = self._composite(t, delta, sigma, h, directions, rays.far, background)
        extras["t"] = t
        extras["weights"] = comp.weights.view(t.shape)
        return RenderOutput(rgb=comp.rgb, acc=comp.acc, depth=comp.depth,
                            samples_evaluated=len(rays) * (cfg.n_samples + cfg.n_importance), extras=extras)

    def _evaluate(
        self, rays: RayBatch, t: torch.Tensor, train: bool, generator: torch.Generator | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Trunk features (n_rays, n, width) and density per world unit (n_rays, n) at distances ``t`` (n_rays, n)."""
        points = rays.origins[:, None, :] + t[..., None] * rays.directions[:, None, :]
        raw_sigma, h = self._raw_density(points)
        if train and self.config.raw_noise_std > 0.0:
            noise = torch.randn(raw_sigma.shape, generator=generator, dtype=raw_sigma.dtype, device="cpu")
            raw_sigma = raw_sigma + self.config.raw_noise_std * noise.to(raw_sigma.device)
        return h, self._activate(raw_sigma) / self.box_unit()

    def _composite(self, t, delta, sigma, h, directions, far, background):
        """The shared compositor over fixed-count samples ((n_rays, n) each, ``h`` (n_rays, n, width)), flattened."""
        n_rays, n = t.shape
        ray_idx = torch.arange(n_rays, device=t.device).repeat_interleave(n)
        flat_h = h.reshape(n_rays * n, -1)
        return render_packed((sigma * delta).reshape(-1), t.reshape(-1), ray_idx, far, background,
                             lambda sel, rays_: self.get_outputs(flat_h, sel, directions, rays_))

    # -- interface -------------------------------------------------------------------------

    def layers(self) -> list[Layer]:
        names = (["encoder"] if any(True for _ in self.encoder.parameters()) else [])
        names += [f"trunk.{i}" for i in range(self.config.depth)] + ["density"]
        if self.config.view_dependent:
            names += ["feature", "view.0"]
        names.append("rgb")
        return [
            Layer(name, tuple(f"{name}.{p}" for p, _ in self.get_submodule(name).named_parameters()))
            for name in names
        ]

    def param_groups(self) -> list[ParamGroup]:
        names = tuple(n for n, _ in self.named_parameters())
        enc = tuple(n for n in names if n.startswith("encoder."))
        mlp = ParamGroup("mlp", tuple(n for n in names if n not in enc), self.config.lr)
        return [mlp, ParamGroup("encoding", enc, self.config.encoding_lr)] if enc else [mlp]

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):  # type: ignore[override]
        # The occupancy grid is rebuilt by the fit (warm-up, refreshes): a state without it (a model
        # zoo entry, a stratified fit) loads into an occupancy model as "nothing skipped yet".
        if "occupancy" in self._modules:
            state_dict.setdefault(prefix + "occupancy.aabb", self.occupancy.aabb)
            state_dict.setdefault(prefix + "occupancy.binaries", self.occupancy.binaries)
        else:
            for key in ("occupancy.aabb", "occupancy.binaries"):
                state_dict.pop(prefix + key, None)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
