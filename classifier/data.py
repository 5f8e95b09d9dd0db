"""Views as model inputs: premultiplied RGBA at the input size, augmentations, normalisation.

Internally a view is **premultiplied** RGBA ``(4, S, S)``: colour times alpha, then alpha. That
is what a loaded scene gives back once its compositing background is taken out
(``rgb_composited - (1 - alpha) * background``), it interpolates correctly under resizing and
affine warps (transparent padding is simply zero), and it composites on any colour in one
step: ``rgb = premultiplied + (1 - alpha) * colour``. Views without an alpha channel (photos)
have alpha 1 everywhere.

The training set (:class:`ViewSet`) is read from a generated collection with
:func:`nerfmeta.data.load_scene`; all views of a scene (its ``train`` and ``test`` view splits)
are used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import torch
import torch.nn.functional as F

from nerfmeta.collection.generate import Collection, SceneRecord
from nerfmeta.compat import import_torchvision
from nerfmeta.data import Scene, load_scene

from classifier.config import AugmentConfig

RGB = tuple[float, float, float]


def scene_premultiplied(scene: Scene) -> torch.Tensor:
    """A loaded scene's views as premultiplied RGBA.

    Returns:
        (n_views, 4, H, W) float32: ``alpha * rgb`` and ``alpha`` (1 when the files had none).
    """
    images = scene.images.permute(0, 3, 1, 2).float()  # (N, 3, H, W) composited on scene.background
    if scene.alphas is None or scene.background is None:
        return torch.cat([images, torch.ones_like(images[:, :1])], dim=1)
    alpha = scene.alphas.float().unsqueeze(1)
    bg = torch.tensor(scene.background, dtype=images.dtype).view(1, 3, 1, 1)
    premultiplied = (images - (1.0 - alpha) * bg).clamp(0.0, 1.0)
    return torch.cat([torch.minimum(premultiplied, alpha), alpha], dim=1)


def to_input_size(views: torch.Tensor, size: int) -> torch.Tensor:
    """Pad views to a square with transparent pixels (centred), then resize to ``size`` x ``size``.

    Padding instead of cropping keeps the whole object in view whatever the aspect ratio.
    Shrinking uses antialiased bilinear filtering.

    Args:
        views: (n, 4, H, W) premultiplied RGBA.
        size: output side in pixels.

    Returns:
        (n, 4, size, size).
    """
    _, _, h, w = views.shape
    side = max(h, w)
    if h != w:
        top, left = (side - h) // 2, (side - w) // 2
        views = F.pad(views, (left, side - w - left, top, side - h - top))
    if side != size:
        views = F.interpolate(views, size=(size, size), mode="bilinear", antialias=side > size, align_corners=False)
    return views.clamp(0.0, 1.0)


def composite(views: torch.Tensor, background: RGB | torch.Tensor) -> torch.Tensor:
    """Premultiplied RGBA on a background colour.

    Args:
        views: (n, 4, H, W) premultiplied RGBA.
        background: one RGB for all views, or (n, 3) one colour per view.

    Returns:
        (n, 3, H, W) RGB.
    """
    bg = torch.as_tensor(background, dtype=views.dtype, device=views.device)
    bg = bg.view(1, 3, 1, 1) if bg.dim() == 1 else bg.view(-1, 3, 1, 1)
    return views[:, :3] + (1.0 - views[:, 3:4]) * bg


def normalize(rgb: torch.Tensor, mean: RGB, std: RGB) -> torch.Tensor:
    """(n, 3, H, W) RGB in [0, 1] -> ``(rgb - mean) / std`` per channel."""
    m = torch.tensor(mean, dtype=rgb.dtype, device=rgb.device).view(1, 3, 1, 1)
    s = torch.tensor(std, dtype=rgb.dtype, device=rgb.device).view(1, 3, 1, 1)
    return (rgb - m) / s


def _transforms():
    """torchvision's v2 functional transforms (imported through the compat shim)."""
    import_torchvision()
    import torchvision.transforms.v2.functional as TF

    return TF


def _uniform(generator: torch.Generator, lo: float, hi: float) -> float:
    return lo + (hi - lo) * float(torch.rand((), generator=generator))


def augment_views(
    views: torch.Tensor, config: AugmentConfig, background: RGB, generator: torch.Generator
) -> torch.Tensor:
    """Randomly transform training views and composite them (torchvision functional transforms).

    Per view, with parameters drawn from ``generator``: an affine warp (zoom in
    ``config.scale``, shift, small rotation; transparent fill), a left-right flip, compositing
    on a random uniform colour (probability ``config.background``) or on ``background``, then
    brightness, contrast, saturation and hue jitter.

    Args:
        views: (n, 4, S, S) premultiplied RGBA in [0, 1].
        config: the augmentation ranges.
        background: the training background RGB.
        generator: source of every random draw (CPU generator).

    Returns:
        (n, 3, S, S) RGB in [0, 1].
    """
    TF = _transforms()
    size = views.shape[-1]
    out = torch.empty(views.shape[0], 3, *views.shape[-2:], dtype=views.dtype)
    for i in range(views.shape[0]):
        view = views[i]
        scale = math.exp(_uniform(generator, math.log(config.scale[0]), math.log(config.scale[1])))
        shift = [round(_uniform(generator, -config.translate, config.translate) * size) for _ in range(2)]
        angle = _uniform(generator, -config.rotate_degrees, config.rotate_degrees)
        if scale != 1.0 or shift != [0, 0] or angle != 0.0:
            view = TF.affine(view, angle=angle, translate=shift, scale=scale, shear=[0.0, 0.0],
                             interpolation=TF.InterpolationMode.BILINEAR, fill=0.0)
        if float(torch.rand((), generator=generator)) < config.hflip:
            view = TF.horizontal_flip(view)
        if float(torch.rand((), generator=generator)) < config.background:
            bg = torch.rand(3, generator=generator)
        else:
            bg = torch.tensor(background)
        rgb = composite(view[None], bg)[0].clamp(0.0, 1.0)
        if config.brightness > 0:
            rgb = TF.adjust_brightness(rgb, _uniform(generator, 1 - config.brightness, 1 + config.brightness))
        if config.contrast > 0:
            rgb = TF.adjust_contrast(rgb, _uniform(generator, 1 - config.contrast, 1 + config.contrast))
        if config.saturation > 0:
            rgb = TF.adjust_saturation(rgb, _uniform(generator, 1 - config.saturation, 1 + config.saturation))
        if config.hue > 0:
            rgb = TF.adjust_hue(rgb, _uniform(generator, -config.hue, config.hue))
        out[i] = rgb
    return out.clamp(0.0, 1.0)


def chimera_partners(labels: torch.Tensor, count: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Draw ``count`` pairs of view indices whose two views belong to different classes.

    The first view of a pair is uniform over all views; the second is uniform over the views of a
    class drawn uniformly among the *other* classes present in ``labels``.

    Returns:
        (first, second): two (count,) index tensors into ``labels``.

    Raises:
        ValueError: fewer than two classes in ``labels`` (no pair can mix two).
    """
    classes = torch.unique(labels)
    if classes.numel() < 2:
        raise ValueError("chimera outliers need views of at least two classes")
    members = [torch.nonzero(labels == c).flatten() for c in classes]
    position = {int(c): k for k, c in enumerate(classes)}
    first = torch.randint(len(labels), (count,), generator=generator)
    shift = torch.randint(1, classes.numel(), (count,), generator=generator)
    second = torch.empty(count, dtype=torch.long)
    for i in range(count):
        pool = members[(position[int(labels[first[i]])] + int(shift[i])) % classes.numel()]
        second[i] = pool[int(torch.randint(len(pool), (), generator=generator))]
    return first, second


def chimera_views(first: torch.Tensor, second: torch.Tensor, generator: torch.Generator, cut: tuple[float, float] = (0.35, 0.65)) -> torch.Tensor:
    """Join two views along a random straight cut: one side from ``first``, the other from ``second``.

    An object made of two categories' halves is an object of no category: trained towards a
    uniform softmax (outlier exposure, Hendrycks et al. 2019, with synthesised outliers in place of an
    auxiliary dataset, as in CutMix), it teaches the network to be unsure of shapes that only share
    parts with the known ones. Premultiplied RGBA joins by selection, so each side keeps its exact pixels.

    Args:
        first, second: (n, 4, S, S) premultiplied RGBA views.
        generator: draws, per pair, the cut's direction (rows or columns), its position (a fraction in
            ``cut`` of the image) and which view lies on the low side.

    Returns:
        (n, 4, S, S) premultiplied RGBA.
    """
    n, _, h, w = first.shape
    out = torch.empty_like(first)
    for i in range(n):
        vertical = bool(torch.rand((), generator=generator) < 0.5)
        frac = _uniform(generator, *cut)
        a, b = (first[i], second[i]) if torch.rand((), generator=generator) < 0.5 else (second[i], first[i])
        out[i] = b
        if vertical:
            k = round(frac * w)
            out[i, :, :, :k] = a[:, :, :k]
        else:
            k = round(frac * h)
            out[i, :, :k] = a[:, :k]
    return out


@dataclass(frozen=True)
class ViewSet:
    """Views of several scenes, ready for training or evaluation.

    Attributes:
        views: (n_views, 4, S, S) uint8 premultiplied RGBA (kept small in memory).
        labels: (n_views,) class index of each view (-1 for categories outside the classes).
        scene_index: (n_views,) index into ``scenes`` of each view.
        scenes: the scene records, in order.
    """

    views: torch.Tensor
    labels: torch.Tensor
    scene_index: torch.Tensor
    scenes: tuple[SceneRecord, ...]

    def __len__(self) -> int:
        return int(self.views.shape[0])

    def float_views(self, idx: torch.Tensor | slice) -> torch.Tensor:
        """(k, 4, S, S) float32 in [0, 1] of the selected views."""
        return self.views[idx].float().div_(255.0)

    def scene_views(self, k: int) -> torch.Tensor:
        """Indices of the views of scene ``k``."""
        return torch.nonzero(self.scene_index == k).flatten()

    def limit_scenes(self, per_class: int) -> "ViewSet":
        """At most ``per_class`` scenes of each label (evenly spaced in scene order), with all their views; scenes
        keep their order and are renumbered."""
        labels = [int(self.labels[self.scene_views(k)[0]]) for k in range(len(self.scenes))]
        keep: list[int] = []
        for c in sorted(set(labels)):
            ks = [k for k, label in enumerate(labels) if label == c]
            keep += [ks[int(i)] for i in evenly_spaced(len(ks), per_class)]
        keep.sort()
        number = torch.full((len(self.scenes),), -1, dtype=torch.long)
        number[keep] = torch.arange(len(keep))
        idx = torch.nonzero(number[self.scene_index] >= 0).flatten()
        return ViewSet(self.views[idx], self.labels[idx], number[self.scene_index[idx]], tuple(self.scenes[k] for k in keep))

    def subset(self, views_per_scene: int) -> "ViewSet":
        """``views_per_scene`` evenly spaced views of every scene (all of them when a scene has fewer)."""
        keep = [self.labels[:0]]
        for k in range(len(self.scenes)):
            idx = self.scene_views(k)
            keep.append(idx[evenly_spaced(idx.numel(), views_per_scene)])
        keep = torch.cat(keep)
        return ViewSet(self.views[keep], self.labels[keep], self.scene_index[keep], self.scenes)


def evenly_spaced(n: int, count: int) -> torch.Tensor:
    """Indices of ``count`` evenly spaced items of ``n`` (first and last included), or all ``n`` when ``n <= count``."""
    if n <= count:
        return torch.arange(n)
    return torch.linspace(0, n - 1, count).round().long()


def to_uint8(views: torch.Tensor) -> torch.Tensor:
    return torch.floor(views.clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8)


def load_view_set(
    collection: Collection,
    records: Sequence[SceneRecord],
    categories: Sequence[str],
    *,
    size: int,
    background: RGB,
    progress: Callable[[SceneRecord], None] | None = None,
) -> ViewSet:
    """Read every view of the given scenes of a collection.

    Args:
        collection: the collection the records belong to.
        records: scenes to read.
        categories: class names; a scene of another category gets label -1.
        size: input size the views are padded and resized to.
        background: RGB the files are composited on when read (taken out again, see module doc).
        progress: called after each scene.
    """
    index = {c: k for k, c in enumerate(categories)}
    chunks, labels, scene_ids = [], [], []
    for k, record in enumerate(records):
        scene = load_scene(collection.scene_path(record), background=background)
        views = to_input_size(scene_premultiplied(scene), size)
        chunks.append(to_uint8(views))
        labels.append(torch.full((views.shape[0],), index.get(record.category, -1), dtype=torch.long))
        scene_ids.append(torch.full((views.shape[0],), k, dtype=torch.long))
        if progress is not None:
            progress(record)
    if not chunks:
        return ViewSet(torch.zeros(0, 4, size, size, dtype=torch.uint8), torch.zeros(0, dtype=torch.long),
                       torch.zeros(0, dtype=torch.long), ())
    return ViewSet(torch.cat(chunks), torch.cat(labels), torch.cat(scene_ids), tuple(records))
