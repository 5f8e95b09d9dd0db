"""classifier.store: save/load round trip gives identical predictions; bad folders are one-line errors."""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from classifier.model import build_model, load_pretrained
from classifier.predict import FeatureStats, scene_scores
from classifier.store import (
    META_FILE,
    WEIGHTS_FILE,
    Classifier,
    ClassifierError,
    ClassifierMeta,
    classify_views,
    load_classifier,
    model_inputs,
    save_classifier,
    view_outputs,
)
from nerfmeta.errors import ConfigError, NerfmetaError

CATS = ("chair", "mug", "table")


def _classifier(seed: int = 0, class_scale: bool = True) -> Classifier:
    model = build_model("resnet18", len(CATS), seed=seed).eval()
    g = torch.Generator().manual_seed(seed)
    dim = model.feature_dim
    stats = FeatureStats(torch.randn(len(CATS), dim, generator=g), torch.eye(dim) * 0.5, torch.eye(dim) * 2.0, torch.tensor(8.0),
                         torch.tensor([300.0, 100.0, 200.0]) if class_scale else None)
    meta = ClassifierMeta(
        categories=CATS, arch="resnet18", stem="imagenet", input_size=16, background=(1.0, 1.0, 1.0),
        mean=(0.5, 0.5, 0.5), std=(0.25, 0.25, 0.25), score="class_mahalanobis", threshold=-1.0,
        thresholds={"msp": 0.5, "energy": 1.0, "mahalanobis": -100.0, "class_mahalanobis": -1.0},
    )
    return Classifier(meta, model, stats)


def _views(n: int = 5) -> torch.Tensor:
    g = torch.Generator().manual_seed(1)
    rgba = torch.rand(n, 4, 16, 16, generator=g)
    rgba[:, :3] *= rgba[:, 3:4]  # premultiplied
    return rgba


@pytest.fixture(scope="module")
def template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("store") / "clf"
    save_classifier(folder, _classifier(), {"note": "test"})
    return folder


@pytest.fixture()
def saved(template: Path, tmp_path: Path) -> Path:
    """A fresh copy of the saved classifier that a test may damage."""
    return Path(shutil.copytree(template, tmp_path / "clf"))


def test_save_then_load_gives_identical_predictions(saved: Path):
    original = classify_views(_classifier(), _views())
    loaded = load_classifier(saved)
    again = classify_views(loaded, _views())
    assert again == original  # every field, probabilities and score bit for bit
    doc = json.loads((saved / META_FILE).read_text())
    assert doc["categories"] == list(CATS) and doc["input"]["size"] == 16 and doc["note"] == "test"
    assert len(doc["weights"]["sha256"]) == 64


def test_class_scale_is_saved_and_required_by_its_score(saved: Path, tmp_path: Path):
    loaded = load_classifier(saved)
    assert loaded.stats.class_scale.tolist() == [300.0, 100.0, 200.0]
    assert classify_views(loaded, _views()).score_name == "class_mahalanobis"
    old = _classifier(class_scale=False)
    save_classifier(tmp_path / "old", old, {})
    with pytest.raises(ClassifierError, match="class_scale is missing") as err:
        load_classifier(tmp_path / "old")
    assert "\n" not in str(err.value)
    # a classifier saved before the score existed (no scale, no such threshold) still loads
    thresholds = {k: v for k, v in old.meta.thresholds.items() if k != "class_mahalanobis"}
    older = Classifier(ClassifierMeta(**{**old.meta.__dict__, "score": "mahalanobis", "threshold": -100.0,
                                         "thresholds": thresholds}), old.model, old.stats)
    save_classifier(tmp_path / "older", older, {})
    assert classify_views(load_classifier(tmp_path / "older"), _views()).score_name == "mahalanobis"


def test_score_norm_is_saved_and_required_by_the_combined_score(tmp_path: Path):
    base = _classifier()
    norm = torch.tensor([2.0, 0.5, -1.0, 0.25])
    meta = ClassifierMeta(**{**base.meta.__dict__, "score": "combined", "threshold": -3.0,
                             "thresholds": {**base.meta.thresholds, "combined": -3.0}})
    save_classifier(tmp_path / "new", Classifier(meta, base.model, replace(base.stats, score_norm=norm)), {})
    loaded = load_classifier(tmp_path / "new")
    assert loaded.stats.score_norm.tolist() == norm.tolist()
    prediction = classify_views(loaded, _views())
    assert prediction.score_name == "combined"
    scores = scene_scores(*reversed(view_outputs(loaded.model, model_inputs(_views(), loaded.meta))), loaded.stats)
    assert prediction.score == pytest.approx((scores["energy"] - 2.0) / 0.5 + (scores["class_mahalanobis"] + 1.0) / 0.25)
    save_classifier(tmp_path / "bare", Classifier(meta, base.model, base.stats), {})
    with pytest.raises(ClassifierError, match="score_norm is missing"):
        load_classifier(tmp_path / "bare")
    save_classifier(tmp_path / "bad", Classifier(meta, base.model, replace(base.stats, score_norm=torch.tensor([1.0, 0.0, 1.0, 1.0]))), {})
    with pytest.raises(ClassifierError, match="score_norm must hold"):
        load_classifier(tmp_path / "bad")


def test_build_model_is_a_function_of_the_seed_and_leaves_global_rng_alone():
    state = torch.get_rng_state()
    a, b, c = build_model("resnet18", 3, seed=0), build_model("resnet18", 3, seed=0), build_model("resnet18", 3, seed=1)
    assert torch.equal(torch.get_rng_state(), state)
    assert torch.equal(a.net.conv1.weight, b.net.conv1.weight)
    assert not torch.equal(a.net.conv1.weight, c.net.conv1.weight)


def test_with_score_switches_to_another_calibrated_threshold(saved: Path):
    clf = load_classifier(saved).with_score("msp")
    assert clf.meta.score == "msp" and clf.meta.threshold == 0.5
    assert classify_views(clf, _views()).score_name == "msp"


def test_missing_classifier_option_says_what_to_pass():
    with pytest.raises(ClassifierError, match="--classifier DIR") as err:
        load_classifier(None)
    assert "model zoo" in str(err.value)


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda f: shutil.rmtree(f), "not found"),
        (lambda f: (f / META_FILE).unlink(), "classifier.json: file missing"),
        (lambda f: (f / WEIGHTS_FILE).unlink(), "weights file missing"),
        (lambda f: (f / META_FILE).write_text("{not json"), "invalid JSON"),
        (lambda f: (f / META_FILE).write_text('{"format": "other"}'), "not a nerfmeta classifier"),
        (lambda f: _edit(f, lambda d: d.pop("categories")), "missing or malformed"),
        (lambda f: _edit(f, lambda d: d["unknown"].update(score="best")), "unknown score"),
        (lambda f: _truncate(f / WEIGHTS_FILE), "SHA-256"),
        (lambda f: _edit(f, lambda d: d["weights"].update(sha256="0" * 64)), "SHA-256"),
        (lambda f: _edit(f, lambda d: d.update(categories=["chair", "mug"])), "do not fit a resnet18 with 2 categories"),
        (lambda f: _edit(f, lambda d: d.update(categories=["chair", "chair", "mug"])), "lists a name twice"),
        (lambda f: _edit(f, lambda d: d["input"].update(size=10**6)), "must be an integer from 8 to 1024"),
        (lambda f: _edit(f, lambda d: d["input"].update(size=True)), "must be an integer from 8 to 1024"),
        (lambda f: _edit(f, lambda d: d["input"].update(background=[0.0, 1e30, 0.0])), "three values in \\[0, 1\\]"),
        (lambda f: _edit(f, lambda d: d["unknown"].update(thresholds={"msp": float("nan")})), "must be finite"),
        (lambda f: _edit(f, lambda d: d["unknown"].update(thresholds={"msp": "abc"})), "missing or malformed"),
        (lambda f: _edit(f, lambda d: d["weights"].update(sha256=7)), "weights.sha256 must be a string"),
    ],
)
def test_damaged_folder_is_a_one_line_error(saved: Path, damage, message):
    damage(saved)
    with pytest.raises(ClassifierError, match=message) as err:
        load_classifier(saved)
    assert isinstance(err.value, NerfmetaError) and "\n" not in str(err.value)


def test_corrupted_weights_with_matching_hash_are_still_an_error(saved: Path):
    _truncate(saved / WEIGHTS_FILE)
    _edit(saved, lambda d: d["weights"].update(sha256=_sha(saved / WEIGHTS_FILE)))
    with pytest.raises(ClassifierError, match="cannot read as safetensors"):
        load_classifier(saved)


def test_load_pretrained_skips_fc_and_accepts_torchvision_keys(tmp_path: Path):
    donor = build_model("resnet18", 10, seed=5)
    path = tmp_path / "resnet18.pth"
    torch.save(donor.net.state_dict(), path)  # plain torchvision keys, 10-class fc
    model = build_model("resnet18", 3, seed=0)
    fresh = load_pretrained(model, path)
    assert torch.equal(model.net.layer1[0].conv1.weight, donor.net.layer1[0].conv1.weight)
    assert fresh == ["fc.bias", "fc.weight"]
    with pytest.raises(ConfigError, match="not found"):
        load_pretrained(model, tmp_path / "none.pth")
    (tmp_path / "junk.pth").write_bytes(b"junk")
    with pytest.raises(ConfigError, match="cannot read"):
        load_pretrained(model, tmp_path / "junk.pth")


def _edit(folder: Path, change) -> None:
    doc = json.loads((folder / META_FILE).read_text())
    change(doc)
    (folder / META_FILE).write_text(json.dumps(doc))


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _sha(path: Path) -> str:
    from nerfmeta.io import sha256_file

    return sha256_file(path)


def test_half_precision_weights_halve_the_file_and_load_as_float32(tmp_path: Path):
    clf = _classifier()
    full = save_classifier(tmp_path / "full", clf).parent
    half = save_classifier(tmp_path / "half", clf, weights_dtype=torch.float16).parent
    size_full, size_half = ((f / WEIGHTS_FILE).stat().st_size for f in (full, half))
    assert size_half < 0.55 * size_full
    assert json.loads((half / META_FILE).read_text())["weights"]["dtype"] == "float16"
    loaded = load_classifier(half)
    assert all(p.dtype == torch.float32 for p in loaded.model.parameters())
    assert loaded.stats.between.dtype == torch.float32
    assert torch.equal(loaded.stats.between, clf.stats.between)  # the score's statistics are not rounded
    expected, got = classify_views(clf, _views()), classify_views(loaded, _views())
    assert got.category == expected.category
    for c in CATS:
        assert got.probabilities[c] == pytest.approx(expected.probabilities[c], abs=2e-3)


# --- --json-out paths that cannot be written: one line naming the path, exit 2, nothing written --------


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda t: (t / "folder").mkdir() or t / "folder", "is a folder; give a file path"),
        (lambda t: str(t / "new_folder") + "/", "names a folder; give a file path"),
        (lambda t: (t / "afile").write_text("x") and t / "afile" / "answer.json", "is a file, not a folder"),
        (lambda t: (t / "dangling").symlink_to(t / "nowhere") or t / "dangling", "is a symbolic link to a missing target"),
        (lambda t: os.mkfifo(t / "pipe") or t / "pipe", "exists and is not a regular file"),  # never a real device here
    ],
)
def test_json_out_that_cannot_be_written_is_refused_before_any_work(saved: Path, tmp_path: Path, capsys, make, message):
    from nerfmeta.cli import main
    from nerfmeta.data.synthetic import write_tiny_scene

    scene = write_tiny_scene(tmp_path / "scene", n_train=2, n_test=1, size=8)
    target = make(tmp_path)
    before = sorted(p.name for p in tmp_path.iterdir())
    assert main(["classify", str(scene), "--classifier", str(saved), "--json-out", str(target)]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and "--json-out" in lines[0] and message in lines[0] and "Traceback" not in captured.err, captured.err
    assert captured.out == "" and sorted(p.name for p in tmp_path.iterdir()) == before


def test_json_out_on_a_full_disk_is_one_line_and_leaves_nothing(saved: Path, tmp_path: Path, capsys, monkeypatch):
    import errno

    from nerfmeta.cli import main
    from nerfmeta.data.synthetic import write_tiny_scene

    scene = write_tiny_scene(tmp_path / "scene", n_train=2, n_test=1, size=8)

    def full(self: Path, data: bytes) -> int:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Path, "write_bytes", full)
    assert main(["classify", str(scene), "--classifier", str(saved), "--json-out", str(tmp_path / "answer.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "answer.json: cannot write (No space left on device)" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clf", "scene"]


@pytest.mark.parametrize("victim", ["scene/transforms_train.json", "clf/classifier.json", "scene/train/r_0.png"])
def test_json_out_never_replaces_a_file_of_the_inputs(saved: Path, tmp_path: Path, capsys, victim: str):
    from nerfmeta.cli import main
    from nerfmeta.data.synthetic import write_tiny_scene

    scene = write_tiny_scene(tmp_path / "scene", n_train=2, n_test=1, size=8)
    target = tmp_path / victim
    before = target.read_bytes()
    assert main(["classify", str(scene), "--classifier", str(saved), "--json-out", str(target)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "would replace a file of the input" in err[0]
    assert target.read_bytes() == before


ZOO_CLASSIFIER = Path(__file__).resolve().parents[1] / "model_zoo" / "classifier"


@pytest.mark.skipif(not (ZOO_CLASSIFIER / WEIGHTS_FILE).is_file(), reason="model_zoo/classifier not in this checkout")
def test_the_shipped_zoo_classifier_decides_with_fused_and_predicts_as_when_it_was_built():
    """model_zoo/classifier (rebuilt 2026-11-27, float16 weights, float32 statistics): its own threshold, its own score,
    and on three views of a flat shaded rectangle the values it gave when it was shipped (a regression pin)."""
    doc = json.loads((ZOO_CLASSIFIER / META_FILE).read_text())
    clf = load_classifier(ZOO_CLASSIFIER)
    assert clf.meta.score == "fused" and clf.meta.threshold == doc["unknown"]["threshold"]
    assert doc["weights"]["dtype"] == "float16" and clf.stats.reference.between.dtype == torch.float32
    ramp = torch.linspace(0, 1, 64)
    views = torch.zeros(3, 4, 64, 64)
    for i in range(3):  # three views of a flat, shaded rectangle
        views[i, 3, 16:48, 16 + 4 * i:48] = 1.0
        views[i, 0] = views[i, 3] * ramp[None, :]
        views[i, 1] = views[i, 3] * 0.5
        views[i, 2] = views[i, 3] * ramp[:, None]
    prediction = classify_views(clf, views)
    assert prediction.category == "mug" and prediction.unknown and prediction.score_name == "fused"
    assert prediction.score == pytest.approx(-35.76393311382475, rel=1e-6)
    assert prediction.confidence == pytest.approx(0.8279129862785339, rel=1e-6)


def test_mirrored_views_follow_the_views_and_survive_a_round_trip(tmp_path: Path):
    """``mirror_views``: every view is also classified flipped left-right; the setting is saved, and a folder
    written before it existed (no ``input.mirror_views``) loads without it."""
    base = _classifier()
    inputs = model_inputs(_views(3), base.meta)
    f, z = view_outputs(base.model, inputs, mirror=True)
    f_plain, z_plain = view_outputs(base.model, inputs)
    f_flip, _ = view_outputs(base.model, inputs.flip(-1))
    assert f.shape[0] == 6 and torch.allclose(f[:3], f_plain, atol=1e-5) and torch.allclose(f[3:], f_flip, atol=1e-5)
    meta = ClassifierMeta(**{**base.meta.__dict__, "mirror_views": True})
    save_classifier(tmp_path / "m", Classifier(meta, base.model, base.stats), {})
    loaded = load_classifier(tmp_path / "m")
    assert loaded.meta.mirror_views
    prediction = classify_views(loaded, _views(3))
    assert prediction.views == 3  # the views given
    plain = classify_views(Classifier(base.meta, base.model, base.stats), _views(3))
    assert prediction.score != pytest.approx(plain.score)  # the mirrored views count in the score
    doc = json.loads((tmp_path / "m" / META_FILE).read_text())
    del doc["input"]["mirror_views"]
    (tmp_path / "m" / META_FILE).write_text(json.dumps(doc))
    assert not load_classifier(tmp_path / "m").meta.mirror_views
    doc["input"]["mirror_views"] = "yes"
    (tmp_path / "m" / META_FILE).write_text(json.dumps(doc))
    with pytest.raises(ClassifierError, match="mirror_views"):
        load_classifier(tmp_path / "m")
