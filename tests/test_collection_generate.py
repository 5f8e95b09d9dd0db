"""Generating a collection: files, determinism, scene parsing, recorded geometry."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from nerfmeta.collection import generate as G
from nerfmeta.collection.categories import CATEGORIES
from nerfmeta.collection.generate import CollectionConfig, generate_collection, load_collection, plan_collection, scene_sdf
from nerfmeta.collection.shapes import shape_sdf
from nerfmeta.errors import ConfigError

SMALL = CollectionConfig(scenes_per_category=1, views=4, test_views=2, resolution=24, seed=3)


def files_of(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def collection(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("coll") / "all"
    generate_collection(SMALL, out)
    return out


def test_layout_and_index(collection: Path):
    doc = json.loads((collection / "collection.json").read_text())
    assert doc["format"] == "nerfmeta-collection"
    names = [s["name"] for s in doc["scenes"]]
    assert names == sorted(names) and len(names) == len(CATEGORIES)
    assert {s["category"] for s in doc["scenes"]} == set(CATEGORIES)
    for entry in doc["scenes"]:
        folder = collection / entry["path"]
        assert (folder / "transforms_train.json").is_file() and (folder / "transforms_test.json").is_file()
        assert entry["split"] in ("train", "val", "test")
        assert entry["shape"]["parts"] and entry["shape"]["traits"]
        assert len(list((folder / "train").glob("*.png"))) == SMALL.views
        assert len(list((folder / "test").glob("*.png"))) == SMALL.test_views
    # nothing left behind beside the collection
    assert [p.name for p in collection.parent.iterdir()] == ["all"]


def test_every_category_has_a_partial_mask_from_every_camera(collection: Path):
    for png in sorted(collection.rglob("r_*.png")):
        alpha = iio.imread(png)[..., 3]
        assert alpha.astype(int).sum() >= 2 * 255, png  # the object is seen (a thin one may cover no pixel fully)
        assert (alpha == 0).mean() > 0.2, png  # and does not fill the frame
        border = np.concatenate([alpha[0], alpha[-1], alpha[:, 0], alpha[:, -1]])
        assert border.max() == 0, png  # nor touch its edges


def test_two_runs_are_byte_identical(collection: Path, tmp_path: Path):
    again = tmp_path / "again"
    generate_collection(SMALL, again)
    assert files_of(again) == files_of(collection)


@pytest.mark.slow
def test_worker_processes_give_the_same_bytes(tmp_path: Path):
    config = replace(SMALL, categories=("mug", "car"), views=2, test_views=1, resolution=16)
    generate_collection(config, tmp_path / "one", workers=1)
    generate_collection(config, tmp_path / "two", workers=2)
    assert files_of(tmp_path / "one") == files_of(tmp_path / "two")


def test_scenes_load_with_the_scene_parser_and_look_at_the_object(collection: Path):
    from nerfmeta.data import load_scene

    for record in load_collection(collection).scenes:
        scene = load_scene(collection / record.path)
        assert scene.format == "blender"
        assert scene.category == record.category
        assert (scene.near, scene.far) == (SMALL.near, SMALL.far)
        assert len(scene.splits["train"]) == SMALL.views and len(scene.splits["test"]) == SMALL.test_views
        np.testing.assert_allclose(scene.bounds.numpy(), record.aabb, atol=1e-6)
        poses = scene.poses.double()
        centres, forward = poses[:, :3, 3], -poses[:, :3, 2]
        torch.testing.assert_close(centres.norm(dim=-1), torch.full((len(poses),), SMALL.radius, dtype=torch.float64))
        # the optical axis passes through the origin, where the object's box is centred
        torch.testing.assert_close(torch.linalg.cross(forward, -centres, dim=-1).norm(dim=-1), torch.zeros(len(poses), dtype=torch.float64), atol=1e-9, rtol=0)
        assert bool(((-centres * forward).sum(-1) > 0).all())
        # upper hemisphere by default, and test directions differ from training ones
        assert bool((centres[:, 2] > 0).all())
        train, test = centres[list(scene.splits["train"])], centres[list(scene.splits["test"])]
        assert float(torch.cdist(train, test).min()) > 1e-3
        # the composited alpha: the object covers the image centre's neighbourhood in some view
        assert scene.alphas is not None and float(scene.alphas.amax()) == 1.0


def test_recorded_parameters_rebuild_the_generators_sdf(collection: Path):
    in_memory = {r.name: r for r in plan_collection(SMALL)}
    doc = json.loads((collection / "collection.json").read_text())
    g = torch.Generator().manual_seed(0)
    p = torch.rand(3000, 3, generator=g, dtype=torch.float64) * 2.4 - 1.2
    for entry in doc["scenes"]:
        sdf = scene_sdf(entry)
        assert torch.equal(sdf(p), shape_sdf(in_memory[entry["name"]].shape, p))
        assert torch.equal(sdf(p.float()), in_memory[entry["name"]].sdf(p.float()))


def test_recorded_sdf_sign_at_known_points(collection: Path):
    for record in load_collection(collection).scenes:
        shape = record.shape
        first = shape.parts[0]  # seat / body / top / base / fuselage / shell bottom: solid at its origin
        inside = (torch.tensor(first.position, dtype=torch.float64) - torch.tensor(shape.center, dtype=torch.float64)) * shape.scale
        outside = torch.tensor([[1.05, 0.0, 0.0], [0.0, 0.0, 1.5], [-2.0, 2.0, -2.0]], dtype=torch.float64)
        sdf = scene_sdf(record)
        assert float(sdf(inside[None])) < 0, record.name
        assert bool((sdf(outside) > 0).all()), record.name


def test_split_assignment_follows_the_fractions():
    config = replace(SMALL, scenes_per_category=10, val_fraction=0.2, test_fraction=0.1)
    splits = G.split_assignment(config, "chair")
    assert sorted(splits).count("train") == 7 and splits.count("val") == 2 and splits.count("test") == 1
    assert G.split_assignment(config, "chair") == splits
    one = G.split_assignment(replace(config, scenes_per_category=1), "chair")
    assert one == ["train"]


def test_scenes_do_not_depend_on_the_other_categories():
    a = {r.name: r for r in plan_collection(replace(SMALL, categories=("vase", "chair")))}
    b = {r.name: r for r in plan_collection(replace(SMALL, categories=("chair",)))}
    assert a["chair_000"] == b["chair_000"]


def test_a_failure_leaves_nothing_behind(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    calls = []

    def failing(record, config, root):
        calls.append(record.name)
        if len(calls) == 2:
            raise RuntimeError("boom")
        return real(record, config, root)

    real = G.write_scene
    monkeypatch.setattr(G, "write_scene", failing)
    with pytest.raises(RuntimeError):
        generate_collection(replace(SMALL, categories=("mug", "vase")), tmp_path / "out")
    assert list(tmp_path.iterdir()) == []


def test_overwrite_only_replaces_a_collection(tmp_path: Path):
    config = replace(SMALL, categories=("mug",), views=1, test_views=1, resolution=12)
    out = tmp_path / "c"
    generate_collection(config, out)
    with pytest.raises(ConfigError, match="not empty"):
        generate_collection(config, out)
    generate_collection(replace(config, seed=4), out, overwrite=True)
    assert json.loads((out / "collection.json").read_text())["config"]["seed"] == 4
    other = tmp_path / "other"
    other.mkdir()
    (other / "keep.txt").write_text("x")
    with pytest.raises(ConfigError, match="no collection.json"):
        generate_collection(config, other, overwrite=True)
    assert (other / "keep.txt").read_text() == "x"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c", "other"]


@pytest.mark.parametrize(
    "change, message",
    [
        ({"categories": ("chair", "spaceship")}, "unknown category 'spaceship'"),
        ({"scenes_per_category": 0}, "positive integer"),
        ({"views": -2}, "positive integer"),
        ({"test_views": 0}, "positive integer"),
        ({"resolution": 7}, "between 8 and 2048"),
        ({"resolution": 100_000}, "between 8 and 2048"),
        ({"val_fraction": 0.6, "test_fraction": 0.5}, "below 1"),
        ({"fov_degrees": 0.0}, "--fov"),
    ],
)
def test_bad_configs_raise_one_line(change, message, tmp_path: Path):
    with pytest.raises(ConfigError, match=message) as err:
        generate_collection(replace(SMALL, **change), tmp_path / "out")
    assert "\n" not in str(err.value)
    assert not (tmp_path / "out").exists()
