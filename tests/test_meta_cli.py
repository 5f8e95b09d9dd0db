"""``nerfmeta meta-train`` through the CLI: smoke runs per backbone, bad input, resume after a kill."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from nerfmeta.cli import main
from nerfmeta.collection.generate import CollectionConfig, generate_collection
from nerfmeta.collection.render import RenderConfig
from nerfmeta.init import load_init
from nerfmeta.io import load_tensors

TINY_NERF = ["--set", "depth=2", "--set", "width=16", "--set", "skips=[]", "--set", "n_samples=8", "--set", "pos_freqs=2"]
TINY_GRID = ["--set", "num_voxels=512", "--set", "feature_dim=2", "--set", "mlp_width=8"]
FAST = ["--meta-batch", "2", "--support-rays", "64", "--query-rays", "64", "--inner-steps", "2", "--eval-tasks", "1"]

FAST_RENDER = RenderConfig(supersample=1, max_steps=48)  # the images only need to differ per scene


@pytest.fixture(scope="module")
def collection(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """2 categories x 3 scenes (2 train + 1 test each), 16 px, 4 views."""
    out = tmp_path_factory.mktemp("meta_coll") / "coll"
    config = CollectionConfig(categories=("mug", "vase"), scenes_per_category=3, views=4, test_views=1, resolution=16,
                              val_fraction=0.0, test_fraction=0.34, render=FAST_RENDER)
    generate_collection(config, out)
    return out


@pytest.fixture(scope="module")
def one_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("meta_one") / "coll"
    generate_collection(CollectionConfig(categories=("mug",), scenes_per_category=1, views=2, test_views=1, resolution=8, render=FAST_RENDER), out)
    return out


def one_error_line(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("nerfmeta meta-train: error:"), err
    return err[0]


@pytest.mark.parametrize("backbone,algo,extra", [("nerf", "maml", TINY_NERF), ("grid", "reptile", TINY_GRID)])
def test_meta_train_writes_an_initialisation_that_loads(collection, tmp_path, capsys, backbone, algo, extra):
    run = tmp_path / "run"
    code = main(["meta-train", str(collection), "--out", str(run), "--backbone", backbone, "--algo", algo,
                 "--meta-steps", "2", *FAST, *extra])
    assert code == 0, capsys.readouterr().err
    assert "nerfmeta fit SCENE --init meta:" in capsys.readouterr().out
    for name in ("config.json", "metrics.jsonl", "checkpoint.safetensors", "model.safetensors", "init.json",
                 "summary.json", "query_psnr_vs_step.png"):
        assert (run / name).is_file(), name
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records] == [1, 2] and all(len(r["tasks"]) == 2 for r in records)
    saved = load_init(run, expect_kind="meta")
    assert saved.backbone == backbone and saved.meta["algo"] == algo and saved.meta["meta_steps"] == 2
    assert len(saved.meta["scenes"]) == 4 and saved.meta["categories"] == ["mug", "vase"]
    assert saved.meta["held_out"]["split"] == "test"
    model = saved.build()
    state = load_tensors(run / "model.safetensors")
    for name, value in model.state_dict().items():
        assert torch.equal(value, state[name]), name
    assert json.loads((run / "config.json").read_text())["backbone"] == backbone


def test_bad_input_one_line_exit_2_nothing_written(collection, one_scene, tmp_path, capsys):
    out = tmp_path / "out"
    cases = [
        ([str(one_scene), "--out", str(out)], "at least 2"),
        ([str(collection), "--out", str(out), "--backbone", "grid", "--algo", "maml"], "second-order"),
        ([str(collection), "--out", str(out), "--inner-steps", "0"], "--inner-steps"),
        ([str(collection), "--out", str(out), "--engine", "l2l", "--set", "nope=1"], "--set"),
        ([str(collection), "--out", str(out), "--categories", "chair"], "chair"),
        ([str(tmp_path / "missing"), "--out", str(out)], "not found"),
        ([str(collection), "--out", str(out), "--resume"], "nothing to resume"),
    ]
    for args, needle in cases:
        assert main(["meta-train", *FAST, *args]) == 2, args
        assert needle in one_error_line(capsys), args
        assert not out.exists(), args
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert main(["meta-train", str(collection), "--out", str(out), *FAST]) == 2
    assert "--overwrite" in one_error_line(capsys)
    assert main(["meta-train", str(collection), "--out", str(out), "--overwrite", *FAST]) == 2
    assert "not a meta-train run" in one_error_line(capsys)
    assert [p.name for p in out.iterdir()] == ["notes.txt"]


def test_resume_after_a_kill_equals_an_uninterrupted_run(collection, tmp_path, capsys):
    """Kill at step 3 (after the checkpoint of step 2), resume: same parameters and records as one run."""
    from pretrain.meta import MetaConfig
    from pretrain.meta_run import meta_train, read_metrics

    config = MetaConfig(algo="fomaml", meta_steps=4, checkpoint_every=2, meta_batch=2, support_rays=64, query_rays=64,
                        inner_steps=2, eval_tasks=0, model={"depth": 2, "width": 16, "skips": (), "n_samples": 8, "pos_freqs": 2})
    whole, broken = tmp_path / "whole", tmp_path / "broken"
    meta_train(config, collection, whole)

    def kill_at_3(record) -> None:
        if record.step == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        meta_train(config, collection, broken, progress=kill_at_3)
    assert not (broken / "init.json").exists()
    assert len(read_metrics(broken / "metrics.jsonl")) == 3
    # another backbone cannot resume it (one line, nothing changed)
    before = (broken / "checkpoint.safetensors").read_bytes()
    assert main(["meta-train", str(collection), "--out", str(broken), "--resume", "--backbone", "grid"]) == 2
    assert "backbone='nerf', not 'grid'" in one_error_line(capsys)
    assert (broken / "checkpoint.safetensors").read_bytes() == before
    assert main(["meta-train", str(collection), "--out", str(broken), "--resume"]) == 0, capsys.readouterr().err
    a, b = load_tensors(whole / "model.safetensors"), load_tensors(broken / "model.safetensors")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    ra, rb = read_metrics(whole / "metrics.jsonl"), read_metrics(broken / "metrics.jsonl")
    strip = lambda rs: [{k: v for k, v in r.items() if k != "time_s"} for r in rs]  # noqa: E731
    assert strip(ra) == strip(rb) and [r["step"] for r in rb] == [1, 2, 3, 4]
    # a further resume may extend the run
    assert main(["meta-train", str(collection), "--out", str(broken), "--resume", "--meta-steps", "5"]) == 0
    assert [r["step"] for r in read_metrics(broken / "metrics.jsonl")] == [1, 2, 3, 4, 5]


def test_a_checkpoint_of_another_shape_is_refused(collection, tmp_path):
    from pretrain.meta import MetaConfig
    from pretrain.meta_run import CHECKPOINT, meta_train
    from nerfmeta.errors import ConfigError

    small = {"depth": 2, "width": 16, "skips": (), "n_samples": 8, "pos_freqs": 2}
    config = MetaConfig(meta_steps=1, meta_batch=2, support_rays=32, query_rays=32, inner_steps=1, eval_tasks=0, model=small)
    a, b = tmp_path / "a", tmp_path / "b"
    meta_train(config, collection, a)
    meta_train(MetaConfig(**{**config.__dict__, "model": {**small, "width": 8}}), collection, b)
    (a / CHECKPOINT).write_bytes((b / CHECKPOINT).read_bytes())  # a checkpoint that is not this run's
    with pytest.raises(ConfigError, match=r"trunk\.0\.weight has shape \(8, 15\), this config builds \(16, 15\)"):
        meta_train(config, collection, a, resume=True)
