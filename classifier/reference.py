"""A second opinion on "unknown" from ImageNet features: the ``fused`` score.

The ResNet is trained on the collection alone; with a dozen scenes per category it knows little about
what else exists, and a sofa shaped like its cars sits inside the cars' features (issue 14). A frozen
ImageNet network has seen a thousand categories. Its features of a scene's views, averaged, are
modelled per known category as the ResNet's are (:class:`~classifier.predict.FeatureStats`: class
means, a shrunk covariance of scene means; but *not* widened for scenes with fewer views, see
:func:`fit_reference`), giving ``reference``: minus the squared Mahalanobis distance to the nearest
known category.

Because the trunk is not trained on the collection, *every* known scene of the collection (training
and validation) can be scored leave-one-out, by statistics fitted without it: dozens of unbiased known
scores instead of the handful of validation scenes the ResNet's scores are calibrated on. They give the
reference score's scale (:class:`ReferenceModel` ``norm``), and the ``fused`` score is::

    fused = combined + (reference - norm[0]) / norm[1]

both halves in units of their known spread. Its threshold is the ``1 - keep_fraction`` quantile of
every sum of a known validation scene's ``combined`` and a known scene's leave-one-out reference
z-score (:func:`fused_threshold`): the two halves treated as independent, which spends all the scenes
the reference half has.

The trunk is torchvision's VGG16 ``features`` with the ImageNet weights LPIPS uses, installed at set-up
(:func:`nerfmeta.metrics.load_imagenet_trunk`; nothing is downloaded). A view's descriptor is the
spatial mean of each of VGG16's five ReLU stages (relu1_2 ... relu5_3, the LPIPS taps), each L2-normalised,
concatenated (64 + 128 + 256 + 512 + 512 = 1472 values), from the view composited on the classifier's
background and resized to :data:`REFERENCE_SIZE` pixels.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from classifier.config import IMAGENET_MEAN, IMAGENET_STD
from classifier.data import evenly_spaced
from classifier.predict import ReferenceModel, _shrink, fit_feature_stats, reference_score

__all__ = ["ReferenceModel", "fit_reference", "fused_threshold", "leave_one_out_scores", "load_trunk",
           "reference_score", "spaced_views", "view_descriptors"]

REFERENCE_SIZE = 128
"""Side the views are resized to for the trunk (design seeds: AUROC 0.97-1.00 at 128 px, 0.95-0.98 at 64)."""

REFERENCE_VIEWS = 16
"""Views per known scene whose descriptors fit the reference statistics (evenly spaced; VGG16 at 128 px costs about
0.13 s a view on one core of the 2-core CPU)."""

REFERENCE_SCENES = 16
"""Training scenes per known category whose descriptors fit the reference statistics (evenly spaced; every validation
scene is used too). Bounds the trunk's cost at training: at 40 scenes per category all 216 known scenes took about
760 s more beside a 1150 s training (a loaded machine); a 12-per-category collection (10 training scenes each) is
unaffected."""

VGG16_TAPS = (3, 8, 15, 22, 29)
"""Indices in torchvision's ``vgg16().features`` of the ReLUs whose outputs are pooled (relu1_2 ... relu5_3)."""


def load_trunk(net: str = "vgg16") -> torch.nn.Sequential:
    """The frozen ImageNet trunk (raises :class:`~nerfmeta.metrics.LpipsUnavailable` when its weights are not installed)."""
    if net != "vgg16":
        raise ValueError(f"unknown reference network {net!r}; expected vgg16")
    from nerfmeta.metrics import load_imagenet_trunk

    return load_imagenet_trunk("vgg")


@torch.no_grad()
def view_descriptors(trunk: torch.nn.Sequential, views: torch.Tensor, background: tuple[float, float, float],
                     size: int = REFERENCE_SIZE, batch_size: int = 32) -> torch.Tensor:
    """(n, 1472) descriptors of (n, 4, S, S) premultiplied RGBA views (see the module docstring)."""
    if views.dim() != 4 or views.shape[1] != 4:
        raise ValueError(f"views must be (n, 4, S, S) premultiplied RGBA, got {tuple(views.shape)}")
    bg = torch.tensor(background, dtype=torch.float32).view(1, 3, 1, 1)
    mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    out = []
    for start in range(0, views.shape[0], batch_size):
        v = views[start : start + batch_size].float()
        rgb = (v[:, :3] + (1.0 - v[:, 3:4]) * bg).clamp(0.0, 1.0)
        if rgb.shape[-1] != size or rgb.shape[-2] != size:
            rgb = F.interpolate(rgb, size=(size, size), mode="bilinear", align_corners=False)
        h = (rgb - mean) / std
        pooled = []
        for i, layer in enumerate(trunk):
            h = layer(h)
            if i in VGG16_TAPS:
                pooled.append(F.normalize(h.mean(dim=(2, 3)), dim=1))
            if i >= VGG16_TAPS[-1]:
                break
        out.append(torch.cat(pooled, dim=1))
    return torch.cat(out)


def spaced_views(views: torch.Tensor, count: int = REFERENCE_VIEWS) -> torch.Tensor:
    """At most ``count`` evenly spaced views of ``views`` (n, ...), as the training scenes' descriptors were taken; a
    scene classified from hundreds of views pays the trunk for ``count`` of them."""
    return views[evenly_spaced(views.shape[0], count)]


def leave_one_out_scores(scenes: list[torch.Tensor], labels: torch.Tensor, n_classes: int, shrinkage: float) -> torch.Tensor:
    """(n_scenes,) reference score of each known scene under statistics fitted without it.

    The scene's own class mean and the scene-mean covariance are refitted without it; the view covariance
    is kept (one scene's views barely move it, and a left-out scene has the reference view count, so the
    view covariance does not enter its distance). A class left with no scene is skipped for that scene.

    Args:
        scenes: per scene, (n_views, dim) descriptors.
        labels: (n_scenes,) class of each scene.
        n_classes: number of classes.
        shrinkage: as ``TrainConfig.covariance_shrinkage``.
    """
    if len(scenes) < 2:
        raise ValueError("leave-one-out scores need at least two scenes")
    means = torch.stack([s.double().mean(dim=0) for s in scenes])
    labels = labels.long()
    out = torch.empty(len(scenes), dtype=torch.float64)
    for i in range(len(scenes)):
        keep = torch.ones(len(scenes), dtype=torch.bool)
        keep[i] = False
        m, y = means[keep], labels[keep]
        present = [c for c in range(n_classes) if bool((y == c).any())]
        centres = torch.stack([m[y == c].mean(dim=0) for c in present])
        index = torch.tensor([present.index(int(c)) for c in y])
        dev = m - centres[index]
        between = _shrink(dev.T @ dev / max(1, m.shape[0] - len(present)), shrinkage)
        diff = means[i][None, :] - centres
        solved = torch.linalg.solve(between, diff.T)  # (dim, n_present)
        out[i] = -(diff.T * solved).sum(dim=0).min()
    return out


def fit_reference(
    scenes: list[torch.Tensor], labels: torch.Tensor, n_classes: int, shrinkage: float
) -> tuple[ReferenceModel, torch.Tensor]:
    """:class:`ReferenceModel` of the known scenes' descriptors (every known scene the collection has, training and
    validation alike: the trunk was not trained on them), and their (n_scenes,) leave-one-out reference scores."""
    features = torch.cat(scenes)
    index = torch.cat([torch.full((s.shape[0],), k, dtype=torch.long) for k, s in enumerate(scenes)])
    view_labels = torch.cat([torch.full((s.shape[0],), int(c), dtype=torch.long) for s, c in zip(scenes, labels)])
    # No widening for scenes with fewer views: the threshold comes from leave-one-out scores of scenes with all their
    # views, and widening only for new scenes moved every new scene, held-out ones too, above it (design seeds:
    # held-out flagged 42-58 % with it, 83-100 % without). So only the class means and the scene-mean spread are kept.
    stats = fit_feature_stats(features, view_labels, index, n_classes, shrinkage)
    loo = leave_one_out_scores(scenes, labels, n_classes, shrinkage)
    spread = float(loo.std()) if loo.numel() > 1 else 1.0
    norm = torch.tensor([float(loo.mean()), max(spread, 1e-6)], dtype=torch.float32)
    return ReferenceModel(stats.means, stats.between, norm), loo


def fused_threshold(val_combined: torch.Tensor, known_reference_z: torch.Tensor, keep_fraction: float) -> float:
    """The ``1 - keep_fraction`` quantile of every sum ``val_combined[i] + known_reference_z[j]``.

    Args:
        val_combined: (n_val,) ``combined`` of the known validation scenes.
        known_reference_z: (n_known,) leave-one-out reference z-scores of the known scenes.
        keep_fraction: in (0, 1].
    """
    if val_combined.numel() < 1 or known_reference_z.numel() < 1:
        raise ValueError("the fused threshold needs at least one scene of each kind")
    sums = (val_combined.double().flatten()[:, None] + known_reference_z.double().flatten()[None, :]).flatten()
    return float(torch.quantile(sums, 1.0 - keep_fraction))
