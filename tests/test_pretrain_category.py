"""Category models (``pretrain/category.py``) and ``nerfmeta pretrain category``."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from nerfmeta.cli import main
from nerfmeta.collection.generate import CollectionConfig, generate_collection, load_collection
from nerfmeta.data import load_scene
from nerfmeta.errors import ConfigError
from nerfmeta.fit.loop import FitConfig
from nerfmeta.init import load_init
from pretrain.category import CANONICAL_BOX, CategoryPretrainConfig, category_records, category_scene, pretrain_category

# 2 categories x 3 scenes (1 test, 2 train each), 3 train + 2 test views of 16 x 16 px.
TINY = CollectionConfig(categories=("chair", "mug"), scenes_per_category=3, views=3, test_views=2, resolution=16,
                        seed=1, val_fraction=0.0, test_fraction=0.34)
NERF_TINY = ["--set", "depth=2", "--set", "width=16", "--set", "skips=[]", "--set", "n_samples=8",
             "--set", "pos_freqs=3", "--set", "dir_freqs=2", "--set", "lr=0.01"]
GRID_TINY = {"num_voxels": 12**3, "coarse_iters": 3, "coarse_num_voxels": 8**3, "growth_steps": [2], "mlp_width": 8,
             "mlp_depth": 2, "feature_dim": 2}


@pytest.fixture(scope="module")
def collection(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("tiny_collection") / "col"
    threads = torch.get_num_threads()  # module fixtures run before the per-test one-thread fixture
    torch.set_num_threads(1)
    try:
        generate_collection(TINY, out)
    finally:
        torch.set_num_threads(threads)
    return out


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("nerfmeta pretrain: error:") and "Traceback" not in err[0], err
    return err[0]


def test_category_scene_merges_the_training_scenes_in_the_canonical_box(collection):
    col = load_collection(collection)
    records = category_records(col, "chair")
    assert [r.split for r in records] == ["train", "train"] and all(r.category == "chair" for r in records)
    data = category_scene(col, records)
    scene = data.scene
    assert data.scene_names == tuple(r.name for r in records)
    assert scene.category == "chair" and scene.n_views == 2 * (3 + 2)
    assert torch.equal(scene.bounds, torch.tensor(CANONICAL_BOX))
    assert len(scene.splits["train"]) == 6 and len(scene.splits["test"]) == 4
    assert set(scene.splits["train"]).isdisjoint(scene.splits["test"])
    # Every view is its scene's view, unchanged, and owned by that scene.
    offset = 0
    for k, record in enumerate(records):
        one = load_scene(col.scene_path(record))
        assert torch.equal(scene.images[offset : offset + one.n_views], one.images)
        assert torch.equal(scene.poses[offset : offset + one.n_views], one.poses)
        assert data.view_scene[offset : offset + one.n_views] == (k,) * one.n_views
        assert [offset + i for i in one.splits["train"]] == [i for i in scene.splits["train"] if data.view_scene[i] == k]
        offset += one.n_views


def test_max_scenes_takes_the_first_training_scenes(collection):
    col = load_collection(collection)
    assert [r.name for r in category_records(col, "mug", max_scenes=1)] == [category_records(col, "mug")[0].name]
    with pytest.raises(ConfigError, match="--max-scenes"):
        category_records(col, "mug", max_scenes=0)


def test_pretrain_category_cli_writes_a_loadable_category_model(collection, tmp_path, capsys):
    out = tmp_path / "chair_nerf"
    code = main(["pretrain", "category", str(collection), "--category", "chair", "--out", str(out), "--backbone", "nerf",
                 "--iters", "30", "--batch-rays", "128", "--seed", "3", *NERF_TINY])
    assert code == 0
    for name in ("model.safetensors", "init.json", "config.json", "metrics.jsonl", "psnr_vs_iter.png"):
        assert (out / name).is_file(), name
    saved = load_init(out, expect_kind="category")
    meta = saved.meta
    assert saved.backbone == "nerf" and saved.model_config.width == 16
    assert meta["category"] == "chair" and meta["seed"] == 3 and meta["steps"] == 30
    col = load_collection(collection)
    assert meta["scenes"] == [r.name for r in col.by_category("chair") if r.split == "train"]
    assert meta["final_psnr"] > 0 and set(meta["scene_psnr"]) == set(meta["scenes"])
    # the final PSNR is the mean over the test views, i.e. over the scenes (same view count each)
    assert meta["final_psnr"] == pytest.approx(sum(meta["scene_psnr"].values()) / 2, abs=1e-3)
    assert meta["optimizer"]["name"] == "Adam" and meta["optimizer"]["batch_rays"] == 128
    assert meta["box"] == [list(CANONICAL_BOX[0]), list(CANONICAL_BOX[1])]
    model = saved.build()
    assert torch.equal(model.bounds, torch.tensor(CANONICAL_BOX))
    lines = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["iter"] for r in lines] == list(range(1, 31))
    config = json.loads((out / "config.json").read_text())
    assert config["category"] == "chair" and config["model"]["width"] == 16 and config["fit"]["iters"] == 30
    assert "category model 'chair'" in capsys.readouterr().out


def test_grid_category_model_is_a_fully_grown_fine_stage_grid(collection, tmp_path):
    auto = {k: v for k, v in GRID_TINY.items() if k != "num_voxels"}  # size resolved like a scratch fit's
    config = CategoryPretrainConfig(collection=str(collection), category="mug", backbone="grid", model=auto,
                                    fit=FitConfig(iters=8, batch_rays=64, eval_every=0, checkpoint_every=0))
    meta = pretrain_category(config, tmp_path / "mug_grid")
    saved = load_init(tmp_path / "mug_grid", expect_kind="category")
    scene = category_scene(load_collection(collection), category_records(load_collection(collection), "mug")).scene
    assert saved.model_config.num_voxels == config.model_config(scene).num_voxels > 0
    assert saved.model_config.coarse_iters == 3 and "coarse_iters=3" in meta["recipe"]
    assert saved.structure["stage"] == "fine" and saved.structure["level"] == 1
    # the coarse stage ran in the canonical box: the fine box lies inside it
    lo, hi = saved.structure["bounds"]
    assert all(-1.0 <= a < b <= 1.0 for a, b in zip(lo, hi))
    model = saved.build()
    assert [layer.name for layer in model.layers()][:2] == ["density", "features"]


def test_pretraining_fits_the_category(collection, tmp_path):
    """The category model's PSNR on its scenes' held-out views rises well above the initial one."""
    fine_only = {**GRID_TINY, "coarse_iters": 0}  # a 3-step coarse stage is too short to find the objects
    config = CategoryPretrainConfig(collection=str(collection), category="mug", backbone="grid", model=fine_only,
                                    fit=FitConfig(iters=40, batch_rays=256, eval_every=0, checkpoint_every=0))
    meta = pretrain_category(config, tmp_path / "mug")
    first = json.loads((tmp_path / "mug" / "metrics.jsonl").read_text().splitlines()[0])["train_psnr"]
    assert meta["final_train_psnr"] > first + 3.0 and meta["final_psnr"] > first + 2.0, (first, meta)


def _copy_index(collection: Path, dest: Path, edit) -> Path:
    doc = json.loads((collection / "collection.json").read_text())
    doc["scenes"] = edit(doc["scenes"])
    dest.mkdir()
    (dest / "collection.json").write_text(json.dumps(doc))
    return dest


@pytest.mark.parametrize("case,needle", [
    ("one_scene", "holds 1 scene"),
    ("no_train", "has no training scenes"),
    ("unknown", "'car' is not in"),
    ("short", "--iters 5: the grid grows until step 5"),
    ("iters", "--iters"),
    ("missing", "not found"),
])
def test_bad_input_is_one_line_exit_2_and_writes_nothing(collection, tmp_path, capsys, case, needle):
    source, category, extra = str(collection), "chair", ["--backbone", "nerf", *NERF_TINY, "--iters", "5"]
    if case == "one_scene":
        source = str(_copy_index(collection, tmp_path / "one", lambda scenes: scenes[:1]))
    elif case == "no_train":
        source = str(_copy_index(collection, tmp_path / "nt", lambda scenes: [
            {**s, "split": "test"} if s["category"] == "chair" else s for s in scenes]))
    elif case == "unknown":
        category = "car"
    elif case == "short":
        extra = ["--backbone", "grid", "--set", "coarse_iters=3", "--set", "growth_steps=[2]", "--iters", "5"]
    elif case == "iters":
        extra = ["--iters", "0"]
    elif case == "missing":
        source = str(tmp_path / "nowhere")
    out = tmp_path / "model"
    code = main(["pretrain", "category", source, "--category", category, "--out", str(out), *extra])
    assert code == 2
    assert needle in _one_error_line(capsys)
    assert not out.exists()


def test_existing_output_needs_overwrite(collection, tmp_path, capsys):
    out = tmp_path / "model"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    code = main(["pretrain", "category", str(collection), "--category", "chair", "--out", str(out), "--iters", "5",
                 "--backbone", "nerf"])
    assert code == 2 and "--overwrite" in _one_error_line(capsys)
    assert (out / "keep.txt").read_text() == "mine"


class _Kill(Exception):
    pass


def test_a_killed_category_run_resumes_to_the_uninterrupted_model(collection, tmp_path):
    """Category pretraining checkpoints like a fit and --resume continues it bit for bit."""
    model = {"depth": 2, "width": 16, "skips": [], "n_samples": 8, "pos_freqs": 3, "dir_freqs": 2}
    config = CategoryPretrainConfig(collection=str(collection), category="mug", backbone="nerf", model=model,
                                    fit=FitConfig(iters=8, batch_rays=64, eval_every=0, checkpoint_every=3))
    pretrain_category(config, tmp_path / "full")

    def kill_at_5(record, model, state):
        if record.iter == 5:
            raise _Kill

    with pytest.raises(_Kill):
        pretrain_category(config, tmp_path / "killed", callbacks=[kill_at_5])
    assert not (tmp_path / "killed" / "init.json").exists()
    pretrain_category(config, tmp_path / "killed", resume=True)
    from safetensors.torch import load_file

    a, b = load_file(str(tmp_path / "full" / "model.safetensors")), load_file(str(tmp_path / "killed" / "model.safetensors"))
    assert sorted(a) == sorted(b) and all(torch.equal(a[k], b[k]) for k in a)
    iters = [json.loads(line)["iter"] for line in (tmp_path / "killed" / "metrics.jsonl").read_text().splitlines()]
    assert iters == list(range(1, 9))


def test_overwrite_keeps_a_user_file_in_a_category_folder(collection, tmp_path, capsys):
    out = tmp_path / "model"
    args = ["pretrain", "category", str(collection), "--category", "chair", "--out", str(out), "--iters", "2",
            "--backbone", "nerf", *NERF_TINY]
    assert main(args) == 0
    (out / "notes.txt").write_text("mine")
    capsys.readouterr()
    assert main([*args, "--overwrite"]) == 2 and "notes.txt" in _one_error_line(capsys)
    assert (out / "notes.txt").read_text() == "mine" and (out / "init.json").is_file()
