"""A learned occupancy start: which coarse voxels a new scene fills, predicted from its own posed views.

The carved start (:mod:`nerfmeta.priors.carve`) fills the visual hull, which holds whatever no silhouette cuts away:
a lamp's shade, a mug's inside, the space under a table top. Started from the *true* occupancy instead, the same
start ends above the scratch grid on every design scene at 128 px (BENCHMARKS.md, *Grid priors: what a right shape is
worth*). Here a small 3-D CNN (:class:`OccupancyNet`) guesses that occupancy from per-voxel multi-view features
(:func:`point_features`), trained over generated collections whose exact shapes are known
(:mod:`pretrain.occupancy`; the model zoo's ``occupancy`` entry). Everything works on the coarse grid's points in the
scene's loaded frame, as the carve does. ``nerfmeta fit SCENE --init occupancy`` uses it, and so does the default
route (``--init auto``) on object scenes of 96-192 px (:func:`nerfmeta.route.occupancy_route`; BENCHMARKS.md says where
it still falls behind the scratch grid).
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass
from types import ModuleType
from typing import Any, Callable, Collection

import numpy
import torch
import torch.nn as nn

from nerfmeta import fused
from nerfmeta.data.scene import Scene
from nerfmeta.errors import ConfigError, message_line
from nerfmeta.fields.grid_ops import dilate, grid_points
from nerfmeta.io import load_tensors
from nerfmeta.priors.carve import HULL_MISSES, MISS_EVERY, SEEN_FRACTION, dilate_masks, in_hull, lookup, silhouettes, visual_hull
from nerfmeta.priors.start import StartReport, carve_blocker, load_occupied_start

N_FEATURES = 10
"""Features per point (:func:`point_features`)."""
ALLOWED_MARGIN_PX = 2
"""The start keeps only points of the visual hull with masks dilated this many pixels, grown one voxel in 3-D."""
FUSED_SPLIT_MIN_POINTS = 1 << 14
""":func:`occupancy_inputs`' kernel splits at least this many points over torch's threads (:func:`nerfmeta.fused.parts`)."""
THRESHOLD = 0.02
"""A point starts occupied when the network gives it at least this probability (recall first: a point started empty
behind a filled one is never sampled again). 0.1 (the first choice) left two unseen sofas about 7 % of their surface
short and 0.27-0.29 dB below the scratch grid after 1000 steps; 0.02 ends them 0.01-0.04 above. Over 44 held-out
128 px scenes 42 end above scratch with 0.02, 40 with 0.1: unseen categories +0.15 dB on average, seen ones -0.15 (the
mugs -0.4 to -0.8: their cups fill up more), every seen one but an airplane (-0.03) still above scratch. A third
unseen sofa ends below with either (-0.52, -0.63). The points between the two thresholds need the full start
density: started at scratch's alpha or at 0.01-0.03 a step they change nothing (BENCHMARKS.md, *Grid priors*,
"Session 33")."""
COARSE_ITERS = 200
"""Coarse steps a learned start keeps (a scratch grid keeps ``VoxelGridConfig.coarse_iters``, 100). The start fills a
little more than the object, and the coarse stage (three times the fine stage's density learning rate) is where the
surplus is carved; the fine stage inherits whatever is left. At fixed iterations (1000 steps) on the 11 held-out scenes
of collection seed 73 at 128 px and three of seed 41, 200 coarse steps instead of 100 ended every started scene
higher (+0.07 to +1.03 dB; the unseen sofa that ended 0.52 dB below scratch now 0.52 above), and a coarse step costs
less than a fine one. On the clock (seeds 79, 73, 47 and 59) all 44 end above scratch; two dip 0.13 and 0.59 dB behind
it mid-fit, just after a grid growth, which now comes 100 steps later. A scratch grid ends higher with 200 on the seed-73
scenes too (+0.09 to +0.75 dB) but not on lego in a 60-s budget (32.93 / 31.70 dB against 33.39 / 33.31 over two
seeds: its longer coarse stage grows density off the object, which widens the fine box up to 4.5-fold), so the
scratch default stays at 100; a learned start's coarse grid starts nearly empty outside its guess (BENCHMARKS.md,
*Grid priors*, "Session 34")."""


def point_features(points: torch.Tensor, masks: torch.Tensor, images: torch.Tensor, poses: torch.Tensor,
                   intrinsics: torch.Tensor, chunk: int = 1 << 15) -> torch.Tensor:
    """(F, N) features of (N, 3) points from (V, H, W) foreground masks and (V, H, W, 3) images.

    Per point: the fraction of views that see it; of those, the fractions on foreground (the masks as they are, and
    dilated a pixel); whether no view / at most one view shows background there; the mean colour over the views on
    foreground (3) and its RMS spread; the fraction of all views on foreground.
    """
    dilated, flat_images = dilate_masks(masks, 1).reshape(masks.shape[0], -1), images.reshape(masks.shape[0], -1, 3)
    return torch.cat([_features(*lookup(p, masks, poses, intrinsics), dilated, flat_images) for p in points.split(chunk)], 1)


def _features(flat: torch.Tensor, seen: torch.Tensor, fg: torch.Tensor, dilated: torch.Tensor,
              flat_images: torch.Tensor) -> torch.Tensor:
    """(F, n) :func:`point_features` of n points from their :func:`~nerfmeta.priors.carve.lookup` (V, n) ``flat``,
    ``seen``, ``fg``, with the (V, H * W) masks ``dilated`` a pixel and (V, H * W, 3) ``flat_images``."""
    v = flat.shape[0]
    fg1 = torch.gather(dilated, 1, flat) & seen
    rgb = torch.gather(flat_images, 1, flat[..., None].expand(-1, -1, 3))
    n_seen = seen.sum(0).clamp(min=1).float()
    w = fg.float()[..., None]
    n_fg = w.sum(0).clamp(min=1)
    mean = (rgb * w).sum(0) / n_fg
    spread = (((rgb - mean) ** 2 * w).sum(0) / n_fg).mean(-1).sqrt()
    background = (seen & ~fg1).sum(0)
    return torch.stack([seen.sum(0) / v, fg.sum(0) / n_seen, fg1.sum(0) / n_seen, (background == 0).float(),
                        (background <= 1).float(), mean[:, 0], mean[:, 1], mean[:, 2], spread, fg.sum(0) / v])


class OccupancyNet(nn.Module):
    """(F, X, Y, Z) features -> (X, Y, Z) occupancy logits: 3x3x3 convolutions dilated 1, 2, 4, 8, 1 (a receptive
    field 33 voxels across), ``width`` channels, ReLU, then a 1x1x1 convolution."""

    def __init__(self, width: int = 16, dilations: tuple[int, ...] = (1, 2, 4, 8, 1)):
        super().__init__()
        layers: list[nn.Module] = []
        channels = N_FEATURES
        for d in dilations:
            layers += [nn.Conv3d(channels, width, 3, padding=d, dilation=d), nn.ReLU()]
            channels = width
        self.net = nn.Sequential(*layers, nn.Conv3d(channels, 1, 1))

    @classmethod
    def from_state(cls, state: dict[str, torch.Tensor]) -> "OccupancyNet":
        """The network of a saved ``state_dict`` (its width read from the first layer)."""
        net = cls(state["net.0.weight"].shape[0])
        net.load_state_dict(state)
        return net.eval()

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        # channels last: oneDNN's convolutions on a CPU read it without a reorder (1.4x on two threads of the 2-core CPU
        # for a 128 px scene's 44 x 86 x 48 grid, about the same on one; the same logits to 1e-6)
        return self.net(features[None].contiguous(memory_format=torch.channels_last_3d))[0, 0]


def load_occupancy_net(path: str | os.PathLike) -> OccupancyNet:
    """The :class:`OccupancyNet` saved (:func:`~nerfmeta.io.save_tensors`) at ``path``; a one-line
    :class:`~nerfmeta.errors.ConfigError` naming the file when it is missing, unreadable or not such a network."""
    try:
        state = load_tensors(path)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such occupancy network file") from None
    except Exception as err:  # OSError, or safetensors' own error types
        raise ConfigError(f"{path}: not readable as safetensors ({message_line(err)})") from None
    try:
        return OccupancyNet.from_state(state)
    except (KeyError, RuntimeError, IndexError) as err:  # another network's tensors
        raise ConfigError(f"{path}: not an occupancy network ({message_line(err)})") from None


@dataclass(frozen=True)
class GridViews:
    """A coarse grid's points and the training views they are judged by, on the grid's device.

    Attributes:
        points: (N, 3) the coarse grid's points (``grid_points`` order) in the scene's loaded frame.
        masks: (V, H, W) bool foreground of the training views.
        images: (V, H, W, 3); poses: (V, 4, 4); intrinsics: (V, 4).
    """

    points: torch.Tensor
    masks: torch.Tensor
    images: torch.Tensor
    poses: torch.Tensor
    intrinsics: torch.Tensor


def grid_views(model, scene: Scene) -> GridViews | str:
    """``model``'s coarse points and ``scene``'s training views, or why the views have no silhouettes."""
    train, device = scene.subset("train"), model.bounds.device
    images = train.images.to(device)
    sil = silhouettes(images, None if train.alphas is None else train.alphas.to(device))
    if sil.masks is None:
        return sil.reason
    return GridViews(grid_points(model.bounds, model.size).reshape(-1, 3), sil.masks, images, train.poses.to(device),
                     train.intrinsics.to(device))


def allowed_points(inside: torch.Tensor, seen_fraction: torch.Tensor, size: tuple[int, int, int]) -> torch.Tensor:
    """(X, Y, Z) bool: the points a start may fill, from the (N,) hull test with :data:`ALLOWED_MARGIN_PX` of mask
    margin and the (N,) fraction of views that see each point: well-seen hull points, grown a voxel."""
    return dilate((inside & (seen_fraction >= SEEN_FRACTION)).view(size), 1)


def _smoke(kernels: ModuleType) -> None:
    """Runs the kernel on one point and one 1 x 1 view, so it does not compile inside a start."""
    kernels.point_inputs(numpy.zeros((1, 3), numpy.float32), numpy.array([[[0.0, 0, 0, 0.5], [0, 0, 0, 0.5], [0, 0, 0, 1]]]),
                         numpy.full((1, 1, 1), 7, numpy.uint8), numpy.ones((1, 1, 1, 3), numpy.float32), HULL_MISSES,
                         MISS_EVERY, numpy.empty((N_FEATURES, 1), numpy.float32), numpy.empty(1, bool), 0, 1)


def _kernels() -> ModuleType | None:
    return fused.load("nerfmeta.priors._features_numba", _smoke, "learned start's feature kernel")


def fused_inputs_available() -> bool:
    """True when :func:`occupancy_inputs` can use its fused kernel (numba importable, the kernel compiled or loaded,
    which this call does once per process, and not switched off: :mod:`nerfmeta.fused`)."""
    return fused.enabled() and _kernels() is not None


def projection_matrices(poses: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
    """(V, 3, 4) float64 rows giving a world point's ``(x * d, y * d, d)``: its pixel position (as
    :func:`~nerfmeta.priors.carve.project`) times its depth ``d`` in front of the camera, for (V, 4, 4) camera-to-world
    ``poses`` (OpenGL cameras, looking along -z) and (V, 4) ``(fx, fy, cx, cy)``."""
    rot, t = poses[:, :3, :3].double(), poses[:, :3, 3].double()
    world_to_camera = torch.cat([rot.transpose(1, 2), -(rot.transpose(1, 2) @ t[..., None])], 2)  # [R^T | -R^T t]
    fx, fy, cx, cy = (intrinsics[:, k, None].double() for k in range(4))
    depth = -world_to_camera[:, 2]
    return torch.stack([fx * world_to_camera[:, 0] + cx * depth, cy * depth - fy * world_to_camera[:, 1], depth], 1)


def _fused_inputs(views: GridViews, dilated: torch.Tensor, wide: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(F, N) features and (N,) hull test of ``views``' points by the kernel
    (:mod:`nerfmeta.priors._features_numba`; the projection in float64), the points split over torch's threads."""
    n = views.points.shape[0]
    features, inside = torch.empty(N_FEATURES, n), torch.empty(n, dtype=torch.bool)
    flags = views.masks.to(torch.uint8) | (dilated.to(torch.uint8) << 1) | (wide.to(torch.uint8) << 2)
    common = (views.points.detach().float().contiguous().numpy(),
              projection_matrices(views.poses.detach(), views.intrinsics.detach()).contiguous().numpy(),
              flags.contiguous().numpy(), views.images.detach().float().contiguous().numpy(), HULL_MISSES, MISS_EVERY,
              features.numpy(), inside.numpy())
    n_parts = fused.parts(n, FUSED_SPLIT_MIN_POINTS)
    cuts = [n * p // n_parts for p in range(n_parts + 1)]
    fused.split(_kernels().point_inputs, [(*common, cuts[p], cuts[p + 1]) for p in range(n_parts)])
    return features, inside


def occupancy_inputs(views: GridViews, size: tuple[int, int, int], chunk: int = 1 << 15) -> tuple[torch.Tensor, torch.Tensor]:
    """The network's input on a coarse grid of ``size`` corners, (F, X, Y, Z) :func:`point_features`, and the
    (X, Y, Z) points it may fill: the visual hull with :data:`ALLOWED_MARGIN_PX` of mask margin, grown a voxel.
    One projection of the points serves both: on a CPU a fused kernel's (:func:`fused_inputs_available`; the same
    values to float rounding), else PyTorch's in chunks of ``chunk`` points."""
    v = views.masks.shape[0]
    dilated, wide = (dilate_masks(views.masks, px) for px in (1, ALLOWED_MARGIN_PX))
    if views.points.device.type == "cpu" and fused_inputs_available():
        feats, inside = _fused_inputs(views, dilated, wide)
    else:
        dilated, wide, flat_images = dilated.reshape(v, -1), wide.reshape(v, -1), views.images.reshape(v, -1, 3)
        chunks = []
        for p in views.points.split(chunk):
            flat, seen, fg = lookup(p, views.masks, views.poses, views.intrinsics)
            chunks.append((_features(flat, seen, fg, dilated, flat_images),
                           in_hull(seen, torch.gather(wide, 1, flat) & seen)))
        feats, inside = torch.cat([f for f, _ in chunks], 1).float(), torch.cat([i for _, i in chunks])
    return feats.reshape(N_FEATURES, *size), allowed_points(inside, feats[0], size)


@dataclass(frozen=True)
class StartInputs:
    """What a start reads of a grid: its points and views, the points it may fill, and (the learned start) its features.

    Attributes:
        views: the grid's coarse points and the training views (:func:`grid_views`).
        allowed: (X, Y, Z) bool, the points a start may fill (:func:`allowed_points`).
        features: (F, X, Y, Z) the network's input (:func:`occupancy_inputs`), None where not computed.
    """

    views: GridViews
    allowed: torch.Tensor
    features: torch.Tensor | None = None


def hull_inputs(model, scene: Scene) -> StartInputs | str:
    """``model``'s :class:`StartInputs` without features (one projection: the hull), or why the views cannot be carved."""
    views = carve_blocker(model, scene) or grid_views(model, scene)
    if isinstance(views, str):
        return views
    inside, seen = visual_hull(views.points, dilate_masks(views.masks, ALLOWED_MARGIN_PX), views.poses, views.intrinsics)
    return StartInputs(views, allowed_points(inside, seen, model.size))


def network_inputs(model, scene: Scene) -> StartInputs | str:
    """``model``'s :class:`StartInputs` with the network's features (one projection serves both), or why not."""
    views = carve_blocker(model, scene) or grid_views(model, scene)
    if isinstance(views, str):
        return views
    features, allowed = occupancy_inputs(views, model.size)
    return StartInputs(views, allowed, features)


def boxed_start(build: Callable[[torch.Tensor], Any], scene: Scene, prepare: Callable[[Any, Scene], StartInputs | str],
                start: Callable[[Any, StartInputs | str], StartReport]) -> tuple[Any, StartReport]:
    """A voxel grid for ``scene`` in a box that holds what its silhouettes allow, started by ``start(model, inputs)``.

    ``build(bounds)`` makes the grid (the scratch config and seed) in a (2, 3) box; ``prepare(model, scene)`` reads it
    (:func:`hull_inputs`, :func:`network_inputs`), and ``start`` gets what it read. The grid is made in the scene's box;
    where the points a start may fill (the visual hull with a margin) do not reach its faces, as on a NeRF-synthetic
    scene whose box is several times its object, it is made again in their bounding box, with the same number of
    voxels, and read again. In the scene's box the coarse stage spends its voxels on empty space and grows faint density
    near the faces, and the fine stage's box comes out nearly the whole scene box: on lego at 100 x 100 both starts ended
    3-3.5 dB below scratch (BENCHMARKS.md). The network also learned shapes on generated scenes, whose box just holds
    the object; on those the two boxes are the same and the grid is read once. A grid the start leaves untouched keeps
    the scene's box. Returns the grid and ``start``'s report (``figures["box"]``: the box used; ``build_s`` includes
    finding it).
    """
    t0 = time.perf_counter()
    model = build(scene.bounds)
    inputs = prepare(model, scene)
    tightened = False
    if not isinstance(inputs, str) and bool(inputs.allowed.any()):
        kept = inputs.views.points[inputs.allowed.reshape(-1)]
        box = torch.stack([kept.amin(0), kept.amax(0)])
        if not torch.equal(box, model.bounds):
            model, tightened = build(box), True
            inputs = prepare(model, scene)
    report = start(model, inputs)
    if tightened and not report.applied:  # no start: the grid keeps the scene's box, as a scratch fit would
        model, tightened = build(scene.bounds), False
    figures = {**report.figures, "box": [[round(float(v), 4) for v in row] for row in model.bounds.tolist()],
               "box_from_silhouettes": tightened}
    return model, dataclasses.replace(report, build_s=round(time.perf_counter() - t0, 4), figures=figures)


def learned_start_config(config, given: Collection[str] = ()):
    """``config`` (a resolved ``VoxelGridConfig``) as a learned start fits it: :data:`COARSE_ITERS` coarse steps, unless
    ``coarse_iters`` is among the ``given`` settings (a user's ``--set``), which win."""
    return config if "coarse_iters" in given else dataclasses.replace(config, coarse_iters=COARSE_ITERS)


def learned_start(build: Callable[[torch.Tensor], Any], scene: Scene, background: torch.Tensor, net: OccupancyNet, *,
                  threshold: float = THRESHOLD) -> tuple[Any, StartReport]:
    """:func:`learned_grid_start` in the silhouettes' box (:func:`boxed_start`): what ``--init occupancy`` fits."""
    return boxed_start(build, scene, network_inputs,
                       lambda model, inputs: learned_grid_start(model, scene, background, net, threshold=threshold, inputs=inputs))


def learned_grid_start(model, scene: Scene, background: torch.Tensor, net: OccupancyNet, *,
                       threshold: float = THRESHOLD, inputs: StartInputs | str | None = None) -> StartReport:
    """Start ``model``'s coarse stage from ``net``'s occupancy of ``scene`` (the carve's densities and mean colours on
    the points it fills); leave it untouched, with the reason, where the scene cannot be (as :func:`carve_blocker`).
    ``inputs``: ``model``'s :func:`network_inputs` when already read."""
    t0 = time.perf_counter()
    if inputs is None:
        inputs = network_inputs(model, scene)
    if isinstance(inputs, str):
        return StartReport(False, "occupancy", f"no learned start: {inputs}", round(time.perf_counter() - t0, 4), {})
    views, feats, allowed = inputs.views, inputs.features, inputs.allowed
    with torch.no_grad():
        occupied = ((torch.sigmoid(net.to(feats.device)(feats)) >= threshold) & allowed).reshape(-1)
    feats = feats.reshape(N_FEATURES, -1)
    # carve.start_colours from the features: their mean colour where a view shows the point on foreground
    on_foreground = (occupied & (feats[9] > 0))[:, None]
    load_occupied_start(model, occupied, torch.where(on_foreground, feats[5:8].t(), background.to(feats.device)))
    fraction = float(occupied.float().mean())
    return StartReport(True, "occupancy", f"the coarse grid starts from the learned occupancy ({100 * fraction:.1f}% of it)",
                       round(time.perf_counter() - t0, 4), {"occupied_fraction": round(fraction, 4),
                                                            "threshold": threshold, "views": views.images.shape[0]})
