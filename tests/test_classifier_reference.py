"""classifier.reference: the ImageNet reference score, its leave-one-out scale and the fused threshold."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from classifier.config import TrainConfig
from classifier.predict import _shrink, fit_feature_stats, scene_scores
from classifier.reference import (REFERENCE_SIZE, ReferenceModel, fit_reference, fused_threshold, leave_one_out_scores,
                                  spaced_views, view_descriptors)
from classifier.store import REFERENCE_PREFIX, WEIGHTS_FILE, ClassifierError, load_classifier, save_classifier
from nerfmeta.errors import ConfigError
from nerfmeta.io import load_tensors, save_tensors, sha256_file
from nerfmeta.metrics import LpipsUnavailable, load_imagenet_trunk


def _scenes(seed: int = 0, per_class: int = 4, classes: int = 3, dim: int = 5, views: int = 3) -> tuple[list[torch.Tensor], torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    centres = 3.0 * torch.randn(classes, dim, generator=g, dtype=torch.float64)
    scenes, labels = [], []
    for c in range(classes):
        for _ in range(per_class):
            mean = centres[c] + torch.randn(dim, generator=g, dtype=torch.float64)
            scenes.append(mean + 0.3 * torch.randn(views, dim, generator=g, dtype=torch.float64))
            labels.append(c)
    return scenes, torch.tensor(labels)


def test_leave_one_out_scores_match_a_refit_without_each_scene():
    scenes, labels = _scenes()
    got = leave_one_out_scores(scenes, labels, 3, shrinkage=0.1)
    means = np.stack([s.mean(0).numpy() for s in scenes])
    y = labels.numpy()
    for i in range(len(scenes)):
        keep = np.arange(len(scenes)) != i
        m, yk = means[keep], y[keep]
        centres = np.stack([m[yk == c].mean(0) for c in range(3)])
        dev = m - centres[yk]
        cov = _shrink(torch.from_numpy(dev.T @ dev / (m.shape[0] - 3)), 0.1).numpy()
        d = [float((means[i] - centres[c]) @ np.linalg.solve(cov, means[i] - centres[c])) for c in range(3)]
        assert got[i].item() == pytest.approx(-min(d), rel=1e-9)


def test_fit_reference_scale_is_that_of_the_leave_one_out_scores_and_scores_outliers_low():
    scenes, labels = _scenes(views=6)
    model, loo = fit_reference([s.float() for s in scenes], labels, 3, shrinkage=0.05)
    assert torch.allclose(model.norm.double(), torch.tensor([loo.mean(), loo.std()], dtype=torch.float64), rtol=1e-5)
    one = scenes[0][:1].float()
    assert model.z(one) == pytest.approx(model.z(one.repeat(6, 1)), rel=1e-6)  # no widening for scenes with fewer views
    known_z = model.z(scenes[0].float())
    far = scenes[0].float() + 25.0  # the same views, moved far from every class
    assert model.z(far) < known_z - 5.0


def test_fused_threshold_is_the_quantile_of_every_pairwise_sum():
    val = torch.tensor([0.0, 1.0])
    z = torch.tensor([-1.0, 0.0, 2.0])  # sums: -1, 0, 2, 0, 1, 3
    assert fused_threshold(val, z, 1.0) == -1.0
    assert fused_threshold(val, z, 0.5) == pytest.approx(float(torch.quantile(torch.tensor([-1.0, 0, 2, 0, 1, 3]), 0.5)))
    with pytest.raises(ValueError):
        fused_threshold(torch.tensor([]), z, 0.9)


def test_fused_score_needs_combined_a_reference_model_and_descriptors():
    scenes, labels = _scenes(views=4)
    feats = torch.cat(scenes).float()
    index = torch.arange(len(scenes)).repeat_interleave(4)
    stats = fit_feature_stats(feats, labels.repeat_interleave(4), index, 3, 0.05)
    stats = replace(stats, class_scale=torch.ones(3), score_norm=torch.tensor([0.0, 1.0, 0.0, 1.0]))
    logits = torch.randn(4, 3)
    assert "fused" not in scene_scores(logits, scenes[0].float(), stats, scenes[0].float())
    model, _ = fit_reference([s.float() for s in scenes], labels, 3, 0.05)
    with_ref = replace(stats, reference=model)
    assert "fused" not in scene_scores(logits, scenes[0].float(), with_ref)
    scores = scene_scores(logits, scenes[0].float(), with_ref, scenes[0].float())
    assert scores["fused"] == pytest.approx(scores["combined"] + model.z(scenes[0].float()))


def test_spaced_views_takes_at_most_sixteen_evenly_spaced_views_as_training_did():
    views = torch.arange(40.0).view(40, 1)
    assert spaced_views(views[:16]).flatten().tolist() == list(range(16))
    picked = spaced_views(views).flatten()
    assert picked.numel() == 16 and picked[0] == 0 and picked[-1] == 39
    assert picked.tolist() == torch.linspace(0, 39, 16).round().tolist()


def test_limit_scenes_keeps_evenly_spaced_scenes_of_each_class_with_all_their_views():
    from classifier.data import ViewSet

    scene_labels = [0, 1, 0, 0, 1, 0, 0]  # five scenes of class 0, two of class 1
    index = torch.tensor([k for k in range(7) for _ in range(2)])
    views = ViewSet(torch.arange(14).view(14, 1, 1, 1).to(torch.uint8), torch.tensor(scene_labels).repeat_interleave(2), index,
                    tuple(f"s{k}" for k in range(7)))
    got = views.limit_scenes(3)
    # class 0 scenes 0, 2, 3, 5, 6 -> evenly spaced 0, 3, 6; class 1 keeps both (1, 4)
    assert got.scenes == ("s0", "s1", "s3", "s4", "s6")
    assert got.scene_index.tolist() == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4]
    assert got.views.flatten().tolist() == [0, 1, 2, 3, 6, 7, 8, 9, 12, 13]
    assert views.limit_scenes(9).scenes == views.scenes


def test_reference_is_left_out_only_where_auto_cannot_use_it():
    from classifier.config import CLASS_SCORE_TRAIN_SCENES
    from classifier.train import reference_skip_reason

    enough = CLASS_SCORE_TRAIN_SCENES
    assert "class_mahalanobis" in reference_skip_reason(TrainConfig(), enough)
    assert reference_skip_reason(TrainConfig(), enough - 1) is None
    assert reference_skip_reason(TrainConfig(score="fused"), enough) is None
    assert reference_skip_reason(TrainConfig(reference="none"), enough) is None


def test_reference_settings_are_validated():
    with pytest.raises(ConfigError, match="--reference 'resnet'"):
        TrainConfig(reference="resnet").validate()
    with pytest.raises(ConfigError, match="--reference-keep-fraction"):
        TrainConfig(reference_keep_fraction=0.2).validate()


def _trunk_or_skip():
    try:
        return load_imagenet_trunk("vgg")
    except LpipsUnavailable as err:  # scripts/setup.sh installs them; a bare checkout may not have them
        pytest.skip(str(err))


def test_view_descriptors_are_five_unit_blocks_and_composite_on_the_background():
    trunk = _trunk_or_skip()
    g = torch.Generator().manual_seed(0)
    views = torch.rand(3, 4, 32, 32, generator=g)
    views[:, :3] *= views[:, 3:4]  # premultiplied
    desc = view_descriptors(trunk, views, (1.0, 1.0, 1.0))
    assert desc.shape == (3, 64 + 128 + 256 + 512 + 512)
    start = 0
    for width in (64, 128, 256, 512, 512):
        assert torch.allclose(desc[:, start : start + width].norm(dim=1), torch.ones(3), atol=1e-5)
        start += width
    empty = torch.zeros(1, 4, 32, 32)  # fully transparent: the background alone
    white = torch.cat([torch.ones(1, 3, REFERENCE_SIZE, REFERENCE_SIZE), torch.ones(1, 1, REFERENCE_SIZE, REFERENCE_SIZE)], 1)
    assert torch.allclose(view_descriptors(trunk, empty, (1.0, 1.0, 1.0)), view_descriptors(trunk, white, (0.0, 0.0, 0.0)), atol=1e-5)
    with pytest.raises(ValueError, match="premultiplied RGBA"):
        view_descriptors(trunk, torch.zeros(2, 3, 8, 8), (1.0, 1.0, 1.0))


@pytest.fixture(scope="module")
def fused_classifier(tmp_path_factory: pytest.TempPathFactory) -> Path:
    _trunk_or_skip()
    from nerfmeta.collection.generate import CollectionConfig, generate_collection

    from classifier.train import train_classifier

    root = tmp_path_factory.mktemp("refcoll")
    generate_collection(CollectionConfig(categories=("chair", "mug", "airplane"), scenes_per_category=3, views=4, test_views=1,
                                         resolution=16, seed=3, val_fraction=0.34, test_fraction=0.0), root / "coll")
    out = root / "clf"
    train_classifier(TrainConfig(input_size=16, batch_size=4, epochs=1, holdout_categories=("airplane",)), root / "coll", out)
    return out


def test_a_trained_classifier_decides_with_fused_and_keeps_its_reference(fused_classifier: Path):
    import json

    doc = json.loads((fused_classifier / "classifier.json").read_text())
    assert doc["unknown"]["score"] == "fused" and "fused" in doc["validation"]["scores"]
    assert 0 < doc["training"]["calibration_time_s"] < doc["training"]["wall_time_s"]  # the trunk's cost is reported
    assert doc["reference"] == {"net": "vgg16", "used": True, "size": 128, "views_per_scene": 16, "train_scenes_per_category": 16}
    clf = load_classifier(fused_classifier)
    assert isinstance(clf.stats.reference, ReferenceModel) and clf.stats.reference.means.shape == (2, 1472)
    from safetensors.torch import load_file

    saved = sorted(k for k in load_file(str(fused_classifier / "model.safetensors")) if k.startswith("reference_stats."))
    assert saved == ["reference_stats.between", "reference_stats.means", "reference_stats.norm"]  # no unused view spread


def test_a_half_precision_save_keeps_the_reference_statistics_exact(fused_classifier: Path, tmp_path: Path):
    """The zoo ships its classifier in float16; the fused threshold was calibrated on float32 statistics."""
    clf = load_classifier(fused_classifier)
    half = load_classifier(save_classifier(tmp_path / "half", clf, weights_dtype=torch.float16).parent)
    for name in ("means", "between", "norm"):
        got, want = getattr(half.stats.reference, name), getattr(clf.stats.reference, name)
        assert got.dtype == torch.float32 and torch.equal(got, want), name


def test_fused_classifier_without_its_reference_tensors_is_refused(fused_classifier: Path, tmp_path: Path):
    import json
    import shutil

    copy = tmp_path / "clf"
    shutil.copytree(fused_classifier, copy)
    weights = copy / WEIGHTS_FILE
    tensors = {k: v for k, v in load_tensors(weights).items() if not k.startswith(REFERENCE_PREFIX)}
    save_tensors(weights, tensors)
    doc = json.loads((copy / "classifier.json").read_text())
    doc["weights"]["sha256"] = sha256_file(weights)
    (copy / "classifier.json").write_text(json.dumps(doc))
    with pytest.raises(ClassifierError, match="calibrates fused"):
        load_classifier(copy)


def test_training_without_the_weights_warns_and_leaves_fused_out(tmp_path: Path, monkeypatch, caplog):
    from nerfmeta.collection.generate import CollectionConfig, generate_collection

    from classifier.train import train_classifier

    generate_collection(CollectionConfig(categories=("chair", "mug"), scenes_per_category=2, views=3, test_views=1,
                                         resolution=16, seed=4, val_fraction=0.5, test_fraction=0.0), tmp_path / "coll")
    monkeypatch.setenv("NERFMETA_LPIPS_DIR", str(tmp_path / "no-weights"))
    doc = train_classifier(TrainConfig(input_size=16, batch_size=4, epochs=1), tmp_path / "coll", tmp_path / "clf")
    assert doc["reference"]["used"] is False and "no-weights" in doc["reference"]["why"]
    assert "fused" not in doc["unknown"]["thresholds"] and doc["unknown"]["score"] == "combined"
    assert any("no fused score" in r.message for r in caplog.records)


def test_fused_classifier_without_the_weights_decides_with_combined_and_says_so(fused_classifier: Path, tmp_path: Path,
                                                                                monkeypatch, caplog):
    from classifier.inputs import read_scene_views
    from classifier.store import cached_trunk, classify_views

    clf = load_classifier(fused_classifier)
    views = read_scene_views(next((fused_classifier.parent / "coll" / "chair").iterdir()), size=16, background=clf.meta.background)
    assert classify_views(clf, views).score_name == "fused"
    cached_trunk.cache_clear()
    monkeypatch.setenv("NERFMETA_LPIPS_DIR", str(tmp_path / "gone"))
    try:
        prediction = classify_views(clf, views)
    finally:
        cached_trunk.cache_clear()
    assert prediction.score_name == "combined" and prediction.threshold == clf.meta.thresholds["combined"]
    assert any("instead of 'fused'" in r.message for r in caplog.records)
