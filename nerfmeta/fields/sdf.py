"""A signed-distance field with a colour branch, volume-rendered NeuS-style through the shared renderer.

The field (IDR, Yariv et al. NeurIPS 2020; NeuS, Wang et al. NeurIPS 2021): an MLP with softplus
(beta 100) activations maps an encoded point to its signed distance and a feature vector; a colour
MLP maps ``[x, normal, encoded view direction, feature]`` to RGB (optionally also the trilinear features of a
dense colour grid, ``color_grid``, so a texture need not bend the SDF network's features). Geometric initialisation (Atzmon
and Lipman's SAL, as IDR) makes the network start as a sphere of radius ``init_radius``.

Frame: points are mapped *isotropically* into the box's frame, ``x = (p - centre) / h`` with ``h``
the box's largest half-side, so ``sdf`` stays a distance (world distance = ``h * sdf``) and the
same weights mean the same shape at any scene scale.

Rendering (NeuS): the shared :class:`~nerfmeta.render.estimators.OccupancyGrid` marches the box, marked where
``|f|`` is within a band of the surface (most refreshes evaluate only the corners near the band: :class:`NarrowBand`);
each sample's SDF ``f``, its gradient and the ray direction give the section's estimated SDF at
both ends, ``f -+ cos * delta / 2`` (``cos``: NeuS's annealed slope, :func:`annealed_cos`, exactly
``min(d . n, 0)`` once ``cos_anneal_iters`` have passed, or from the start by default), and the
discrete opacity ``alpha = (Phi(f_prev) - Phi(f_next)) / Phi(f_prev)`` with the logistic
``Phi(f) = sigmoid(s f)`` of a learned inverse standard deviation ``s = exp(10 * variance)``
(:func:`neus_tau` gives its optical depth exactly in log space). With ``refine`` > 1 the sections whose
middle is within a section length of the surface are split into ``refine`` sub-sections first
(:func:`~nerfmeta.render.estimators.split_sections`; NeuS up-samples near the surface for the same reason: a
wall thinner than the step is otherwise missed by the samples and leaks light). The compositor is
:func:`~nerfmeta.render.volume.render_packed`, as for every backbone.

Losses (named terms, :meth:`SdfField.loss_terms`): ``mse``; ``eikonal``: ``(|grad f| - 1)^2``
at the samples times ``eikonal_weight`` (0.1, as IDR, NeuS, Neuralangelo; optionally ramped up from
``eikonal_start_weight`` over the steps ``eikonal_ramp`` or the fractions of the fit ``eikonal_ramp_progress``); ``mask``: binary
cross-entropy of the opacity against the scene's alpha (when the rays carry one) times
``mask_weight``; ``curvature``: the mean absolute Laplacian of ``f`` (Neuralangelo) times
``curvature_weight`` (0: off); ``shell``: the samples' mean inside-probability ``sigmoid(-s f)`` times
``shell_weight`` (0: off; a thin-shell prior, 0.005 in ``--preset concave``; optionally faded out over ``shell_fade_progress``). Gradients are analytic (autograd, second order for the eikonal
term) or finite differences of step ``numerical_eps`` (Neuralangelo's choice for hash grids,
whose trilinear gradient jumps at cell faces): ``gradient=auto`` picks numerical for grid encodings.
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
from nerfmeta.fields.base import Layer, MetaHints, ParamGroup, RadianceModel, RenderOutput, SamplingPlan, StepEvent, photometric_mse
from nerfmeta.fields.encoding import encoding_dim, positional_encoding
from nerfmeta.fields.encodings import GRID_ENCODINGS, EncodingChoice, build_encoding, encoding_config
from nerfmeta.fields.grid_kernels import fused_available, interp_points
from nerfmeta.render.estimators import OccupancyGrid, dilate, grid_points, split_sections, values_near
from nerfmeta.render.volume import render_packed

GRADIENTS = ("auto", "analytic", "numerical")
TETRAHEDRON = ((1.0, -1.0, -1.0), (-1.0, -1.0, 1.0), (-1.0, 1.0, -1.0), (1.0, 1.0, 1.0))
"""Directions of the 4-point numerical gradient (NeuS2's tetrahedron)."""
SOFTPLUS_BETA = 100.0
"""Sharpness of the SDF network's softplus activations (IDR, NeuS: 100)."""
UNIT_BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
"""The box frame's cube, which the colour grid covers."""


@dataclass
class NarrowBand:
    """The occupancy refreshes' memory: ``|f|`` at the grid's corners and when the next full refresh is due.

    Attributes:
        corners: (K, 3) the grid's corners in the box frame, or None (made at the next refresh: they follow ``bounds``).
        distance: (K,) ``|f|`` at them (box half-sides) as last evaluated, or None (the next refresh is full).
        period: refreshes from one full refresh to the next.
        since_full: refreshes since the last full one.
        full, evaluated, missed: counts over the fit: full refreshes, corners evaluated, and corners a full refresh
            marked that the narrow refreshes before it had left out.
    """

    corners: torch.Tensor | None = None
    distance: torch.Tensor | None = None
    period: int = 1
    since_full: int = 0
    full: int = 0
    evaluated: int = 0
    missed: int = 0

    def forget(self) -> None:
        """Drop what was remembered (the field or its box changed outside a fit step): the next refresh is full."""
        self.corners, self.distance, self.period, self.since_full = None, None, 1, 0

    def record(self, distance: torch.Tensor, evaluated: int, full: bool, band: float, limit: float, most: int) -> None:
        """Keep a refresh's ``distance``; after a full one, double the period (up to ``most``) when no corner within
        ``band`` was beyond ``limit`` before it, else fall back to 1."""
        if full and self.distance is not None:
            missed = int(((distance < band) & (self.distance >= limit)).sum())
            self.missed += missed
            self.period = 1 if missed else min(2 * self.period, most)
        self.since_full = 0 if full else self.since_full + 1
        self.distance = distance
        self.full += int(full)
        self.evaluated += evaluated


def annealed_cos(true_cos: torch.Tensor, ratio: float) -> torch.Tensor:
    """NeuS's ``iter_cos``: the slope of the SDF along a ray that the opacity uses, annealed from soft to exact.

    ``-((1 - ratio) * relu(0.5 - 0.5 cos) + ratio * relu(-cos))``: at ``ratio`` 1 it is ``min(cos, 0)``
    (only sections where the SDF falls are opaque); at 0 every section gets a slope of at least
    ``-(1 - cos) / 2``, so back-facing and grazing sections stay partly opaque early in a fit, and
    the surface can still move and change topology before the density sharpens.

    Args:
        true_cos: (M,) ``d . grad f`` per sample.
        ratio: in [0, 1], the fraction of the anneal done.

    Returns:
        (M,) non-positive slopes.
    """
    if ratio >= 1.0:
        return torch.clamp(true_cos, max=0.0)
    return -((1.0 - ratio) * F.relu(0.5 - 0.5 * true_cos) + ratio * F.relu(-true_cos))


def ramped_weight(at: float, start: float, final: float, ramp: tuple[float, float]) -> float:
    """A loss weight that is ``start`` until ``ramp[0]``, ``final`` from ``ramp[1]`` on, and linear between.

    ``at`` and ``ramp`` are on one axis: steps, or fractions of the fit (its progress).
    ``start < 0`` means no ramp (``final`` throughout); ``ramp[0] == ramp[1]`` is a switch there.
    """
    if start < 0.0 or at >= ramp[1]:
        return final
    if at <= ramp[0]:
        return start
    return start + (final - start) * (at - ramp[0]) / (ramp[1] - ramp[0])


def neus_tau(sdf: torch.Tensor, cos: torch.Tensor, delta: torch.Tensor, inv_s: torch.Tensor) -> torch.Tensor:
    """NeuS's discrete opacity of a section as an optical depth ``tau = -log(1 - alpha)``.

    ``alpha = (Phi(f_prev) - Phi(f_next)) / Phi(f_prev)`` clipped to [0, 1], with
    ``Phi(f) = sigmoid(s f)``, ``f_prev/next = sdf -/+ cos * delta / 2``; so
    ``tau = log Phi(f_prev) - log Phi(f_next) = softplus(-s f_next) - softplus(-s f_prev)``, clamped
    at 0: finite for any finite input, where the alpha form divides by a vanishing ``Phi``.

    Args:
        sdf: (M,) signed distance at the section's middle.
        cos: (M,) the slope along the ray, :func:`annealed_cos` (``min(d . grad f, 0)`` when fully annealed).
        delta: (M,) section lengths, in the SDF's units.
        inv_s: () inverse standard deviation ``s`` of the logistic density.

    Returns:
        (M,) non-negative optical depths.
    """
    half = 0.5 * cos * delta
    prev, nxt = sdf - half, sdf + half
    return (F.softplus(-inv_s * nxt) - F.softplus(-inv_s * prev)).clamp(min=0.0)


@dataclass(frozen=True)
class SdfConfig(EncodingChoice):
    """Architecture, rendering, losses and learning rates of :class:`SdfField` (``encoding`` picks the position encoding)."""

    pos_freqs: int = 6
    """pe: octaves of the positional encoding of the position (NeuS: 6)."""
    dir_freqs: int = 4
    """Octaves of the positional encoding of the view direction (NeuS: 4)."""
    color_pos_freqs: int = 0
    """Octaves of a positional encoding of the position fed to the colour network beside ``x`` (0: ``x`` only, as NeuS), so texture need not bend the SDF's features."""
    color_grid: int = 0
    """Corners per axis of a dense feature grid over the box whose trilinear features feed the colour network (0: none, as NeuS), so a texture is stored in the grid and need not bend the SDF network's features."""
    color_grid_dim: int = 8
    """Features per corner of the colour grid."""
    color_grid_lr: float = 0.05
    """Adam learning rate of the colour grid."""
    view_dependent: bool = True
    """Feed the view direction to the colour network; False: a diffuse colour, which cannot fake a concavity's parallax (no shape-radiance ambiguity)."""
    depth: int = 4
    """Hidden layers of the SDF network."""
    width: int = 64
    """Width of the SDF network."""
    feature_dim: int = 32
    """Features the SDF network hands to the colour network."""
    color_depth: int = 2
    """Hidden layers of the colour network."""
    color_width: int = 64
    """Width of the colour network."""
    init_radius: float = 0.5
    """Radius of the sphere the geometric initialisation starts from, in box half-sides."""
    init_variance: float = 0.3
    """Initial ``variance``: the inverse standard deviation starts at ``exp(10 * init_variance)`` (NeuS: 0.3)."""
    n_samples: int = 64
    """Marching step is ``2 / n_samples`` box half-sides."""
    refine: int = 1
    """Split each marching section whose middle lies within one section length of the surface (``|f| < delta``, judged
    without gradient) into this many equal sub-sections (1: off): NeuS's up-sampling near the surface in the packed
    march's form, so a wall thinner than the step is sampled inside and stays opaque."""
    gradient: str = "auto"
    """SDF gradients: analytic (autograd), numerical (central differences) or auto (numerical for grid encodings)."""
    numerical_eps: float = 0.01
    """Step of the central differences, in box half-sides."""
    eikonal_weight: float = 0.1
    """Weight of the eikonal term (|grad f| - 1)^2 (from the end of its ramp on when ``eikonal_start_weight`` is set)."""
    eikonal_start_weight: float = -1.0
    """Eikonal weight until the start of its ramp (``eikonal_ramp`` in steps or ``eikonal_ramp_progress`` in fractions of the fit), then linear to ``eikonal_weight`` at its end (< 0: no ramp). A weak term early lets the surface change topology (carve a concavity), the full term later makes it a distance again and clears what the weak one let through."""
    eikonal_ramp: tuple[int, int] = (0, 0)
    """Steps ``[start, end]`` of the eikonal weight's ramp (see ``eikonal_start_weight``)."""
    eikonal_ramp_progress: tuple[float, float] = (0.0, 0.0)
    """The ramp as fractions ``[start, end]`` of the fit (its iterations or its time budget, whichever is further along, as the learning-rate decay), used instead of ``eikonal_ramp`` when ``end > 0``: the same schedule on a fast or a slow machine."""
    mask_weight: float = 0.1
    """Weight of the mask term (binary cross-entropy of opacity against the scene's alpha; used when rays carry alpha)."""
    curvature_weight: float = 0.0
    """Weight of the curvature term, the mean |Laplacian of f| (Neuralangelo; 0: off)."""
    shell_weight: float = 0.0
    """Weight of a thin-shell prior (0: off): the mean over a training step's samples of their logistic
    inside-probability ``sigmoid(-s f)`` (``s`` held), which moves a surface the photos barely place (a plain cup's inner
    wall) towards the inside of the solid, while the photos and the mask hold the rest. 0.005 in ``--preset concave``:
    at 15000 steps three generated mugs read 0.245 / 0.300 / 0.311 % Chamfer against 0.695 / 0.959 / 0.390 % without
    it, their inner walls within 0.36 % of the truth (BENCHMARKS.md, *Surfaces: carving concavities*, section 23). It
    empties any solid no photo asks for: under a cup carved only to a false floor, everything below it (section 25). It
    thins thin parts too: a chair's 10-minute fit read 0.318 % with it against 0.131 % without (section 24), so only
    the concave preset sets it."""
    shell_fade_progress: tuple[float, float] = (0.0, 0.0)
    """The shell prior's fade as fractions ``[start, end]`` of the fit (as ``eikonal_ramp_progress``): ``shell_weight``
    until ``start``, then linear to 0 at ``end`` (end 0: no fade). The prior pushes every surface a little inwards, the
    ones the photos hold too; without it late in the fit they go back. Measured on a plain mug with ``[0.6, 0.85]``: the
    outside back on the truth and up to +1.7 dB, but the inner wall thick again and the Chamfer worse (0.46-0.70 %
    against 0.40-0.52 %; BENCHMARKS.md, *Surfaces: carving concavities*, section 25), so no preset sets it. A model
    stepped without a planned end keeps ``shell_weight``."""
    occupancy: bool = True
    """Skip empty space with the shared occupancy grid, refreshed from |sdf| after the warm-up."""
    occupancy_resolution: int = 64
    """Occupancy grid corners per axis."""
    occupancy_margin: float = 3.0
    """A corner is occupied when ``|f|`` there is below this many grid cells plus a marching step: the band around the
    surface that is marched (narrower: fewer samples per ray, but a surface that moves faster than the refreshes may leave it)."""
    occupancy_warmup: int = 50
    """Steps before the first occupancy refresh."""
    occupancy_every: int = 25
    """Steps between occupancy refreshes."""
    occupancy_reach: float = 2.0
    """Grid cells the surface may move between full refreshes: the refreshes in between evaluate only the corners whose
    last ``|f|`` was within the band plus this reach (0: every refresh evaluates every corner)."""
    occupancy_full_every: int = 8
    """Most refreshes from one full refresh to the next. The period starts at 1 and doubles after every full refresh
    that finds no corner the narrow ones left out, and falls back to 1 after one that does."""
    lr: float = 1e-3
    """Adam learning rate of the SDF and colour networks."""
    variance_lr: float = 1e-3
    """Adam learning rate of the variance: each step moves ``s`` by at most a factor ``exp(10 variance_lr)`` (NeuS: the networks' rate)."""
    cos_anneal_iters: int = 0
    """Steps over which NeuS's cos anneal goes from soft to exact (:func:`annealed_cos`; 0: exact from the start)."""

    def __post_init__(self) -> None:
        check_fields(self, "sdf config")  # types first, then the ranges below
        checks = (
            ("pos_freqs", self.pos_freqs >= 0), ("dir_freqs", self.dir_freqs >= 0), ("color_pos_freqs", self.color_pos_freqs >= 0),
            ("color_grid", self.color_grid == 0 or self.color_grid >= 2), ("color_grid_dim", self.color_grid_dim >= 1),
            ("color_grid_lr", 0.0 < self.color_grid_lr < math.inf), ("depth", self.depth >= 1),
            ("width", self.width >= 3), ("feature_dim", self.feature_dim >= 0), ("color_depth", self.color_depth >= 1),
            ("color_width", self.color_width >= 1), ("init_radius", 0.0 < self.init_radius < 1.0),
            ("n_samples", self.n_samples >= 2), ("refine", self.refine >= 1), ("gradient", self.gradient in GRADIENTS),
            ("numerical_eps", 0.0 < self.numerical_eps < 0.5), ("eikonal_weight", self.eikonal_weight >= 0.0),
            ("eikonal_ramp", len(self.eikonal_ramp) == 2 and 0 <= self.eikonal_ramp[0] <= self.eikonal_ramp[1]),
            ("eikonal_ramp_progress", len(self.eikonal_ramp_progress) == 2
             and 0.0 <= self.eikonal_ramp_progress[0] <= self.eikonal_ramp_progress[1] <= 1.0
             and not (self.eikonal_ramp_progress[1] > 0.0 and self.eikonal_ramp[1] > 0)),  # one ramp, not two
            ("eikonal_start_weight", self.eikonal_start_weight < 0.0  # a start weight needs a ramp that some step would reach
             or self.eikonal_ramp[1] > 0 or self.eikonal_ramp_progress[1] > 0.0),
            ("mask_weight", self.mask_weight >= 0.0), ("curvature_weight", self.curvature_weight >= 0.0),
            ("shell_weight", self.shell_weight >= 0.0),
            ("shell_fade_progress", len(self.shell_fade_progress) == 2
             and 0.0 <= self.shell_fade_progress[0] <= self.shell_fade_progress[1] <= 1.0),
            ("occupancy_resolution", self.occupancy_resolution >= 2), ("occupancy_margin", self.occupancy_margin > 0.0), ("occupancy_every", self.occupancy_every >= 1),
            ("occupancy_reach", self.occupancy_reach >= 0.0), ("occupancy_full_every", self.occupancy_full_every >= 1),
            ("occupancy_warmup", self.occupancy_warmup >= 0), ("lr", 0.0 < self.lr < math.inf),
            ("variance_lr", 0.0 <= self.variance_lr < math.inf), ("cos_anneal_iters", self.cos_anneal_iters >= 0),
        )
        for name, ok in checks:
            if not ok:
                raise ConfigError(f"sdf config {name}={getattr(self, name)!r} is not allowed (nerfmeta fit --help lists the sdf fields and their ranges)")
        encoding_config(self, self.pos_freqs)  # an unknown encoding is refused here, not at build time

    @property
    def numerical(self) -> bool:
        """Whether gradients are central differences."""
        return self.gradient == "numerical" or (self.gradient == "auto" and self.encoding in GRID_ENCODINGS)


SDF_META_HINTS = MetaHints(
    model_defaults={"depth": 3, "width": 32, "feature_dim": 16, "color_width": 32, "n_samples": 32},
    fixed={"occupancy": False},
    fixed_reason="one initialisation serves many scenes, so it keeps no per-scene occupancy grid",
    inner_lr=1.0,
)
"""Meta-learning the SDF: weight-space like the NeRF MLP; no per-scene occupancy grid."""


@dataclass
class SdfSamples:
    """What the SDF network says at some points (the field's *embedding*).

    Attributes:
        sdf: (N,) signed distance, box half-sides.
        grad: (N, 3) its gradient in the box frame (unit length for a true SDF).
        feature: (N, feature_dim) features for the colour network.
        x: (N, 3) the points in the box frame.
        laplacian: (N,) the Laplacian of ``sdf`` (central differences), or None.
    """

    sdf: torch.Tensor
    grad: torch.Tensor
    feature: torch.Tensor
    x: torch.Tensor
    laplacian: torch.Tensor | None = None


class SdfField(RadianceModel):
    """NeuS-style SDF + colour backbone (see the module docstring).

    Layers, input to output: ``encoder`` (when it has parameters), ``sdf.0 .. sdf.{depth}`` (the last
    outputs ``[sdf, feature]``), ``variance``, ``color.0 .. color.{color_depth}``.
    """

    backbone = "sdf"
    meta_hints = SDF_META_HINTS

    @classmethod
    def warm_up(cls) -> None:
        """Load the fused CPU lookups of the colour grid (``color_grid``; :mod:`~nerfmeta.fields.grid_kernels`)."""
        super().warm_up()
        fused_available()

    def __init__(self, config: SdfConfig, bounds: torch.Tensor):
        super().__init__()
        if tuple(bounds.shape) != (2, 3) or not bool((bounds[1] > bounds[0]).all()):
            raise ConfigError(f"sdf bounds {bounds.tolist()} must be [min_xyz, max_xyz] with min < max on every axis")
        self.config = config
        self.register_buffer("bounds", bounds.detach().clone())
        self.encoder = build_encoding(encoding_config(config, config.pos_freqs))
        in_dim, w = self.encoder.out_dim, config.width
        dims = [in_dim] + [w] * config.depth + [1 + config.feature_dim]
        self.sdf = nn.ModuleList(nn.Linear(dims[i], dims[i + 1]) for i in range(len(dims) - 1))
        self._geometric_init(in_dim)
        self.variance = nn.Parameter(torch.tensor(float(config.init_variance)))
        dir_dim = encoding_dim(3, config.dir_freqs) if config.view_dependent else 0
        grid_dim = config.color_grid_dim if config.color_grid else 0
        if config.color_grid:
            self.color_grid = nn.Parameter(torch.zeros((grid_dim,) + (config.color_grid,) * 3, device=bounds.device))
        cdims = [encoding_dim(3, config.color_pos_freqs) + 3 + dir_dim + grid_dim + config.feature_dim] + [config.color_width] * config.color_depth + [3]
        self.color = nn.ModuleList(nn.Linear(cdims[i], cdims[i + 1]) for i in range(len(cdims) - 1))
        self.occupancy = OccupancyGrid(self._box())
        self.band = NarrowBand()
        """What the occupancy refreshes remember between calls (not saved: a loaded model starts with a full refresh)."""
        self.register_load_state_dict_post_hook(lambda module, _keys: module.band.forget())
        self.cos_anneal_ratio = 1.0
        """Fraction of the cos anneal done: set by :meth:`begin_step` (a fit), 1 for a model no fit steps (loaded, meta-learned)."""
        self.eikonal_now = config.eikonal_weight
        """The eikonal weight of the current step (:func:`ramped_weight`): set by :meth:`begin_step` (a fit), the final weight for a model no fit steps (meta-learned, pretrained), as the cos anneal."""
        self.shell_now = config.shell_weight
        """The shell prior's weight of the current step (``shell_fade_progress``): set by :meth:`begin_step`."""

    def _geometric_init(self, in_dim: int) -> None:
        """SAL/IDR's geometric initialisation: the SDF starts as a sphere of radius ``init_radius``.

        Hidden layers ``N(0, 2 / out)`` with zero bias; the first layer sees only ``x`` (weights
        on the other encoded columns zero); the last layer's SDF row ``N(sqrt(pi / in), 1e-4)``
        with bias ``-init_radius``, so ``f(x) ~ |x| - r`` through softplus(beta=100) ~ ReLU.
        """
        with torch.no_grad():
            for i, layer in enumerate(self.sdf):
                out_dim, fan_in = layer.weight.shape
                if i == len(self.sdf) - 1:
                    nn.init.normal_(layer.weight, 0.0, 1e-4)
                    layer.weight[0].normal_(math.sqrt(math.pi) / math.sqrt(fan_in), 1e-4)
                    layer.bias.zero_()
                    layer.bias[0] = -self.config.init_radius
                else:
                    nn.init.normal_(layer.weight, 0.0, math.sqrt(2.0) / math.sqrt(out_dim))
                    layer.bias.zero_()
                    if i == 0:
                        layer.weight[:, 3:in_dim].zero_()

    # -- frames --------------------------------------------------------------------------------

    def half_side(self) -> torch.Tensor:
        """() world length of one box half-side (the largest), the SDF's unit."""
        return 0.5 * (self.bounds[1] - self.bounds[0]).max()

    def to_box(self, points: torch.Tensor) -> torch.Tensor:
        """(N, 3) world points -> the isotropic box frame (the box's longest axis spans [-1, 1])."""
        return (points - 0.5 * (self.bounds[0] + self.bounds[1])) / self.half_side()

    def _box(self) -> torch.Tensor:
        """(2, 3) the cube (in world) that the box frame's [-1, 1]^3 covers: marched by the estimator."""
        centre, h = 0.5 * (self.bounds[0] + self.bounds[1]), self.half_side()
        return torch.stack([centre - h, centre + h])

    # -- the SDF -------------------------------------------------------------------------------

    def sdf_and_feature(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Signed distance (N,) and features (N, feature_dim) at box-frame points (N, 3)."""
        out = self._mlp(self.encoder(x))
        return out[:, 0], out[:, 1:]

    def _mlp(self, encoded: torch.Tensor, slopes: list[torch.Tensor] | None = None) -> torch.Tensor:
        """The SDF network on encoded points: (N, 1 + feature_dim); appends each hidden layer's softplus slope
        ``sigmoid(SOFTPLUS_BETA z)`` to ``slopes`` when given (for :meth:`_sdf_with_gradient`)."""
        h = encoded
        for layer in self.sdf[:-1]:
            z = layer(h)
            h = F.softplus(z, beta=SOFTPLUS_BETA)
            if slopes is not None:
                slopes.append(torch.sigmoid(SOFTPLUS_BETA * z))
        return self.sdf[-1](h)

    def inv_s(self) -> torch.Tensor:
        """() the logistic density's inverse standard deviation ``exp(10 * variance)``, at most 1e6."""
        return torch.exp(10.0 * self.variance).clamp(max=1e6)

    def evaluate(self, x: torch.Tensor, *, laplacian: bool = False) -> SdfSamples:
        """SDF, gradient and features at box-frame points (N, 3) (graph kept when grad mode is on)."""
        cfg = self.config
        if cfg.numerical or laplacian:
            return self._numerical(x, cfg.numerical_eps, laplacian)
        graph = torch.is_grad_enabled()
        with torch.enable_grad():
            xg = x.detach().requires_grad_(True)
            if graph:
                sdf, feature, grad = self._sdf_with_gradient(xg)
                return SdfSamples(sdf, grad, feature, x)
            sdf, feature = self.sdf_and_feature(xg)
            (grad,) = torch.autograd.grad(sdf.sum(), xg)
        return SdfSamples(sdf.detach(), grad, feature.detach(), x)

    def _sdf_with_gradient(self, xg: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """SDF, features and ``grad f`` at ``xg`` (requires grad), all differentiable in the parameters (for the eikonal term).

        The same values as :meth:`sdf_and_feature` and autograd's ``create_graph`` gradient, faster: the MLP's part of the
        chain rule is written out, ``df/dh_0 = w^T diag(sigmoid(SOFTPLUS_BETA z_k)) W_k ...`` (softplus' derivative is that sigmoid),
        so the outer backward never differentiates softplus' backward (a profile of the concave-object recipe on a CPU: 8 %
        less time per step); autograd does only the encoding's part.
        """
        encoded, slopes = self.encoder(xg), []
        out = self._mlp(encoded, slopes)
        g = self.sdf[-1].weight[0].expand(xg.shape[0], -1)
        for layer, slope in zip(reversed(self.sdf[:-1]), reversed(slopes)):
            g = (g * slope) @ layer.weight
        (grad,) = torch.autograd.grad(encoded, xg, grad_outputs=g, create_graph=True)
        return out[:, 0], out[:, 1:], grad

    def _numerical(self, x: torch.Tensor, eps: float, laplacian: bool) -> SdfSamples:
        """Finite-difference gradient: from the 4 vertices ``x + eps v_k`` of a tetrahedron (``sum v_k = 0``,
        ``sum v_k v_k^T = 4 I``, so ``grad = sum_k v_k f(x + eps v_k) / (4 eps)``, exact for linear ``f``), or, with
        the Laplacian, central differences at ``x +- eps e_i`` (6 more evaluations)."""
        n = x.shape[0]
        if not laplacian:
            v = torch.tensor(TETRAHEDRON, dtype=x.dtype, device=x.device)
            sdf_all, feature_all = self.sdf_and_feature(torch.cat([x, (x[None] + eps * v[:, None]).reshape(-1, 3)]))
            around = sdf_all[n:].reshape(4, n)
            grad = (v[:, None, :] * around[..., None]).sum(0) / (4.0 * eps)
            return SdfSamples(sdf_all[:n], grad, feature_all[:n], x)
        offsets = torch.cat([torch.eye(3, dtype=x.dtype, device=x.device), -torch.eye(3, dtype=x.dtype, device=x.device)]) * eps
        around = (x[None] + offsets[:, None]).reshape(-1, 3)
        sdf_all, feature_all = self.sdf_and_feature(torch.cat([x, around]))
        sdf, feature = sdf_all[:n], feature_all[:n]
        plus, minus = sdf_all[n:].reshape(6, n)[:3], sdf_all[n:].reshape(6, n)[3:]
        grad = ((plus - minus) / (2.0 * eps)).t()
        lap = ((plus + minus).sum(0) - 6.0 * sdf) / eps**2 if laplacian else None
        return SdfSamples(sdf, grad, feature, x, lap)

    def sdf_world(self, points: torch.Tensor) -> torch.Tensor:
        """(N,) signed distance in world units at world points (N, 3)."""
        return self.sdf_and_feature(self.to_box(points))[0] * self.half_side()

    # -- the field interface -------------------------------------------------------------------

    def get_density(self, points: torch.Tensor) -> tuple[torch.Tensor, SdfSamples]:
        """NeuS's density ``s * sigmoid(-s f) * |cos| ~ s * sigmoid(-s f)`` per world unit (for estimators and meshes of density)."""
        ev = self.evaluate(self.to_box(points))
        s = self.inv_s()
        return s * torch.sigmoid(-s * ev.sdf) / self.half_side(), ev

    def get_outputs(self, embedding: SdfSamples, sel: torch.Tensor | None, directions: torch.Tensor,
                    ray_idx: torch.Tensor) -> torch.Tensor:
        """Colour (K, 3) from ``[encoded x, normal, encoded view direction, colour-grid features, feature]`` of the points
        ``sel`` (no direction unless ``view_dependent``; ``x`` itself when ``color_pos_freqs`` is 0; grid features when
        ``color_grid`` is on)."""
        ev = embedding
        x, grad, feature = (ev.x, ev.grad, ev.feature) if sel is None else (ev.x[sel], ev.grad[sel], ev.feature[sel])
        parts = [positional_encoding(x, self.config.color_pos_freqs), F.normalize(grad, dim=-1)]
        if self.config.view_dependent:
            parts.append(positional_encoding(directions.index_select(0, ray_idx).to(x.dtype), self.config.dir_freqs))
        if self.config.color_grid:
            parts.append(interp_points(self.color_grid, x.detach(), UNIT_BOX.to(x)))
        h = torch.cat(parts + [feature], dim=-1)
        for layer in self.color[:-1]:
            h = F.relu(layer(h))
        return torch.sigmoid(self.color[-1](h))

    def sample(self, rays: RayBatch, *, train: bool, generator: torch.Generator | None) -> SamplingPlan:
        """March the box every ``2 / n_samples`` half-sides, skipping cells the occupancy grid marks empty; with ``refine``,
        split the sections near the surface."""
        n, dtype, device = len(rays), rays.origins.dtype, rays.origins.device
        if train:
            jitter = torch.rand(n, generator=generator, dtype=dtype, device="cpu").to(device)
        else:
            jitter = torch.full((n,), 0.5, dtype=dtype, device=device)
        step = float(2.0 / self.config.n_samples * self.half_side())
        samples = self.occupancy.sampling(rays.origins, rays.directions, rays.near, rays.far, step=step, jitter=jitter)
        if self.config.refine > 1 and len(samples):
            with torch.no_grad():
                sdf = self.sdf_and_feature(self.to_box(samples.points(rays.origins, rays.directions)))[0]
            samples = split_sections(samples, sdf.abs() < samples.delta / self.half_side(), self.config.refine)
        return SamplingPlan(samples)

    def render(self, rays: RayBatch, *, background: torch.Tensor, train: bool = False,
               generator: torch.Generator | None = None, view_dirs: torch.Tensor | None = None) -> RenderOutput:
        """Estimator, SDF to optical depth (:func:`neus_tau`), shared compositor; extras ``grad``, ``laplacian``."""
        samples = self.sample(rays, train=train, generator=generator).samples
        ev = self.evaluate(self.to_box(samples.points(rays.origins, rays.directions)),
                           laplacian=train and self.config.curvature_weight > 0.0)
        d = rays.directions.index_select(0, samples.ray_idx).to(ev.grad.dtype)
        cos = annealed_cos((d * ev.grad).sum(-1), self.cos_anneal_ratio)
        inv_s = self.inv_s()
        tau = neus_tau(ev.sdf, cos, samples.delta / self.half_side(), inv_s)
        directions = rays.directions if view_dirs is None else view_dirs
        comp = render_packed(tau, samples.t, samples.ray_idx, samples.far, background,
                             lambda sel, ray_idx: self.get_outputs(ev, sel, directions, ray_idx))
        extras = {"grad": ev.grad}
        if ev.laplacian is not None:
            extras["laplacian"] = ev.laplacian
        if train and self.shell_now > 0.0:
            extras["inside"] = torch.sigmoid(-inv_s.detach() * ev.sdf)
        return RenderOutput(rgb=comp.rgb, acc=comp.acc, depth=comp.depth, samples_evaluated=len(samples), extras=extras)

    def forward(self, rays: RayBatch, *, background: torch.Tensor, train: bool = False,
                generator: torch.Generator | None = None, target: torch.Tensor | None = None) -> RenderOutput:
        """:meth:`RadianceModel.forward` plus the ``mask`` term when the rays carry the scene's alpha."""
        out = super().forward(rays, background=background, train=train, generator=generator, target=target)
        alpha = getattr(rays, "alpha", None)
        if target is not None and alpha is not None and self.config.mask_weight > 0.0:
            acc = out.acc.clamp(1e-3, 1.0 - 1e-3)
            out.losses["mask"] = self.config.mask_weight * F.binary_cross_entropy(acc, alpha.to(acc.dtype))
        return out

    def loss_terms(self, out: RenderOutput, target: torch.Tensor) -> dict[str, torch.Tensor]:
        """``mse``, ``eikonal`` and, when on, ``curvature`` and ``shell`` (see the module docstring)."""
        cfg = self.config
        terms = {"mse": photometric_mse(out.rgb, target)}
        grad = out.extras["grad"]
        if grad.shape[0] and self.eikonal_now > 0.0:
            terms["eikonal"] = self.eikonal_now * ((grad.norm(dim=-1) - 1.0) ** 2).mean()
        if "laplacian" in out.extras and out.extras["laplacian"].shape[0]:
            terms["curvature"] = cfg.curvature_weight * out.extras["laplacian"].abs().mean()
        if "inside" in out.extras and out.extras["inside"].shape[0]:
            terms["shell"] = self.shell_now * out.extras["inside"].mean()
        return terms

    # -- structure -----------------------------------------------------------------------------

    def begin_step(self, step: int, progress: float | None) -> StepEvent:
        """Advance the cos anneal, the eikonal ramp and the shell fade; refresh the occupancy grid every ``occupancy_every`` steps after the warm-up:
        a corner is occupied when the surface may be within ``occupancy_margin`` cells (``|f| < margin cells + a marching step``)."""
        cfg = self.config
        self.cos_anneal_ratio = min(1.0, step / cfg.cos_anneal_iters) if cfg.cos_anneal_iters else 1.0
        self.eikonal_now = self._eikonal_weight_at(step, progress)
        fade = cfg.shell_fade_progress
        self.shell_now = cfg.shell_weight if fade[1] <= 0.0 or progress is None else ramped_weight(progress, cfg.shell_weight, 0.0, fade)
        if not cfg.occupancy or step < cfg.occupancy_warmup or (step - cfg.occupancy_warmup) % cfg.occupancy_every:
            return StepEvent()
        self._refresh_occupancy()
        message = f"occupancy grid refreshed: {100 * self.occupancy.occupied_fraction():.1f}% near the surface" \
            if step == cfg.occupancy_warmup else ""
        return StepEvent(False, message)

    @torch.no_grad()
    def _refresh_occupancy(self) -> None:
        """Mark the corners where ``|f|`` is below the band (``occupancy_margin`` cells plus a marching step), dilated by
        one cell. A full refresh evaluates every corner; the ones between (see ``occupancy_full_every``) only the corners
        whose last ``|f|`` was within the band plus ``occupancy_reach`` cells, the others keeping their marks (unmarked)."""
        cfg = self.config
        size = (cfg.occupancy_resolution,) * 3
        cell = 2.0 / (cfg.occupancy_resolution - 1)  # box half-sides
        band = cfg.occupancy_margin * cell + 2.0 / cfg.n_samples
        limit = band + cfg.occupancy_reach * cell
        band_state = self.band
        if band_state.corners is None:
            band_state.corners = self.to_box(grid_points(self.occupancy.aabb, size).reshape(-1, 3))
        full = band_state.distance is None or cfg.occupancy_reach <= 0.0 or band_state.since_full + 1 >= band_state.period
        distance, evaluated = values_near(lambda x: self.sdf_and_feature(x)[0].abs(), band_state.corners,
                                          None if full else band_state.distance, limit)
        band_state.record(distance, evaluated, full, band, limit, cfg.occupancy_full_every)
        self.occupancy.mark(dilate((distance < band).view(size), 1))

    def _eikonal_weight_at(self, step: int, progress: float | None) -> float:
        """The eikonal weight of ``step`` (:func:`ramped_weight`): on the progress axis when the ramp is set in
        fractions of the fit (the final weight where no fit gives a progress), else on the step axis."""
        cfg = self.config
        if cfg.eikonal_ramp_progress[1] > 0.0:
            if progress is None:
                return cfg.eikonal_weight
            return ramped_weight(progress, cfg.eikonal_start_weight, cfg.eikonal_weight, cfg.eikonal_ramp_progress)
        return ramped_weight(step, cfg.eikonal_start_weight, cfg.eikonal_weight, cfg.eikonal_ramp)

    def structure(self) -> dict[str, Any]:
        return {"occupancy_shape": list(self.occupancy.size)}

    def load_structure(self, structure: dict[str, Any]) -> None:
        if "occupancy_shape" in structure:
            self.occupancy.binaries = torch.zeros(structure["occupancy_shape"], dtype=torch.bool, device=self.bounds.device)

    def layers(self) -> list[Layer]:
        def of(name: str) -> Layer:
            return Layer(name, tuple(f"{name}.{p}" for p, _ in self.get_submodule(name).named_parameters()))

        first = [of("encoder")] if any(True for _ in self.encoder.parameters()) else []
        grid = [Layer("color_grid", ("color_grid",))] if self.config.color_grid else []
        return (first + [of(f"sdf.{i}") for i in range(len(self.sdf))] + [Layer("variance", ("variance",))]
                + grid + [of(f"color.{i}") for i in range(len(self.color))])

    def param_groups(self) -> list[ParamGroup]:
        names = tuple(n for n, _ in self.named_parameters())
        enc = tuple(n for n in names if n.startswith("encoder."))
        groups = [ParamGroup("sdf", tuple(n for n in names if n not in enc and n not in ("variance", "color_grid")), self.config.lr),
                  ParamGroup("variance", ("variance",), self.config.variance_lr)]
        if self.config.color_grid:
            groups.append(ParamGroup("color_grid", ("color_grid",), self.config.color_grid_lr))
        return groups + [ParamGroup("encoding", enc, self.config.encoding_lr)] if enc else groups
