"""A DirectVoxGO-style voxel-grid backbone in pure PyTorch (CPU and CUDA).

Two stages, as in DirectVoxGO (Sun et al., CVPR 2022):

1. **Coarse** (``coarse_iters`` steps): a density grid and a direct RGB grid (``sigmoid`` of three
   logits per voxel) over the scene box. It finds the occupied region: the fine box is the
   bounding box of the voxels whose coarse alpha exceeds ``bbox_thres``, padded by a voxel and
   scaled by ``world_bound_scale``; the fine stage's occupancy (mask) cache starts as the fine
   voxels whose coarse alpha exceeds ``mask_cache_thres``, dilated by two voxels.
2. **Fine**: a density grid and a feature grid in the tightened box. Colour is
   ``sigmoid(diffuse + mlp(features, view))`` (DirectVoxGO's non-direct colour head): the feature
   grid holds 3 diffuse logits plus ``feature_dim`` channels that a shallow MLP decodes with the
   encoded view direction; the MLP's last layer starts at zero. With ``view_dependent="auto"`` (the
   default, see the field's note) this is a per-scene trial: ``view_probe_step`` steps into the fine stage,
   :meth:`VoxelGrid.decide` measures on training rays how much lower the error is with the view
   direction than with the MLP's output averaged over training directions; when that gain is below
   ``view_gain_db`` the direction-averaged MLP is folded into the diffuse colour and the MLP and its
   feature channels are dropped (the rest of the fit then steps about twice as fast). The fine stage starts from the
   coarse one (density converted through world units, diffuse logits copied), so switching stages
   keeps the picture. The grids grow progressively: ``num_voxels / 2**len(growth_steps)`` voxels
   at first, doubling at each of ``growth_steps`` (fine-stage steps), resampled trilinearly (or the density
   L2-projected, ``growth_density``); a growth
   falling due after ``growth_cutoff`` of the fit's length is skipped (too late to pay for itself). The
   occupancy cache is refreshed every ``occupancy_every`` fine steps: voxels whose alpha fell
   below ``mask_cache_thres`` (dilated by one voxel) leave it. An optional total-variation loss
   (``tv_weight``) smooths the fine density.

Density is *post-activated*: the raw grid is interpolated first and only then passed through
``softplus(raw + shift)``, which lets a trilinear grid represent sharp surfaces inside a voxel.
``shift`` is chosen so that raw 0 gives alpha ``alpha_init`` (``coarse_alpha_init``) over one step
of ``stepsize`` voxels (DirectVoxGO's shifted softplus). Densities are in units of 1/``unit``,
``unit`` being the voxel side of the fully grown grid of the current stage (``tau = sigma * delta
/ unit``), so growing the grid does not change what a raw value means.

Rendering goes through the shared pipeline (:class:`~nerfmeta.fields.base.RadianceModel`): the
occupancy-grid estimator (:class:`~nerfmeta.render.estimators.OccupancyGrid`, whose grid *is*
the fine stage's occupancy cache) marches every ``stepsize`` voxels through the box in a packed
layout and drops samples whose nearest cache voxel is off before anything is evaluated
(``empty_space_skipping``; what remains is ``RenderOutput.samples_evaluated``); the shared
compositor (:func:`~nerfmeta.render.volume.render_packed`) asks for colour only where a sample's
compositing weight exceeds ``fast_color_thres`` (``coarse_fast_color_thres`` in the coarse stage). Training
lookups on a CPU use the fused kernels of :mod:`~nerfmeta.fields.grid_kernels` (numba: a sample's corners,
weights and values in one compiled loop, its gradient scattered in another; the embedding is then the corner
coordinates), elsewhere, or without numba, :func:`~nerfmeta.fields.grid_ops.trilinear_gather`: corner indices and weights
computed once per sample, a gather forward and an ``index_add_`` backward. Test-time renders on a CPU look up the
density grid and colour grids of up to :data:`FUSED_RENDER_MAX_CHANNELS` channels with the same fused kernels;
other test-time lookups (no gradient) use one fused ``grid_sample`` per grid instead (:func:`~nerfmeta.fields.grid_ops.interp_coords`,
on channels-last copies of the colour grids, made once per whole-view render, :meth:`VoxelGrid.render_session`,
not per chunk): the same values, 1.8x the rays per second on a contracted beer frame
and 1.1-1.2x on lego (BENCHMARKS.md, *Faster test renders*).
An optional distortion loss (``distortion_weight``, mip-NeRF 360) gathers each ray's weight. What a ray meets after
everything the grid holds can be learned (``background_map``: a table of colours by ray direction added to the fixed
background colour, :mod:`nerfmeta.render.background`; one row on forward-facing and unbounded scenes).

Defaults: DirectVoxGO's, except where a 60-second budget on a 2-core CPU asked otherwise (each
measured on lego at 100 x 100, see BENCHMARKS.md): a 100-step coarse stage (DirectVoxGO: 5000)
with a 3x higher density learning rate, a ``bbox_thres`` of 0.1 (1e-3 after a short coarse stage
counts faint floaters, doubling the box), a 6-channel feature grid and a 32-wide MLP (12 and 128),
and colour decoded only above weight 1e-3 (1e-4). ``num_voxels = 0`` and ``coarse_num_voxels =
0`` mean "auto": :meth:`VoxelGridConfig.for_scene` sizes them from the image resolution.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import Any, Callable, ClassVar, ContextManager

import torch
import torch.nn.functional as F
from torch import nn

from nerfmeta.config import check_fields
from nerfmeta.data.scene import RayBatch, Scene
from nerfmeta.errors import ConfigError
from nerfmeta.fields.base import Decision, Layer, MetaHints, ParamGroup, RadianceModel, RenderOutput, SamplingPlan, StepEvent
from nerfmeta.fields.encoding import encoding_dim, positional_encoding
from nerfmeta.fields.grid_kernels import fused_available, fused_for, trilinear_coords
from nerfmeta.fields.grid_ops import (
    ChannelsLastCopies,
    corners_from_coords,
    grid_coords,
    grid_points,
    interp_cf,
    interp_coords,
    project_cf,
    resample_cf,
    take_columns,
    total_variation,
    trilinear_gather,
    voxel_layout,
)
from nerfmeta.data.scene_type import focus_point, view_directions
from nerfmeta.render.background import clamp_inward, equirect_lookup
from nerfmeta.render.contraction import InnerBox, inner_box_from_cameras, to_march
from nerfmeta.render.estimators import OccupancyGrid, PackedSamples, contracted_interval, evaluate_in_chunks
from nerfmeta.render.volume import Composite, packed_distortion, softplus_shift_for_alpha

FUSED_RENDER_MAX_CHANNELS = 3
"""Test-time renders on a CPU look up colour grids of at most this many channels with the fused kernels
(:mod:`~nerfmeta.fields.grid_kernels`; the density grid always): faster than ``grid_sample`` on a channels-last
copy for 1 and 3 channels, slower for the MLP's 9 (BENCHMARKS.md, *Fused grid lookups*)."""

AUTO_VOXELS_PER_PIXEL = 0.88
"""Auto fine grid: voxels per axis per pixel of the larger image side (88^3 for 100x100 views)."""
AUTO_MAX_SIDE = 160
"""Auto fine grid: at most 160^3 voxels (DirectVoxGO's NeRF-synthetic setting, for 800x800)."""
AUTO_MIN_SIDE = 16
"""Auto fine grid: at least 16^3 voxels."""
AUTO_COARSE_RATIO = 0.5
"""Auto coarse grid: voxels per axis as a fraction of the fine grid's (44^3 for 88^3)."""

DENSITY_ADAM_EPS = 1e-15
"""Adam's epsilon for the density grids (declared by their parameter groups; Instant-NGP's value).

A post-activated density ``softplus(raw + shift)`` has gradient ``sigmoid(raw + shift)`` in ``raw``,
which at the start is about the initial alpha per step, so the density grid's gradients shrink in
proportion to ``alpha_init``: on the tiny scene at alpha 1e-6 they are 1e-10 (median) to 1e-8 (max)
per voxel, and Adam's ``g / (sqrt(v) + eps)`` with eps 1e-8 moves a voxel a few percent of its
learning rate per step (the raw density rose 0.5 in 100 steps instead of 3.9). With 1e-15 the step
is scale-free again. The other groups keep the fit's ``adam_eps``: a tiny epsilon on the colour grid
and MLP cost 1.5 dB at alpha 1e-4 (noisy low-gradient voxels then take full steps), on the density
alone it cost nothing."""

GROWTH_MODES = ("interp", "project")
"""The ways the density grid moves onto a grown lattice (``VoxelGridConfig.growth_density``)."""


def growth_mode(spec: str, growth: int) -> str:
    """The way of growth number ``growth`` (0 the first) in a ``growth_density`` spec: one mode for every growth, or a
    comma-separated list, one per growth, whose last entry stands for every growth after it."""
    modes = spec.split(",")
    return modes[min(growth, len(modes) - 1)]


GRID_META_HINTS = MetaHints(
    algos=("fomaml", "reptile"),
    why_not="--algo maml needs second-order gradients, which the grid backbone does not support (grid "
            "Hessian-vector products over a dense grid would cost several times a first-order step); "
            "use --algo fomaml or --algo reptile",
    model_defaults={"num_voxels": 40**3, "feature_dim": 6, "mlp_width": 32, "mlp_depth": 2,
                    "view_dependent": True},  # fixed: "auto" would add the MLP mid-fit, changing the parameter set
    fixed={"coarse_iters": 0, "growth_steps": (), "empty_space_skipping": False, "occupancy_every": 0},
    fixed_reason="meta-learning uses the grid in one fixed fine stage",
    inner_lr=10.0,
    # The loss is a mean over the support rays, so a voxel's gradient is tiny (each voxel is touched by
    # few of the rays): the grids need rates ~1e4 times the decoder MLP's; measured on a 16-32 px
    # collection, where they lower the support MSE several-fold in 8 steps without diverging.
    inner_group_lr={"density": 1e5, "features": 3e4},
)
"""Meta-learning the grid: first order only, in one fixed fine stage (no coarse stage, no growth, no
empty-space skipping) so its parameter set never changes."""


FORWARD_DEFAULTS: dict[str, Any] = {"coarse_iters": 50, "coarse_alpha_init": 1e-2, "stepsize": 1.0,
                                    "voxels_per_pixel": 0.25, "max_side": 64, "lr_density": 0.3, "render_phases": 2,
                                    "background_map": 1}
"""Defaults for a forward-facing scene fitted in NDC (``--set`` still overrides them).

- ``voxels_per_pixel`` 0.25 (DirectVoxGO's LLFF ratio: 256^3 voxels for 1008-pixel-wide images; 40^3 at
  160 x 120 instead of 141^3). NDC's x and y are image coordinates, so a grid about as fine as the pixels
  is finer than the parallax a capture's few centimetres give: with it the fit painted each training view
  onto fog in front of everything (expected depth 1.25 world units where the nearest object is at 1.6 and
  the wall at 16) and scored 20.9 dB on held-out views; at 0.25 it drew the wall where it is and scored
  27-29 dB (ranking runs, BENCHMARKS.md #16 session 6). 0.19 and 0.375 did about as well on one layout,
  0.375 2 dB worse on the other.
- ``max_side`` 64: the grid no finer than 64 voxels across, whatever the images' size. The parallax a capture gives
  does not grow with its pixels: at LLFF's 504 x 378 (0.25 would give 126) two generated layouts at 2000 steps
  scored best at 45-96 voxels across (scene A: 32 / 45 / 63 / 96 / 126 / 189 voxels: 32.7 / 34.8 / 35.3 / 34.2 /
  31.2 / 28.6 dB; layout 2: 28.2 / 27.6 / 27.6 / 27.9 / 26.5 / 24.9), and 64 made the user's 120-s fit of scene A
  36.2 dB instead of 31.3, its steps twice as fast, layout 2's 27.8 instead of 26.4, and layout 3's (not used to
  choose it) 28.4 instead of 27.6 (BENCHMARKS.md #16 session 47). At 160 x 120 (40 across) nothing changes.
- ``lr_density`` 0.3 (0.1 for objects): +1.7 dB at equal steps on both generated layouts.
- Every ray ends on something (no blank background), so the coarse grid starts a third opaque along a ray
  (alpha 1e-2 a step) rather than clear (from 1e-4 the first 30 steps render mostly the background), 50
  coarse steps find where the content is, and a step is one voxel as in DirectVoxGO's LLFF config.
- ``render_phases`` 2: with one-voxel steps a test render at the bins' middles shows the field's aliasing (see
  the field's documentation).
- ``background_map`` 1: what shows through where the grid is not opaque is a learned colour (two, blended round
  the horizon), not the fixed white, which no real capture has behind it. At 504 x 378 and 2000 fixed steps: scene
  A 36.92 dB against 35.51, layout 2 30.96 against 27.42, layout 3 32.84 against 27.86 (with the white, the view
  trial read the white's mismatch as view dependence and kept the MLP on layouts 2 and 3: steps 2.5x as slow); at
  160 x 120, 1500 steps, scenes A and B +0.78 and +1.24 dB (BENCHMARKS.md #16 session 48).

Tried and left off (ranking runs): total variation on the density (1e-3 and 1e-1: no change, 1.0: worse)
and on the features (``tv_features_weight`` 1e-2: no change)."""


UNBOUNDED_DEFAULTS: dict[str, Any] = {"stepsize": 1.0, "render_phases": 2, "background_map": 1}
"""Defaults for an unbounded capture (cameras around a subject, a real background) fitted in a contracted space.

(``view_dependent``: the field's default, the per-scene trial ``"auto"``, was decided for these captures first, in
session 26, and for every scene since session 43, rather than the MLP always: every ray of such a capture
ends on something, so most of its samples carry weight and are colour-decoded (beer at 178 x 316, grown grid:
about 490k decoded samples a 4096-ray step, 60 % of those marched), and the MLP's products and their backward are
most of a CPU step. On beer the view input lowered the training error by 0.07 dB, the trial dropped the MLP and
the 120-s fit made 578-601 steps instead of about 375: +0.28 dB on its nine held-out frames (median of three, 27.47
against 27.19), LPIPS 0.36 against 0.40, a visibly sharper walk video and test renders as fast (62k rays/s against
61k; BENCHMARKS.md, #16 session 26). A capture whose view dependence pays (glossy paint, glass) keeps the MLP;
``--set view_dependent=true`` keeps it always. A transfer fit keeps its saved model's setting, and a resumed run the
setting it was started with (its ``config.json`` holds the whole model config).)

``stepsize`` 1.0 (one sample a voxel, DirectVoxGO's LLFF step; its unbounded config marches half voxels): on a CPU
the walk video's sharpness is a matter of steps (a GPU fit of beer went from soft at 360 steps to sharp at
1000-2000), and half the samples a ray make each step about 1.6x as fast. On beer's 120-s fit: 924-951 steps instead
of 563-574, 27.56 dB on the nine held-out frames instead of 27.43 (medians of three), LPIPS 0.32 against 0.36, a
visibly sharper walk, and test renders at 106k rays/s instead of 62k (103 samples a ray instead of 203;
BENCHMARKS.md, #16 session 27). Measured on beer only (the one unbounded capture here), on this CPU only.

``render_phases`` 2: as for forward-facing scenes (one-voxel steps).

``background_map`` 1: what a ray meets after the whole contracted space is a learned colour (two, blended round the
horizon), not the fixed white, which a third of beer's light came from (light tiles and walls left half transparent).
On beer's 120-s fit 28.66-28.79 dB on the nine held-out frames against 27.41-27.55 (three seeds), LPIPS 0.25 against
0.33, more steps in the time (1121-1179 against 867-948) and faster test renders (63k rays/s against 52-57k, 145
samples a ray against 207); at fixed steps on a generated room 26.85 dB against 22.27. Finer tables did worse on both
(beer at 16 rows 28.16, at 128 26.60; BENCHMARKS.md #16 session 48)."""


@dataclass(frozen=True)
class VoxelGridConfig:
    """Voxel-grid backbone settings (defaults tuned for ~100x100 views on a 2-core CPU)."""

    scene_type_defaults: ClassVar[dict[str, dict[str, Any]]] = {"forward": FORWARD_DEFAULTS,
                                                                 "unbounded": UNBOUNDED_DEFAULTS}
    """Defaults that differ by kind of scene (:mod:`nerfmeta.data.scene_type`), applied before ``--set``."""

    coarse_iters: int = 100
    """Steps of the coarse stage before the fine stage starts (0 skips the coarse stage: the fine stage uses the scene box and no mask)."""
    coarse_num_voxels: int = 0
    """Voxels in the coarse grids (0: auto, see ``for_scene``)."""
    coarse_alpha_init: float = 1e-4
    """Alpha of one coarse step at raw density 0 (keep it below ``bbox_thres`` so unseen voxels do not count as occupied)."""
    num_voxels: int = 0
    """Voxels in the fine grids once fully grown (0: auto from the image resolution, see ``for_scene``)."""
    alpha_init: float = 1e-2
    """Alpha of one fine step at raw density 0."""
    feature_dim: int = 6
    """Channels of the fine feature grid fed to the MLP (3 diffuse-colour channels come on top)."""
    mlp_width: int = 32
    """Width of the colour MLP."""
    mlp_depth: int = 3
    """Linear layers in the colour MLP (>= 1)."""
    view_dependent: bool | str = "auto"
    """Decode view-dependent colour with the MLP (True), keep the diffuse colour alone (False: no MLP, 3 feature channels), or ``"auto"`` (the default): decide per scene, ``view_probe_step`` steps into the fine stage, whether the MLP's view input lowers the training error by at least ``view_gain_db``; if not, fold the MLP into the diffuse colour and drop it. Since the fused kernels (sessions 37-41) the MLP is most of an object fit's step: where the trial drops it, 1000-step fits of generated 64 and 128 px objects took 0.5-0.7x the time and ended 0.2 dB lower at most (table 0.20, chair 0.10-0.16, vase 0.00-0.11, car and sofa within 0.03), and in a 20-s budget ended +0.05..+0.52 dB higher (table -0.14..-0.20); it kept the MLP on the metal-shaded lamps and lego, which need it (BENCHMARKS.md, *The colour MLP decided per scene by default*). With few views the trial over-reads the MLP's gain (it measures training error: 1.2 dB on a 16-view chair against 0.25 on its 40-view twin) and keeps it. ``true`` keeps it always (the default before session 43)."""
    view_probe_step: int = 100
    """``auto``: fine-stage step at which the view dependence is measured (the fine stage has the MLP until then)."""
    view_gain_db: float = 0.45
    """``auto``: keep the MLP when its view input lowers the training MSE by at least this (dB) against its output averaged over training directions (measured at the trial's end: 0.07-0.33 dB on diffuse generated scenes, 0.76-1.42 dB on specular ones, 0.58-0.64 dB on lego in session 8; in session 43 0.09-0.44 on the generated objects the trial dropped it on, 0.77-1.75 on those it kept it on, 0.65 on lego; see BENCHMARKS.md)."""
    view_probe_rays: int = 16384
    """``auto``: training rays rendered to measure the gain."""
    view_probe_dirs: int = 4
    """``auto``: training directions the MLP's output is averaged over (in the measurement and in the fold)."""
    dir_freqs: int = 4
    """Frequencies of the view-direction encoding."""
    stepsize: float = 0.5
    """Distance between samples along a ray, in voxels of the current grid (1.0 on forward-facing and unbounded scenes, see their defaults)."""
    bbox_thres: float = 0.1
    """Coarse alpha above which a voxel counts as occupied when tightening the fine box (DirectVoxGO uses 1e-3 after a 5000-step coarse stage; a short one leaves faint floaters that such a low value would count)."""
    mask_cache_thres: float = 1e-3
    """Alpha above which a voxel stays in the occupancy cache."""
    coarse_fast_color_thres: float = 1e-5
    """Coarse samples with a smaller compositing weight are not colour-decoded (DirectVoxGO: a tenth of the initial alpha)."""
    fast_color_thres: float = 1e-3
    """Fine samples with a smaller compositing weight are not colour-decoded."""
    empty_space_skipping: bool = True
    """Skip samples in voxels the occupancy cache marks empty (switch off to compare)."""
    tighten_box: bool = True
    """Shrink the fine stage's box to the region the coarse stage found occupied (switch off to compare: the fine grid spans the scene box)."""
    occupancy_every: int = 100
    """Fine steps between occupancy-cache pruning (0: never prune)."""
    growth_steps: tuple[int, ...] = (100, 200, 300)
    """Fine-stage steps at which the grids double their voxel count."""
    growth_density: str = "interp"
    """How the density grid moves onto the grown lattice at each growth: ``interp`` (trilinear resampling at the new
    corners, as DirectVoxGO does) or ``project`` (the L2 projection of its field, :func:`~nerfmeta.fields.grid_ops.project_cf`),
    one way for every growth or a comma-separated list, one per growth in order, its last entry standing for the
    growths after it (``project,interp``: the first growth projected, the rest interpolated; :func:`growth_mode`). The
    feature grid is always interpolated. Interpolation smooths the density's surfaces (the new lattice is not nested in
    the old), which is most of the growth's dip: on a generated 128 px table the test PSNR fell 1.04 dB at the first
    growth and was still 0.28 dB down 25 steps later; projected, it does not fall. But the smoothing pays later: from
    a learned start, 1000-step fits ended lower with every growth projected on all 11 scenes of a generated collection
    (BENCHMARKS.md, *The growth dip is the density's interpolation*); with the first growth alone projected, 0.04 dB
    lower on average and scratch's final reached no sooner (median, *Only the first growth projected*). So
    ``interp`` stays the default."""
    growth_cutoff: float = 0.7
    """A growth falling due after this fraction of the fit's length (its iterations or time budget) is skipped, with
    the ones after it: a grid grown that late has too few steps left to use its new voxels, and each step and every
    later render costs more (1: never skipped). On beer's 120-s CPU fit the second growth falls due at 77-80 % of the
    time (steps after a growth are slower, so that is about 88 % of the steps): skipped, +0.10 dB and 25 % fewer
    samples per test ray (BENCHMARKS.md #16, session 25); 0.8 kept it on a faster day."""
    world_bound_scale: float = 1.05
    """Scale of the tightened fine box about its centre."""
    coarse_lr_density: float = 0.3
    """Learning rate of the coarse density grid."""
    lr_density: float = 0.1
    """Learning rate of the fine density grid."""
    lr_features: float = 0.1
    """Learning rate of the colour/feature grids."""
    lr_mlp: float = 1e-3
    """Learning rate of the colour MLP."""
    tv_weight: float = 0.0
    """Weight of a total-variation loss on the fine density grid (0: off). Off by default: 1e-4 on 11 generated 128 px
    scenes lifted 1000-step fits by 0.04 dB on average (scratch; +0.01 from a learned start) and made them about 25 %
    slower (BENCHMARKS.md, *The density TV term on the clock*)."""
    distortion_weight: float = 0.0
    """Weight of mip-NeRF 360's distortion loss on every training ray's weights (0: off): it gathers a ray's weight into one short interval, against haze and floaters (DirectVoxGO v2 uses 0.01 on unbounded scenes). Positions along a ray are normalised to [0, 1]: marching distance in a contracted space (even steps in the contracted cube), distance over the ray's far end in a box."""
    tv_features_weight: float = 0.0
    """Weight of a total-variation loss on the fine feature grid (diffuse logits and MLP features; 0: off; DirectVoxGO's ``weight_tv_k0``)."""
    voxels_per_pixel: float = AUTO_VOXELS_PER_PIXEL
    """Auto fine grid (``num_voxels`` 0): voxels per axis per pixel of the larger image side, before the clamp to 16..``max_side`` (see ``for_scene``)."""
    max_side: int = AUTO_MAX_SIDE
    """Auto fine grid (``num_voxels`` 0): at most ``max_side^3`` voxels, whatever the images' size (at least 16)."""
    space: str = "auto"
    """Where the grids live: ``box`` (the scene's bounding box), ``contracted`` (an unbounded scene: an inner box around what the cameras look at at full resolution, the rest of space squashed into a shell, see :mod:`nerfmeta.render.contraction`), or ``auto``: contracted for scenes detected (or declared) unbounded, else box."""
    inner_box: tuple[float, ...] = ()
    """``contracted``: the inner box as ``(x, y, z, half_side)`` in world units (empty: from the cameras, see ``for_scene``)."""
    render_stop_eps: float = 0.0
    """Test-time renders (evaluation, videos) stop each ray once its transmittance falls below this, marching and evaluating ``render_round_samples`` samples of the rays still alive at a time (0: off, the one-pass path). Training renders never stop early. Off by default: the models a few minutes' fit gives are semi-transparent, so 1e-4 cut 0-6 % of the samples and the rounds' second density lookup made renders 0-15 % slower (beer and lego fits, BENCHMARKS.md #16)."""
    render_round_samples: int = 32
    """Samples per ray marched and evaluated at a time in test-time renders (see ``render_stop_eps``)."""
    render_phases: int = 1
    """Test-time renders (evaluation, videos) average the colours of this many marches, their samples
    (i + 0.5) / n of a step into their bins (i < n; 1: one march at the bins' middles; 2 on forward-facing and
    unbounded scenes, see their defaults). Training jitters
    each ray's samples by a random fraction of a step, so the field learns to render well *on average over that
    shift*, not at any one shift; with one-voxel steps (forward-facing and unbounded scenes) one march at
    the middles shows the difference as a fine crosshatch over walls and floors. Two marches average it away
    at twice the samples (``samples_evaluated`` counts both), on the same checkpoints: beer's 120-s fits +0.07-0.08
    dB, SSIM +0.008, LPIPS -0.003..-0.006 (a 2000-step fit +0.14 dB, up on each of its nine held-out frames), two
    generated forward-facing scenes +0.16..+0.31 dB (3000 steps, three seeds each); on lego (an object, half-voxel
    steps) +0.01 dB, so objects keep 1 (BENCHMARKS.md #16, session 46)."""
    shell: float = 1.0
    """``contracted``: width of the shell holding everything outside the inner box, in inner-box half-sides (1: mip-NeRF 360's ``2 - 1/|x|``)."""
    background_map: int = 0
    """Rows of a learned background: what a ray meets after everything the grid holds (beyond the contracted cube,
    past an NDC grid's far plane, out of a box) is an equirectangular table of ``background_map x 2 background_map``
    colours looked up by the direction of the ray the grid marches (world directions; NDC ones on forward-facing
    scenes; :mod:`nerfmeta.render.background`), added to the fixed background colour (so a fit starts from it) and
    clamped to [0, 1] by :func:`~nerfmeta.render.background.clamp_inward`, whose gradient still brings back a channel
    pushed past either end (with a plain clamp the generated forward-facing scenes' colour overshot black and stayed
    there; now it comes back to a dark blue, +0.22..+0.30 dB at equal steps on four of five; beer's settles at a light warm grey, 0.70-0.79,
    and never reaches either end). 0: the fixed colour alone
    (objects: their photos are composited on it). 1 (forward-facing and unbounded scenes, see their defaults) is
    two colours blended round the horizon, close to one learned colour; finer tables did worse on beer and on a
    generated room (BENCHMARKS.md #16 session 48)."""
    lr_background: float = 0.1
    """Learning rate of the background table (``background_map`` > 0)."""

    def __post_init__(self) -> None:
        check_fields(self, "grid config")  # types first (a bool is no count, a string no step), then the ranges below
        # JSON has no tuples: accept a list for ``growth_steps`` so a saved config loads back equal.
        object.__setattr__(self, "growth_steps", tuple(int(s) for s in self.growth_steps))
        object.__setattr__(self, "inner_box", tuple(float(v) for v in self.inner_box))
        checks = (
            ("coarse_iters", self.coarse_iters >= 0, "use 0 (no coarse stage) or more"),
            ("coarse_num_voxels", self.coarse_num_voxels == 0 or self.coarse_num_voxels >= 8, "use 0 (auto) or at least 8"),
            ("num_voxels", self.num_voxels == 0 or self.num_voxels >= 8, "use 0 (auto) or at least 8"),
            ("coarse_alpha_init", 0.0 < self.coarse_alpha_init < 1.0, "use a value in (0, 1), e.g. 1e-4"),
            ("alpha_init", 0.0 < self.alpha_init < 1.0, "use a value in (0, 1), e.g. 1e-2"),
            ("feature_dim", self.feature_dim >= 0, "use 0 or more"),
            ("mlp_width", self.mlp_width >= 1, "use 1 or more"),
            ("mlp_depth", self.mlp_depth >= 1, "use 1 or more"),
            ("dir_freqs", self.dir_freqs >= 0, "use 0 or more"),
            ("view_dependent", isinstance(self.view_dependent, bool) or self.view_dependent == "auto", 'use true, false or "auto"'),
            ("view_probe_step", self.view_probe_step >= 1, "use 1 or more fine-stage steps"),
            ("view_probe_rays", self.view_probe_rays >= 1, "use 1 or more"),
            ("view_probe_dirs", self.view_probe_dirs >= 1, "use 1 or more"),
            ("stepsize", self.stepsize > 0.0, "use a positive step, e.g. 0.5 voxels"),
            ("occupancy_every", self.occupancy_every >= 0, "use 0 (never) or more"),
            ("growth_steps", list(self.growth_steps) == sorted(set(self.growth_steps)) and all(s > 0 for s in self.growth_steps),
             "use increasing positive fine-stage steps, e.g. [100, 200]"),
            ("growth_density", all(m in GROWTH_MODES for m in self.growth_density.split(",")),
             "use project or interp, or one of them per growth, comma-separated (e.g. project,interp)"),
            ("growth_cutoff", 0.0 < self.growth_cutoff <= 1.0, "use a fraction of the fit in (0, 1], e.g. 0.7"),
            ("world_bound_scale", self.world_bound_scale > 0.0, "use a positive scale, e.g. 1.05"),
            *((name, 0.0 < getattr(self, name) < math.inf, "use a positive finite learning rate")
              for name in ("coarse_lr_density", "lr_density", "lr_features", "lr_mlp", "lr_background")),
            *((name, 0.0 <= getattr(self, name) < math.inf, "use 0 (off) or a positive finite weight")
              for name in ("tv_weight", "tv_features_weight")),
            ("voxels_per_pixel", 0.0 < self.voxels_per_pixel < math.inf, "use a positive ratio, e.g. 0.88"),
            ("max_side", self.max_side >= AUTO_MIN_SIDE, f"use at least {AUTO_MIN_SIDE}, e.g. {AUTO_MAX_SIDE}"),
            ("distortion_weight", 0.0 <= self.distortion_weight < math.inf, "use 0 (off) or a positive finite weight"),
            ("space", self.space in ("auto", "box", "contracted"), "use auto, box or contracted"),
            ("inner_box", len(self.inner_box) == 0 or (len(self.inner_box) == 4 and self.inner_box[3] > 0),
             "use [] (from the cameras) or [x, y, z, half_side] with half_side > 0"),
            ("shell", 0.0 < self.shell < math.inf, "use a positive width, e.g. 1"),
            ("background_map", self.background_map >= 0, "use 0 (the fixed background colour) or a number of rows, e.g. 1"),
            ("render_stop_eps", 0.0 <= self.render_stop_eps < 1.0, "use a value in [0, 1), e.g. 1e-4"),
            ("render_round_samples", self.render_round_samples >= 1, "use 1 or more, e.g. 32"),
            ("render_phases", self.render_phases >= 1, "use 1 or more, e.g. 2"),
        )
        for name, ok, hint in checks:
            if not ok:
                raise ConfigError(f"grid config {name}={getattr(self, name)!r} is not allowed: {hint}")

    def for_scene(self, scene: Scene) -> "VoxelGridConfig":
        """This config with the "auto" (0) grid sizes resolved for ``scene``.

        Rule: the fine grid gets ``n^3`` voxels with ``n = voxels_per_pixel * max(height, width)`` clamped to
        16..``max_side`` (160); the default 0.88 is about one voxel per pixel footprint for NeRF-synthetic cameras (88^3 for 100x100
        views, 28^3 for 32x32, and DirectVoxGO's 160^3 from 182x182 up, e.g. 800x800). The
        coarse grid gets ``(n / 2)^3`` voxels (at least 16^3). Sizes given explicitly are kept.

        ``space="auto"`` becomes ``contracted`` for an unbounded scene (``scene.scene_type``), else
        ``box``; a contracted space without an ``inner_box`` gets one from the cameras
        (:func:`~nerfmeta.render.contraction.inner_box_from_cameras`: centred on the point nearest
        every optical axis, just holding every camera).
        """
        side = round(self.voxels_per_pixel * max(scene.height, scene.width))
        side = min(self.max_side, max(AUTO_MIN_SIDE, side))
        num = self.num_voxels or side**3
        coarse = self.coarse_num_voxels or max(AUTO_MIN_SIDE, round(AUTO_COARSE_RATIO * side)) ** 3
        space = self.space
        if space == "auto":
            space = "contracted" if scene.scene_type.kind == "unbounded" else "box"
        inner = self.inner_box
        if space == "contracted" and not inner:
            centres = scene.poses[:, :3, 3]
            box = inner_box_from_cameras(centres, focus_point(centres, view_directions(scene.poses)), shell=self.shell)
            inner = (*box.centre, box.radius)
        return replace(self, num_voxels=num, coarse_num_voxels=coarse, space=space, inner_box=inner)


# ----- model --------------------------------------------------------------------------------------


MLP_PIECE_ROWS = 1 << 13
"""Rows a test-time colour MLP evaluates at once: its (rows, 32) intermediates then stay in a CPU core's cache. Beer
180 x 320 (1024-ray render chunks of ~140k samples): 36.7k rays/s against 27.3k in one piece, 35.4k with 16384-row
pieces; lego unchanged (its chunks hold ~24k samples; BENCHMARKS.md, *Small chunks on every core*)."""


class ColorMLP(nn.Module):
    """Shallow MLP mapping grid features and the encoded view direction to RGB logits; last layer zero.

    The first layer's input is ``[features, view]``; its view part is applied once per *ray* and
    gathered per sample (the same sum, fewer products).
    """

    def __init__(self, feature_dim: int, view_dim: int, width: int, depth: int):
        super().__init__()
        self.feature_dim = feature_dim
        dims = [feature_dim + view_dim] + [width] * (depth - 1) + [3]
        self.linears = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))
        nn.init.zeros_(self.linears[-1].weight)
        nn.init.zeros_(self.linears[-1].bias)

    def forward(self, features: torch.Tensor, view: torch.Tensor, ray_idx: torch.Tensor) -> torch.Tensor:
        """RGB logits (N, 3) from features (N, feature_dim), per-ray encoded views (n_rays, view_dim), ray_idx (N,).

        Without gradient the rows go through in pieces of :data:`MLP_PIECE_ROWS` (each row is its own input)."""
        n, piece = features.shape[0], MLP_PIECE_ROWS
        if torch.is_grad_enabled() or n <= piece:
            return self._logits(features, view, ray_idx)
        return torch.cat([self._logits(features[i : i + piece], view, ray_idx[i : i + piece]) for i in range(0, n, piece)])

    def _logits(self, features: torch.Tensor, view: torch.Tensor, ray_idx: torch.Tensor) -> torch.Tensor:
        first = self.linears[0]
        w_feat, w_view = first.weight.split([self.feature_dim, first.weight.shape[1] - self.feature_dim], 1)
        per_ray = F.linear(view, w_view, first.bias).index_select(0, ray_idx)
        # test time: the feature product added into the gathered per-ray part and the ReLUs in place, no
        # intermediate copies (a quarter of the MLP's time on beer; BENCHMARKS.md, #16 session 23)
        inplace = not torch.is_grad_enabled()
        x = per_ray.addmm_(features, w_feat.t()) if inplace else F.linear(features, w_feat) + per_ray
        for lin in self.linears[1:]:
            x = lin(F.relu(x, inplace=inplace))
        return x


def march_phases(count: int) -> tuple[float, ...]:
    """Where a test-time march's samples sit in their bins, one entry per march: ``(i + 0.5) / count``, evenly
    spread over the step and symmetric about its middle (``(0.5,)`` for one march)."""
    if count < 1:
        raise ValueError(f"count {count}: use 1 or more marches")
    return tuple((i + 0.5) / count for i in range(count))


def softplus_inverse(y: torch.Tensor) -> torch.Tensor:
    """``x`` with ``softplus(x) == y`` for ``y > 0`` (clamped at 1e-12), computed stably."""
    y = y.clamp(min=1e-12)
    return y + torch.log(-torch.expm1(-y))


class VoxelGrid(RadianceModel):
    """DirectVoxGO-style backbone; see the module docstring.

    Layers, input to output: coarse stage ``density_coarse``, ``color_coarse``; fine stage
    ``density``, ``features``, ``mlp.0`` ... ``mlp.{depth-1}`` (no MLP layers when the scene is
    not view-dependent: ``view_dependent`` False, or ``"auto"`` once :meth:`decide` found the MLP
    not worth it; ``self.view_dependent`` and :meth:`structure` hold the resolved value, None while
    ``auto`` is undecided, with the MLP on trial). ``freeze_first(1)`` freezes the density grid (geometry),
    ``freeze_first(2)`` also the feature grid, leaving only the decoder to adapt.

    Parameters (channels-first grids): ``density_coarse`` / ``density`` (1, X, Y, Z),
    ``color_coarse`` (3, X, Y, Z), ``features`` (3 + feature_dim, X, Y, Z). Buffers: ``scene_bounds`` (2, 3),
    ``bounds`` (2, 3) the current stage's box, ``mask`` the occupancy cache (a (1, 1, 1) True
    when there is none).
    """

    backbone = "grid"
    meta_hints = GRID_META_HINTS

    @classmethod
    def settles_at(cls, config: VoxelGridConfig) -> int:
        """The grid is final once the coarse stage and every growth step are over."""
        return config.coarse_iters + max(config.growth_steps, default=0) if config.growth_steps else 0

    def recipe_notes(self) -> dict[str, Any]:
        return {"coarse_iters": self.config.coarse_iters}

    def __init__(self, config: VoxelGridConfig, bounds: torch.Tensor):
        super().__init__()
        if config.num_voxels == 0 or (config.coarse_iters > 0 and config.coarse_num_voxels == 0):
            raise ConfigError("grid config: num_voxels/coarse_num_voxels 0 means auto; resolve them with "
                              "VoxelGridConfig.for_scene(scene) or set them explicitly")
        self.config = config
        self.box = self._inner_box(config)
        if self.box is not None:  # the grids fill the contracted cube, not the scene's box
            bounds = torch.tensor([[-self.box.extent] * 3, [self.box.extent] * 3], device=bounds.device)
        self.register_buffer("scene_bounds", bounds.detach().clone().float())
        self.register_buffer("bounds", self.scene_bounds.clone())
        if config.background_map > 0:
            rows = config.background_map
            self.background_map = nn.Parameter(torch.zeros(3, rows, 2 * rows, device=bounds.device))
        self.occupancy = OccupancyGrid(self.scene_bounds, box=self.box)
        self.level = 0
        self.growth_skipped = False  # a late growth was skipped (said once)
        self.fine_step0 = config.coarse_iters
        # Resolved view dependence; None ("auto") until ``decide`` measures it, the MLP on trial until then.
        self.view_dependent: bool | None = config.view_dependent if isinstance(config.view_dependent, bool) else None
        self._fold_dirs: torch.Tensor | None = None  # directions ``decide`` drew, for the fold in ``begin_step``
        # The colour MLP is created now (with the caller's RNG state, so a seeded build is
        # reproducible) but only registered when the fine stage starts.
        mlp = ColorMLP(config.feature_dim, encoding_dim(3, config.dir_freqs), config.mlp_width, config.mlp_depth)
        object.__setattr__(self, "_pending_mlp", mlp)
        self._render_copies = ChannelsLastCopies()  # channels-last colour grids, kept while a view renders
        if config.coarse_iters > 0:
            self._init_coarse(self.scene_bounds.clone(), voxel_layout(self.scene_bounds, config.coarse_num_voxels)[0])
        else:
            self._init_fine(self.scene_bounds.clone(), None, None)

    @staticmethod
    def _inner_box(config: VoxelGridConfig) -> InnerBox | None:
        """The contraction of a ``contracted`` config (None: the grids live in the scene's box)."""
        if config.space != "contracted":
            return None
        if not config.inner_box:
            raise ConfigError("grid config: space=contracted needs an inner_box; resolve it with "
                              "VoxelGridConfig.for_scene(scene) or set it as [x, y, z, half_side]")
        x, y, z, radius = config.inner_box
        return InnerBox((x, y, z), radius, config.shell)

    # ----- structure -------------------------------------------------------------------------
    @classmethod
    def warm_up(cls) -> None:
        """Load the fused CPU lookups (:mod:`~nerfmeta.fields.grid_kernels`: about half a second the first time in a
        process with numba's cache warm) and the learned start's feature kernel
        (:func:`~nerfmeta.priors.occupancy.fused_inputs_available`), which the default route builds a grid with."""
        from nerfmeta.priors.occupancy import fused_inputs_available  # the priors import this module

        super().warm_up()
        fused_available()
        fused_inputs_available()

    def _init_coarse(self, bounds: torch.Tensor, size: tuple[int, int, int]) -> None:
        cfg = self.config
        self.stage = "coarse"
        self.bounds = bounds
        self.occupancy = OccupancyGrid(bounds, box=self.box)
        self.size, self.voxel = tuple(size), voxel_layout(bounds, cfg.coarse_num_voxels)[1]
        self.unit = self.voxel
        self.shift = softplus_shift_for_alpha(cfg.coarse_alpha_init, cfg.stepsize)
        self.density_coarse = nn.Parameter(torch.zeros(1, *self.size, device=bounds.device))
        self.color_coarse = nn.Parameter(torch.zeros(3, *self.size, device=bounds.device))

    @torch.no_grad()
    def load_coarse_start(self, sigma: torch.Tensor, rgb: torch.Tensor | None = None) -> None:
        """Start the coarse grids from a feed-forward guess (e.g. :mod:`nerfmeta.priors.carve`) before the first step.

        Args:
            sigma: (X, Y, Z) density per world unit at ``grid_points(self.bounds, self.size)`` (> 0).
            rgb: (3, X, Y, Z) colour in [0, 1] at those points, None to keep the coarse colour grid.
        """
        if self.stage != "coarse" or tuple(sigma.shape) != tuple(self.size):
            raise ValueError(f"a coarse start needs the coarse stage and a {tuple(self.size)} grid, got stage "
                             f"{self.stage!r} and {tuple(sigma.shape)}")
        self.density_coarse.data = (softplus_inverse(sigma.float() * self.unit) - self.shift)[None].to(self.density_coarse)
        if rgb is not None:
            self.color_coarse.data = torch.logit(rgb.float().clamp(1e-3, 1.0 - 1e-3)).to(self.color_coarse)

    def _fine_num_voxels(self) -> int:
        return max(8, int(self.config.num_voxels / 2 ** (len(self.config.growth_steps) - self.level)))

    def _init_fine(self, bounds: torch.Tensor, mask: torch.Tensor | None, coarse: tuple | None) -> None:
        """Switch to the fine stage in ``bounds``; ``coarse`` = (density, color, bounds, size, unit, shift) to start from."""
        cfg = self.config
        device = bounds.device
        self.stage = "fine"
        self.bounds = bounds
        self.occupancy = OccupancyGrid(bounds, mask, box=self.box)
        _, self.unit = voxel_layout(bounds, cfg.num_voxels)
        self.size, self.voxel = voxel_layout(bounds, self._fine_num_voxels())
        self.shift = softplus_shift_for_alpha(cfg.alpha_init, cfg.stepsize)
        density = torch.zeros(1, *self.size, device=device)
        feats = torch.zeros(self._channels(), *self.size, device=device)
        if coarse is not None:
            c_density, c_color, c_bounds, c_size, c_unit, c_shift = coarse
            pts = grid_points(bounds, self.size).reshape(-1, 3)
            sigma_world = F.softplus(interp_cf(c_density, pts, c_bounds)[:, 0] + c_shift) / c_unit
            density = (softplus_inverse(sigma_world * self.unit) - self.shift).view(1, *self.size)
            feats[:3] = interp_cf(c_color, pts, c_bounds).t().reshape(3, *self.size)
        for name in ("density_coarse", "color_coarse"):
            if name in self._parameters:
                delattr(self, name)
        self.density = nn.Parameter(density)
        self.features = nn.Parameter(feats)
        if self.view_dependent is not False and "mlp" not in self._modules:
            self.mlp = self._pending_mlp.to(device)
        elif self.view_dependent is False and "mlp" in self._modules:
            del self.mlp

    def _channels(self) -> int:
        """Feature-grid channels: 3 diffuse logits, plus the MLP's inputs unless decided diffuse."""
        return 3 + (0 if self.view_dependent is False else self.config.feature_dim)

    @torch.no_grad()
    def _fold_view_branch(self, directions: torch.Tensor, chunk: int = 1 << 16) -> None:
        """Drop the MLP: at every voxel, the diffuse logits become those of the colour averaged over ``directions`` (K, 3).

        Exact at the voxel corners; in between, the MLP of interpolated features becomes an
        interpolation of its outputs (a small change the following steps correct).
        """
        feats = self.features.detach().view(self.features.shape[0], -1)
        view = positional_encoding(directions.to(feats), self.config.dir_freqs)  # (K, view_dim)
        folded = []
        for cols in torch.arange(feats.shape[1], device=feats.device).split(chunk):
            f = feats[:, cols]
            zero = torch.zeros(f.shape[1], dtype=torch.long, device=f.device)
            rgb = torch.stack([torch.sigmoid(f[:3].t() + self.mlp(f[3:].t(), v[None], zero)) for v in view]).mean(0)
            folded.append(torch.logit(rgb.clamp(1e-6, 1.0 - 1e-6)).t())
        old = self.features
        self.features = nn.Parameter(torch.cat(folded, 1).view(3, *old.shape[1:]), requires_grad=old.requires_grad)
        del self.mlp

    @property
    def mask(self) -> torch.Tensor:
        """The occupancy cache: the estimator's grid, (X, Y, Z) bool ((1, 1, 1) True: none)."""
        return self.occupancy.binaries

    @mask.setter
    def mask(self, value: torch.Tensor) -> None:
        self.occupancy.binaries = value

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):  # type: ignore[override]
        # States saved before the occupancy cache became the estimator's grid: ``mask`` beside ``bounds``.
        if prefix + "mask" in state_dict:
            state_dict[prefix + "occupancy.binaries"] = state_dict.pop(prefix + "mask")
            state_dict.setdefault(prefix + "occupancy.aabb", state_dict[prefix + "bounds"])
        # Grids saved flat channels-last, (X*Y*Z, C), before they were stored channels-first.
        for name in ("features", "color_coarse"):
            value, own = state_dict.get(prefix + name), self._parameters.get(name)
            if value is not None and own is not None and value.dim() == 2 and own.dim() == 4:
                state_dict[prefix + name] = value.t().reshape(own.shape)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def structure(self) -> dict[str, Any]:
        return {
            "stage": self.stage,
            "level": self.level,
            "fine_step0": self.fine_step0,
            "bounds": self.bounds.tolist(),
            "size": list(self.size),
            "mask_shape": list(self.mask.shape),
            "view_dependent": self.view_dependent,
        }

    def load_structure(self, structure: dict[str, Any]) -> None:
        device = self.scene_bounds.device
        bounds = torch.tensor(structure["bounds"], dtype=torch.float32, device=device)
        self.level = int(structure["level"])
        self.fine_step0 = int(structure["fine_step0"])
        if "view_dependent" in structure:  # absent from structures saved before it was resolved per scene
            self.view_dependent = structure["view_dependent"]
        if structure["stage"] == "fine":
            mask = torch.zeros(structure["mask_shape"], dtype=torch.bool, device=device)
            self._init_fine(bounds, mask, None)
        else:
            self._init_coarse(bounds, tuple(structure["size"]))
        if list(self.size) != list(structure["size"]):
            raise ValueError(f"grid size {self.size} does not match the checkpoint's {structure['size']}")

    # ----- interface ---------------------------------------------------------------------------
    def layers(self) -> list[Layer]:
        background = [Layer("background_map", ("background_map",))] if "background_map" in self._parameters else []
        if self.stage == "coarse":
            return [Layer("density_coarse", ("density_coarse",)), Layer("color_coarse", ("color_coarse",)), *background]
        out = [Layer("density", ("density",)), Layer("features", ("features",))]
        if "mlp" in self._modules:
            out += [Layer(f"mlp.{i}", (f"mlp.linears.{i}.weight", f"mlp.linears.{i}.bias")) for i in range(len(self.mlp.linears))]
        return out + background

    def param_groups(self) -> list[ParamGroup]:
        cfg = self.config
        background = ([ParamGroup("background", ("background_map",), cfg.lr_background)]
                      if "background_map" in self._parameters else [])
        if self.stage == "coarse":
            return [
                ParamGroup("density", ("density_coarse",), cfg.coarse_lr_density, DENSITY_ADAM_EPS),
                ParamGroup("features", ("color_coarse",), cfg.lr_features),
                *background,
            ]
        groups = [
            ParamGroup("density", ("density",), cfg.lr_density, DENSITY_ADAM_EPS),
            ParamGroup("features", ("features",), cfg.lr_features),
        ]
        if "mlp" in self._modules:
            groups.append(ParamGroup("mlp", tuple(f"mlp.{n}" for n, _ in self.mlp.named_parameters()), cfg.lr_mlp))
        return groups + background

    def loss_terms(self, out: RenderOutput, target: torch.Tensor) -> dict[str, torch.Tensor]:
        """``mse``, plus in the fine stage ``tv`` (``tv_weight`` times the density grid's total variation) and
        ``tv_features`` (``tv_features_weight`` times the feature grid's), each when its weight is positive;
        ``distortion`` (``distortion_weight`` times the batch's mean distortion) in either stage."""
        terms = super().loss_terms(out, target)
        if self.stage == "fine":
            for name, weight, grid in (("tv", self.config.tv_weight, self.density),
                                       ("tv_features", self.config.tv_features_weight, self.features)):
                if weight > 0:
                    terms[name] = weight * total_variation(grid)
        if "distortion" in out.extras:
            terms["distortion"] = self.config.distortion_weight * out.extras["distortion"].mean()
        return terms

    def render_extras(self, rays: RayBatch, samples: PackedSamples, comp: Composite) -> dict[str, torch.Tensor]:
        """``distortion`` (n_rays,): each ray's distortion (:func:`packed_distortion`) when ``distortion_weight > 0``."""
        if self.config.distortion_weight <= 0:
            return {}
        s, ds = self.ray_positions(rays, samples)
        return {"distortion": packed_distortion(comp.weights, s, ds, samples.ray_idx, len(rays))}

    def ray_positions(self, rays: RayBatch, samples: PackedSamples) -> tuple[torch.Tensor, torch.Tensor]:
        """Positions (M,) of packed samples along their rays, normalised to [0, 1], and their intervals (M,).

        In a contracted space: the marching distance (:func:`~nerfmeta.render.contraction.to_march`, in
        which the samples are evenly spaced) from the ray's start, over the ray's whole march. In a box:
        the distance over the ray's far end.
        """
        idx, tiny = samples.ray_idx, torch.finfo(samples.t.dtype).tiny
        if self.box is None:
            far = samples.far.clamp(min=tiny).index_select(0, idx)
            return samples.t / far, samples.delta / far
        t1, near_m, far_m = contracted_interval(rays.origins, rays.directions, rays.near, self.box)
        length = (far_m - near_m).clamp(min=tiny).index_select(0, idx)
        m = to_march(samples.t, t1.index_select(0, idx), self.box.shell * self.box.radius)
        step = self.config.stepsize * self.voxel * self.box.radius  # the march's step (see ``sample``)
        return (m - near_m.index_select(0, idx)) / length, step / length

    # ----- schedule ----------------------------------------------------------------------------
    def stage_ending(self, step: int) -> str | None:
        """``"coarse"`` before the fine stage starts; ``"view trial"`` when ``auto`` is due to decide on the MLP."""
        if self.stage == "coarse":
            return "coarse" if step >= self.config.coarse_iters else None
        if self.view_dependent is None and step - self.fine_step0 >= self.config.view_probe_step:
            return "view trial"
        return None

    @torch.no_grad()
    def decide(self, draw_rays: Callable[[int], RayBatch], *, background: torch.Tensor) -> list[Decision]:
        """Resolve ``view_dependent="auto"``: does the MLP's view input pay for itself on this scene?

        On ``view_probe_rays`` training rays, the training MSE of the model as it is against that of
        the same model with the MLP's output averaged over ``view_probe_dirs`` training directions
        (each ray's colour rendered with the directions of other training rays; the average is the
        best the model can do without its view input). The MLP stays when the gain is at least
        ``view_gain_db``; otherwise the next :meth:`begin_step` folds it into the diffuse colour and
        drops it. A fixed ``view_dependent`` is recorded (at the end of the coarse stage), not measured.
        """
        cfg = self.config
        if isinstance(cfg.view_dependent, bool):
            if self.stage != "coarse":
                return []
            return [Decision("view_dependent", cfg.view_dependent, f"view_dependent={cfg.view_dependent}: set in the config")]
        if self.stage != "fine" or self.view_dependent is not None or "mlp" not in self._modules:
            return []
        start = time.perf_counter()
        rays = draw_rays(cfg.view_probe_rays)
        gen = torch.Generator().manual_seed(len(rays))
        err_view = err_avg = 0.0
        for first in range(0, len(rays), 8192):
            batch = rays[first : first + 8192]
            target = batch.target
            err_view += float(((self.render(batch, background=background, phases=1).rgb - target) ** 2).sum())
            others = [batch.directions[torch.randperm(len(batch), generator=gen).to(target.device)]
                      for _ in range(cfg.view_probe_dirs)]
            averaged = torch.stack([self.render(batch, background=background, view_dirs=d, phases=1).rgb
                                    for d in others]).mean(0)
            err_avg += float(((averaged - target) ** 2).sum())
        gain = 10.0 * math.log10(max(err_avg, 1e-12) / max(err_view, 1e-12))
        self.view_dependent = gain >= cfg.view_gain_db
        if not self.view_dependent:
            pick = torch.randperm(len(rays), generator=gen)[: cfg.view_probe_dirs].to(rays.directions.device)
            self._fold_dirs = rays.directions[pick]
        n = 3 * len(rays)
        why = (f"the view input lowers the training error by {gain:.2f} dB "
               f"{'>=' if self.view_dependent else '<'} {cfg.view_gain_db:g} dB"
               + ("" if self.view_dependent else ": the MLP is folded into the diffuse colour and dropped"))
        evidence = {"gain_db": round(gain, 4), "threshold_db": cfg.view_gain_db, "mse_view": round(err_view / n, 7),
                    "mse_view_averaged": round(err_avg / n, 7), "rays": len(rays), "directions": cfg.view_probe_dirs,
                    "probe_s": round(time.perf_counter() - start, 3)}
        return [Decision("view_dependent", self.view_dependent, f"view_dependent={self.view_dependent}: {why}", evidence)]

    def begin_step(self, step: int, progress: float | None) -> StepEvent:
        cfg = self.config
        if self.stage == "coarse" and step >= cfg.coarse_iters:
            bounds, mask = self._fine_box_and_mask()
            coarse = (self.density_coarse.data, self.color_coarse.data, self.bounds.clone(), self.size, self.unit, self.shift)
            self.fine_step0 = step
            self._init_fine(bounds, mask, coarse)
            lo, hi = bounds.tolist()
            occupied = float(self.mask.float().mean())
            volume = float((bounds[1] - bounds[0]).prod() / (self.scene_bounds[1] - self.scene_bounds[0]).prod())
            box = [[round(v, 4) for v in lo], [round(v, 4) for v in hi]]
            decisions = (
                Decision("tighten_box", cfg.tighten_box,
                         f"fine box {box[0]}..{box[1]}: {100 * volume:.1f}% of the scene box's volume"
                         if cfg.tighten_box else "tighten_box=False: the fine box is the scene box",
                         {"box": box, "volume_fraction": round(volume, 4)}),
                Decision("empty_space_skipping", self.mask.numel() > 1,
                         f"occupancy cache keeps {100 * occupied:.1f}% of the fine voxels" if self.mask.numel() > 1
                         else ("empty_space_skipping=False: no occupancy cache" if not cfg.empty_space_skipping
                               else "no occupancy cache: the coarse stage found nothing occupied"),
                         {"occupied_fraction": round(occupied, 4)}),
            )
            return StepEvent(True, f"fine stage: box {[round(v, 3) for v in lo]}..{[round(v, 3) for v in hi]}, "
                                   f"grid {self.size}, {100 * occupied:.1f}% occupied", decisions)
        if self.stage != "fine":
            return StepEvent()
        fine_step = step - self.fine_step0
        due = self.level < len(cfg.growth_steps) and fine_step >= cfg.growth_steps[self.level]
        late = due and progress is not None and progress >= cfg.growth_cutoff and cfg.growth_cutoff < 1.0
        grown = due and not late
        if grown:
            self._grow()
        if cfg.occupancy_every > 0 and fine_step > 0 and fine_step % cfg.occupancy_every == 0 and cfg.empty_space_skipping:
            self._prune_mask()
        if self.view_dependent is None and fine_step >= cfg.view_probe_step:
            self.view_dependent = True  # "auto" never decided (no ``decide`` call): keep the MLP
        notes = [f"grid grown to {self.size}"] if grown else []
        changed = grown
        if late and not self.growth_skipped:
            self.growth_skipped = True
            notes.append(f"growth skipped, and the ones after it: {100 * progress:.0f}% of the fit done "
                         f"(growth_cutoff {cfg.growth_cutoff:g})")
        if self.view_dependent is False and "mlp" in self._modules:
            if self._fold_dirs is None:
                raise RuntimeError("view_dependent was resolved to False without decide(): no directions to fold the MLP over")
            self._fold_view_branch(self._fold_dirs)
            self._fold_dirs = None
            notes.append("colour MLP folded into the diffuse colour and dropped (not view-dependent)")
            changed = True
        return StepEvent(changed, "; ".join(notes))  # a skipped growth changes no parameter: the optimiser is kept

    def _density_grid(self) -> torch.Tensor:
        return self.density_coarse if self.stage == "coarse" else self.density

    @torch.no_grad()
    def alpha_per_step(self, points: torch.Tensor, chunk: int = 1 << 18) -> torch.Tensor:
        """Alpha over one step (``stepsize`` units) at (N, 3) world points, from the current density grid."""
        def alpha(p: torch.Tensor) -> torch.Tensor:
            raw = interp_cf(self._density_grid(), p, self.bounds)[:, 0]
            return -torch.expm1(-F.softplus(raw + self.shift) * self.config.stepsize)

        return evaluate_in_chunks(alpha, points, chunk)

    @torch.no_grad()
    def _fine_box_and_mask(self) -> tuple[torch.Tensor, torch.Tensor | None]:
        cfg = self.config
        pts = grid_points(self.bounds, self.size)
        alpha = self.alpha_per_step(pts.reshape(-1, 3)).view(self.size)
        occupied = alpha > cfg.bbox_thres
        if not cfg.tighten_box or self.box is not None or not bool(occupied.any()):  # the contracted cube holds all space
            bounds = self.bounds.clone()
        else:
            occ_pts = pts[occupied]
            lo, hi = occ_pts.amin(0) - self.voxel, occ_pts.amax(0) + self.voxel
            centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo) * cfg.world_bound_scale
            bounds = torch.stack([torch.maximum(centre - half, self.bounds[0]), torch.minimum(centre + half, self.bounds[1])])
        if not cfg.empty_space_skipping:
            return bounds, None
        full_size, _ = voxel_layout(bounds, cfg.num_voxels)
        mask = OccupancyGrid(bounds).occupied_by(self.alpha_per_step, full_size, cfg.mask_cache_thres, dilation=2)
        # A coarse stage too short to find anything must not leave the fine stage blind.
        return bounds, mask if bool(mask.any()) else None

    @torch.no_grad()
    def _grow(self) -> None:
        self.level += 1
        self.size, self.voxel = voxel_layout(self.bounds, self._fine_num_voxels())
        for name in ("density", "features"):  # frozen grids stay frozen
            old = self._parameters[name]
            move = project_cf if name == "density" and growth_mode(self.config.growth_density, self.level - 1) == "project" else resample_cf
            setattr(self, name, nn.Parameter(move(old.data, self.size), requires_grad=old.requires_grad))

    def _prune_mask(self) -> None:
        """Voxels whose alpha fell below ``mask_cache_thres`` (dilated by one voxel) leave the cache."""
        self.occupancy.prune(self.alpha_per_step, self.config.mask_cache_thres, dilation=1)

    # ----- rendering: the estimator and the field (the base class composites) ---------------------
    def sample(self, rays: RayBatch, *, train: bool, generator: torch.Generator | None,
               phase: float = 0.5) -> SamplingPlan:
        """March every ``stepsize`` voxels through the stage's box, skipping the cache's empty voxels (fine stage);
        each ray's samples sit a random fraction of a step into their bins in training, ``phase`` of one at test time."""
        cfg = self.config
        n, dtype, device = len(rays), rays.origins.dtype, rays.origins.device
        if train:
            jitter = torch.rand(n, generator=generator, dtype=dtype, device="cpu").to(device)
        else:
            jitter = torch.full((n,), phase, dtype=dtype, device=device)
        fine = self.stage == "fine"
        stop = 0.0 if train else cfg.render_stop_eps  # test time only: training sees every sample
        samples = self.occupancy.sampling(rays.origins, rays.directions, rays.near, rays.far, step=cfg.stepsize * self.voxel,
                                          jitter=jitter, skip_empty=fine and cfg.empty_space_skipping,
                                          sigma_fn=(lambda points, _: self.get_density(points)[0]) if stop > 0 else None,
                                          early_stop_eps=stop, round_samples=cfg.render_round_samples)
        return SamplingPlan(samples, cfg.fast_color_thres if fine else cfg.coarse_fast_color_thres)

    def render(self, rays: RayBatch, *, background: torch.Tensor, train: bool = False,
               generator: torch.Generator | None = None, view_dirs: torch.Tensor | None = None,
               phases: int | None = None) -> RenderOutput:
        """The shared render (one march); at test time the mean of ``phases`` (default ``render_phases``) marches
        shifted by :func:`march_phases` (colour, opacity and depth averaged, every march's samples counted)."""
        count = 1 if train else (phases or self.config.render_phases)
        if count == 1:
            return super().render(rays, background=background, train=train, generator=generator, view_dirs=view_dirs)
        outs = [self.render_plan(rays, self.sample(rays, train=False, generator=None, phase=phase),
                                 background=background, view_dirs=view_dirs) for phase in march_phases(count)]
        return RenderOutput(rgb=torch.stack([o.rgb for o in outs]).mean(0), acc=torch.stack([o.acc for o in outs]).mean(0),
                            depth=torch.stack([o.depth for o in outs]).mean(0),
                            samples_evaluated=sum(o.samples_evaluated for o in outs))

    def render_plan(self, rays: RayBatch, plan: SamplingPlan, *, background: torch.Tensor, train: bool = False,
                    view_dirs: torch.Tensor | None = None) -> RenderOutput:
        """The shared render, with the learned background table (``background_map``) added to ``background`` (the fixed
        colour, or a training ray's random one under ``FitConfig.random_background``) and the sum clamped to [0, 1]
        (:func:`~nerfmeta.render.background.clamp_inward`: a channel past either end can come back). A
        render of several marches (``render_phases``) looks the table up once a march: a few operations a ray against
        the march's hundred-odd samples, not worth threading the colour past the base class's render."""
        if "background_map" in self._parameters:
            background = clamp_inward(background + equirect_lookup(self.background_map, rays.directions))
        return super().render_plan(rays, plan, background=background, train=train, view_dirs=view_dirs)

    def get_density(self, points: torch.Tensor) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
        """Post-activated density per world unit (per contracted unit in a contracted space).

        The embedding is the trilinear corners (indices, weights), (8, N) each, shared by the colour
        lookups; with the fused CPU kernels (:func:`~nerfmeta.fields.grid_kernels.trilinear_coords`), which
        recompute them in registers, the corner coordinates (3, N), training or not. Without gradient and
        without those kernels (test-time renders on a GPU) it is the corner coordinates (3, N) too, and every
        lookup is one fused :func:`~nerfmeta.fields.grid_ops.interp_coords` (on a channels-last copy of
        a colour grid, kept for a whole view inside :meth:`render_session`, else made when the samples outnumber
        an eighth of its voxels): the same values, faster. On a CPU, test-time colour grids of more than
        :data:`FUSED_RENDER_MAX_CHANNELS` channels take that path too.
        """
        if self.box is not None:
            points = self.box.contract(points)
        x = grid_coords(points, self.bounds, self.size).contiguous()
        density = self._density_grid()
        if fused_for(density, x):  # on a CPU the fused kernels take the coordinates
            raw = trilinear_coords(density, x)[0]
            return F.softplus(raw + self.shift) / self.unit, (x,)
        if not torch.is_grad_enabled():
            raw = interp_coords(density, x)[0]
            return F.softplus(raw + self.shift) / self.unit, (x,)
        idx, w = corners_from_coords(x, self.size)
        raw = trilinear_gather(density.view(1, -1), idx, w)[0]
        return F.softplus(raw + self.shift) / self.unit, (idx, w)

    def render_session(self) -> ContextManager[None]:
        """Keep the colour grids' channels-last copies while a whole view renders (see :meth:`get_density`)."""
        return self._render_copies.kept()

    def _colour_values(self, name: str, embedding: tuple[torch.Tensor, ...], sel: torch.Tensor | None) -> torch.Tensor:
        """(C, K) values of the colour grid ``name`` at the samples ``sel`` (all when None) of ``embedding``."""
        grid = getattr(self, name)
        if len(embedding) == 1:  # corner coordinates: test time, or training with the fused kernels
            x = embedding[0] if sel is None else take_columns(embedding[0], sel)
            wide = grid.shape[0] > FUSED_RENDER_MAX_CHANNELS
            # Without gradient, grid_sample on a channels-last copy wins where the fused kernels do not apply or the
            # grid is wider than FUSED_RENDER_MAX_CHANNELS, when the copy costs less than it saves: kept for a whole
            # view, or for this many samples.
            if not torch.is_grad_enabled() and (wide or not fused_for(grid, x)) \
                    and (self._render_copies.keeping or 8 * x.shape[1] >= grid[0].numel()):
                return interp_coords(self._render_copies.get(name, grid), x)
            return trilinear_coords(grid, x)
        idx, w = embedding
        if sel is not None:
            idx, w = take_columns(idx, sel), take_columns(w, sel)
        return trilinear_gather(grid.view(grid.shape[0], -1), idx, w)

    def get_outputs(self, embedding: tuple[torch.Tensor, ...], sel: torch.Tensor | None, directions: torch.Tensor,
                    ray_idx: torch.Tensor) -> torch.Tensor:
        """``sigmoid`` of the colour grid (coarse) or of the diffuse logits plus the colour MLP (fine)."""
        if self.stage != "fine":
            return torch.sigmoid(self._colour_values("color_coarse", embedding, sel).t())
        feats = self._colour_values("features", embedding, sel)  # (C, K)
        logits = feats[:3].t()
        if "mlp" in self._modules:
            logits = logits + self.mlp(feats[3:].t(), positional_encoding(directions, self.config.dir_freqs), ray_idx)
        return torch.sigmoid(logits)
