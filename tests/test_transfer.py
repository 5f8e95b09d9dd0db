"""Transfer fits: ``nerfmeta fit SCENE --init category:DIR|meta:DIR --freeze K`` (``nerfmeta/fit/run.py``)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from nerfmeta.cli import main
from nerfmeta.collection.generate import CollectionConfig, generate_collection, load_collection
from nerfmeta.data import load_scene
from nerfmeta.errors import ConfigError
from nerfmeta.fields.registry import build_model, config_from_dict, default_config
from nerfmeta.fit.evaluate import evaluate_views
from nerfmeta.fit.loop import FitConfig, fit
from nerfmeta.fit.run import RunConfig, build_initial_model, read_metrics, run_fit
from nerfmeta.init import WEIGHTS, load_init, save_init
from pretrain.category import CANONICAL_BOX, CategoryPretrainConfig, pretrain_category

TINY = CollectionConfig(categories=("chair", "mug"), scenes_per_category=3, views=3, test_views=2, resolution=16,
                        seed=1, val_fraction=0.0, test_fraction=0.34)
MODELS = {
    "nerf": {"depth": 2, "width": 32, "skips": [], "n_samples": 16, "pos_freqs": 4, "dir_freqs": 2, "lr": 0.01},
    "grid": {"num_voxels": 16**3, "coarse_iters": 0, "growth_steps": [2], "mlp_width": 8,
             "mlp_depth": 2, "feature_dim": 2, "view_dependent": True},  # the colour MLP, so --freeze 2 exists
}
SCRATCH_ONLY = {"nerf": {}, "grid": {"coarse_iters": 10, "coarse_num_voxels": 10**3}}  # a scratch grid's usual coarse stage
FAST = ["--iters", "6", "--batch-rays", "64", "--eval-every", "0", "--checkpoint-every", "0"]
CPU = torch.device("cpu")


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A tiny collection, a category model per backbone trained on its chairs, and the held-out chair."""
    root = tmp_path_factory.mktemp("transfer")
    threads = torch.get_num_threads()  # module fixtures run before the per-test one-thread fixture
    torch.set_num_threads(1)
    try:
        generate_collection(TINY, root / "col")
        models = {}
        for backbone, overrides in MODELS.items():
            models[backbone] = root / f"chair_{backbone}"
            config = CategoryPretrainConfig(collection=str(root / "col"), category="chair", backbone=backbone,
                                            model=overrides, fit=FitConfig(iters=80, batch_rays=256, eval_every=0, holdout_tile=0.0))
            pretrain_category(config, models[backbone])
    finally:
        torch.set_num_threads(threads)
    col = load_collection(root / "col")
    test_chair = next(r for r in col.scenes if r.category == "chair" and r.split == "test")
    return {"root": root, "models": models, "scene": col.scene_path(test_chair)}


def _run_config(world, backbone: str, init: str, freeze: int = 0, iters: int = 6) -> RunConfig:
    model = {**MODELS[backbone], **SCRATCH_ONLY[backbone]} if init == "scratch" else {}
    return RunConfig(scene=str(world["scene"]), backbone=backbone, model=model,
                     init=init, freeze=freeze, fit=FitConfig(iters=iters, batch_rays=64, eval_every=0, checkpoint_every=0))


def _one_error_line(capsys) -> str:
    err = [line for line in capsys.readouterr().err.strip().splitlines() if "error" in line]
    assert len(err) == 1 and err[0].startswith("nerfmeta fit: error:"), err
    return err[0]


@pytest.mark.parametrize("backbone,k", [("nerf", 2), ("grid", 1)])
def test_fit_cli_from_a_category_model_records_init_and_frozen_layers(world, tmp_path, capsys, backbone, k):
    out = tmp_path / "run"
    model_dir = world["models"][backbone]
    code = main(["fit", str(world["scene"]), "--out", str(out), "--init", f"category:{model_dir}", "--freeze", str(k), *FAST])
    assert code == 0  # --backbone left out: taken from the category model
    summary = json.loads((out / "summary.json").read_text())
    config = json.loads((out / "config.json").read_text())
    saved = load_init(model_dir)
    names = [layer.name for layer in saved.build().layers()]
    for doc in (summary, config):
        assert doc["init_path"] == str(model_dir.resolve()) and doc["frozen_layers"] == names[:k]
        assert doc["freeze"] == k and doc["backbone"] == backbone
        assert doc["init_sha256"] == json.loads((model_dir / "init.json").read_text())["sha256"]
    assert summary["init"] == "category" and config["init"] == f"category:{model_dir}" and config["init_kind"] == "category"
    assert summary["init_source"]["category"] == "chair"
    assert summary["optimizer"]["name"] == "Adam"
    frozen_params = [n for layer in saved.build().layers()[:k] for n in layer.param_names]
    assert summary["optimizer"]["frozen_parameters"] == frozen_params
    assert config["model"] == json.loads((model_dir / "init.json").read_text())["model_config"]
    assert RunConfig.from_json(config).init == f"category:{model_dir}"  # the resolved keys do not break reloading
    assert "started from the category model" in capsys.readouterr().out


@pytest.mark.parametrize("backbone,k", [("nerf", 1), ("nerf", 3), ("grid", 1), ("grid", 2)])
def test_transfer_fit_changes_exactly_the_unfrozen_parameters(world, backbone, k):
    scene = load_scene(world["scene"])
    model, _, info = build_initial_model(_run_config(world, backbone, f"category:{world['models'][backbone]}", k), scene, CPU)
    saved = load_init(world["models"][backbone]).state
    frozen = set(info.frozen_parameters)
    assert frozen == {n for layer in model.layers()[:k] for n in layer.param_names} and frozen
    for name, p in model.named_parameters():  # starts exactly at the category model
        assert torch.equal(p.detach(), saved[name]), name
    fit(model, scene, FitConfig(iters=4, batch_rays=64, eval_every=0), background=torch.ones(3))
    for name, p in model.named_parameters():
        if name in frozen:
            assert torch.equal(p.detach(), saved[name]) and p.grad is None, name
        else:
            assert not torch.equal(p.detach(), saved[name]), name


@pytest.mark.parametrize("backbone", ["nerf", "grid"])
def test_transfer_starts_well_above_scratch_on_a_scene_of_the_category(world, backbone):
    """On the held-out chair, the category model renders much better before any step than a scratch
    fit's start (about +3 dB here) and than the same architecture freshly initialised, which is what a
    fit would start from if the weights were not loaded (+2 dB for the MLP, +1.5 dB for the grid,
    whose fresh fine stage already renders a light haze); its first training iteration too."""
    scene = load_scene(world["scene"])
    saved = load_init(world["models"][backbone])
    starts = {
        "scratch": build_initial_model(_run_config(world, backbone, "scratch"), scene, CPU)[0],
        "fresh": build_model(backbone, saved.model_config, torch.tensor(CANONICAL_BOX), seed=0),
        "category": build_initial_model(_run_config(world, backbone, f"category:{world['models'][backbone]}"), scene, CPU)[0],
    }
    first = {}
    for name, model in starts.items():
        initial = evaluate_views(model, scene, list(scene.splits["train"]), torch.ones(3), with_ssim=False).psnr
        records = []
        fit(model, scene, FitConfig(iters=1, batch_rays=256, eval_every=0, holdout_tile=0.0), background=torch.ones(3),
            callbacks=[lambda record, m, s: records.append(record)])
        first[name] = (initial, records[0].train_psnr)
    for other, margin in (("scratch", 2.0), ("fresh", 2.0 if backbone == "nerf" else 1.0)):
        assert first["category"][0] > first[other][0] + margin, (other, first)
        assert first["category"][1] > first[other][1] + margin, (other, first)


def test_meta_initialisation_loads_through_the_same_path(world, tmp_path):
    scene = load_scene(world["scene"])
    overrides = MODELS["nerf"]
    config = config_from_dict("nerf", {**vars(default_config("nerf")), **overrides})
    source = build_model("nerf", config, torch.tensor([[-1.0] * 3, [1.0] * 3]), seed=7)
    save_init(tmp_path / "meta", source, "meta", {"algorithm": "test"})
    summary = run_fit(_run_config(world, "nerf", f"meta:{tmp_path / 'meta'}", freeze=1), tmp_path / "run")
    assert summary["init"] == "meta" and summary["init_source"] == {"algorithm": "test"}
    assert summary["frozen_layers"] == ["trunk.0"]
    model, _, _ = build_initial_model(_run_config(world, "nerf", f"meta:{tmp_path / 'meta'}"), scene, CPU)
    for name, p in model.named_parameters():
        assert torch.equal(p, source.state_dict()[name]), name
    with pytest.raises(ConfigError, match="is a 'meta' initialisation, not 'category'"):
        build_initial_model(_run_config(world, "nerf", f"category:{tmp_path / 'meta'}"), scene, CPU)


def test_resume_of_a_transfer_fit_continues_from_its_checkpoint(world, tmp_path):
    config = RunConfig(scene=str(world["scene"]), backbone="nerf", init=f"category:{world['models']['nerf']}", freeze=1,
                       fit=FitConfig(iters=6, batch_rays=64, eval_every=0, checkpoint_every=3))

    class Kill(Exception):
        pass

    def kill_at_4(record, model, state):
        if record.iter == 4:
            raise Kill

    with pytest.raises(Kill):
        run_fit(config, tmp_path / "killed", callbacks=[kill_at_4])
    summary = run_fit(config, tmp_path / "killed", resume=True)
    full = run_fit(config, tmp_path / "full")
    assert summary["frozen_layers"] == full["frozen_layers"] == ["trunk.0"]
    a, b = read_metrics(tmp_path / "killed" / "metrics.jsonl"), read_metrics(tmp_path / "full" / "metrics.jsonl")
    assert [r["train_psnr"] for r in a] == [r["train_psnr"] for r in b]


@pytest.mark.parametrize("case,needle", [
    ("scratch_freeze", "needs --init category:DIR or meta:DIR"),
    ("negative", "--freeze -1"),
    ("all_layers", "--freeze 6: this nerf model has 6 layers"),
    ("too_many", "--freeze 99"),
    ("backbone", "holds a nerf model, not grid"),
    ("shape", "--set width=64: the category model"),
    ("spec", "use scratch, carve, occupancy[:NET.safetensors], category:DIR or meta:DIR"),
    ("missing", "init.json: missing"),
    ("corrupt", "SHA-256"),
    ("kind", "is a 'category' initialisation, not 'meta'"),
])
def test_bad_init_or_freeze_is_one_line_exit_2_and_writes_nothing(world, tmp_path, capsys, case, needle):
    model_dir = world["models"]["nerf"]
    args = {
        "scratch_freeze": ["--backbone", "nerf", "--freeze", "1"],
        "negative": ["--init", f"category:{model_dir}", "--freeze", "-1"],
        "all_layers": ["--init", f"category:{model_dir}", "--freeze", "6"],
        "too_many": ["--init", f"category:{model_dir}", "--freeze", "99"],
        "backbone": ["--init", f"category:{model_dir}", "--backbone", "grid"],
        "shape": ["--init", f"category:{model_dir}", "--set", "width=64"],
        "spec": ["--init", f"categroy:{model_dir}"],
        "missing": ["--init", f"category:{tmp_path / 'nowhere'}"],
        "corrupt": ["--init", "category:CORRUPT"],
        "kind": ["--init", f"meta:{model_dir}"],
    }[case]
    if case == "corrupt":
        bad = tmp_path / "bad"
        bad.mkdir()
        for name in ("init.json", WEIGHTS):
            (bad / name).write_bytes((model_dir / name).read_bytes())
        data = bytearray((bad / WEIGHTS).read_bytes())
        data[-1] ^= 0xFF
        (bad / WEIGHTS).write_bytes(bytes(data))
        args = ["--init", f"category:{bad}"]
    out = tmp_path / "run"
    code = main(["fit", str(world["scene"]), "--out", str(out), *args, *FAST])
    assert code == 2
    assert needle in _one_error_line(capsys)
    assert not out.exists()
