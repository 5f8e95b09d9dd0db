"""The learned occupancy start as a fit's init (``--init occupancy[:NET]``), its training, and its zoo entry."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from conftest import TINY_ZOO
from nerfmeta.cli import main
from nerfmeta.errors import ConfigError
from nerfmeta.io import save_tensors, sha256_file
from nerfmeta.priors.occupancy import N_FEATURES, THRESHOLD, OccupancyNet, load_occupancy_net
from nerfmeta.zoo import MANIFEST, load_zoo, write_manifest
from pretrain.occupancy import OccupancyTrainConfig, OccupancyVolume, train_occupancy_net
from pretrain.zoo import add_occupancy

GRID = ["--set", "num_voxels=1728", "--set", "coarse_num_voxels=512", "--set", "coarse_iters=2", "--set", "growth_steps=[]"]
FAST = ["--iters", "3", "--batch-rays", "32", "--eval-every", "0", "--no-eval-ssim"]


def saved_net(path: Path, logit: float) -> Path:
    """A network giving every point the occupancy logit ``logit``, saved at ``path``."""
    net = OccupancyNet(width=2)
    with torch.no_grad():
        for p in net.parameters():
            p.zero_()
        net.net[-1].bias.fill_(logit)
    save_tensors(path, net.state_dict())
    return path


def test_fit_from_a_named_network_records_the_file_and_the_start(tiny_scene, tmp_path, capsys):
    net = saved_net(tmp_path / "net.safetensors", 10.0)
    out = tmp_path / "run"
    assert main(["fit", str(tiny_scene), "--out", str(out), "--init", f"occupancy:{net}", *GRID, *FAST]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["backbone"] == "grid" and summary["init"] == "occupancy"
    assert summary["init_path"] == str(net.resolve()) and summary["init_sha256"] == sha256_file(net)
    start = summary["init_source"]
    assert start["kind"] == "occupancy" and start["applied"] and start["figures"]["occupied_fraction"] > 0
    assert json.loads((out / "config.json").read_text())["init"] == f"occupancy:{net}"
    assert "--init occupancy: the coarse grid starts from the learned occupancy" in capsys.readouterr().out


def test_a_learned_start_keeps_a_longer_coarse_stage_unless_the_user_sets_one(tiny_scene, tmp_path, monkeypatch):
    """200 coarse steps carve a too-full start before the fine stage inherits it (BENCHMARKS.md, *Grid priors*,
    "Session 34"); a user's ``--set coarse_iters`` wins, and a start that does not apply leaves the scratch grid."""
    import nerfmeta.priors.occupancy as occupancy
    from nerfmeta.fields.voxel_grid import VoxelGridConfig
    from nerfmeta.fit.run import RunConfig, build_initial_model, run_scene
    from nerfmeta.priors.start import StartReport

    net = saved_net(tmp_path / "net.safetensors", 10.0)
    small = {"num_voxels": 1728, "coarse_num_voxels": 512, "growth_steps": []}

    def built(settings):
        config = RunConfig(scene=str(tiny_scene), backbone="grid", init=f"occupancy:{net}", model=settings)
        model, model_config, info = build_initial_model(config, run_scene(config), torch.device("cpu"))
        assert model.config == model_config  # config.json records the grid the fit runs
        return model_config.coarse_iters, info.meta["applied"]

    scratch = VoxelGridConfig().coarse_iters
    assert occupancy.COARSE_ITERS > scratch
    assert built(small) == (occupancy.COARSE_ITERS, True)
    assert built({**small, "coarse_iters": 7}) == (7, True)

    def no_start(build, scene, background, net):
        return build(scene.bounds), StartReport(False, "occupancy", "no learned start: a test", 0.0, {})

    monkeypatch.setattr(occupancy, "learned_start", no_start)
    assert built(small) == (scratch, False)


def test_bare_occupancy_takes_the_zoos_network(tiny_scene, tmp_path, zoo_dir):
    out = tmp_path / "run"
    assert main(["fit", str(tiny_scene), "--out", str(out), "--init", "occupancy", "--zoo", str(zoo_dir), *GRID, *FAST]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["init_path"] == str(zoo_dir.resolve() / "occupancy" / "model.safetensors")
    assert summary["init_source"]["kind"] == "occupancy"


def test_occupancy_init_errors_are_one_line_and_write_nothing(tiny_scene, tmp_path, zoo_dir, capsys):
    bare = tmp_path / "zoo_without"
    shutil.copytree(zoo_dir, bare)
    doc = json.loads((bare / MANIFEST).read_text())
    write_manifest(bare, [e for e in doc["entries"] if e["kind"] != "occupancy"],
                   **{k: v for k, v in doc.items() if k not in ("format", "entries", "total_bytes")})
    cases = [
        (["--init", "occupancy"], "--init occupancy needs a model zoo"),  # the tests' default: no zoo
        (["--init", "occupancy", "--zoo", str(bare)], "has no occupancy network"),
        (["--init", f"occupancy:{tmp_path / 'absent.safetensors'}"], f"{tmp_path / 'absent.safetensors'}: no such occupancy"),
        (["--init", f"occupancy:{saved_net(tmp_path / 'n.safetensors', 1.0)}", "--backbone", "nerf"],
         "--init occupancy starts a voxel grid"),
        (["--init", "carve", "--zoo", str(zoo_dir)], "--zoo is used by --init auto and --init occupancy only"),
    ]
    for k, (args, message) in enumerate(cases):
        out = tmp_path / f"run{k}"
        assert main(["fit", str(tiny_scene), "--out", str(out), *args, *FAST]) == 2, args
        err = capsys.readouterr().err.strip()
        assert message in err and "\n" not in err, (args, err)
        assert not out.exists() or not any(out.iterdir()), args


def ball_scene() -> OccupancyVolume:
    """An 8^3 scene: a ball occupied, its foreground feature high inside, noise elsewhere, the loss taken within 1.2."""
    x = torch.linspace(-1, 1, 8)
    r = (x[:, None, None] ** 2 + x[None, :, None] ** 2 + x[None, None, :] ** 2).sqrt()
    features = 0.2 * torch.rand(N_FEATURES, 8, 8, 8, generator=torch.Generator().manual_seed(0))
    features[1] += (r < 0.7).float()
    return OccupancyVolume(features, r < 1.2, r < 0.7)


def bce(net: OccupancyNet, v: OccupancyVolume) -> float:
    with torch.no_grad():
        return float(F.binary_cross_entropy_with_logits(net(v.features)[v.allowed], v.target[v.allowed].float()))


@pytest.mark.parametrize("seed", [0, 1])
def test_training_is_deterministic_and_fits_a_scene(seed):
    v = ball_scene()
    config = OccupancyTrainConfig(width=4, steps=100, lr=1e-2, pos_weight=1.0, seed=seed)
    torch.manual_seed(seed)
    before = bce(OccupancyNet(4), v)  # the weights training starts from (same seed)
    net, log = train_occupancy_net([v], config, log_every=50)
    again, _ = train_occupancy_net([v], config, log_every=50)
    assert all(torch.equal(a, b) for a, b in zip(net.state_dict().values(), again.state_dict().values()))
    assert [r["step"] for r in log] == [0, 50, 99] and log[0]["loss"] == pytest.approx(before, abs=1e-4)
    assert bce(net, v) < 0.25 * before and not net.training
    with torch.no_grad():
        assert bool(((net(v.features) > 0) == v.target)[v.allowed].all())
    with pytest.raises(ValueError, match="no training scenes"):
        train_occupancy_net([], config)


def test_the_zoo_build_lists_its_network_and_adds_it_to_an_older_zoo(zoo_dir, tmp_path):
    zoo = load_zoo(zoo_dir)
    entry = zoo.occupancy
    assert entry is not None and set(entry.files) == {"occupancy.json", "model.safetensors"}
    record = json.loads((entry.path / "occupancy.json").read_text())
    assert record["config"]["steps"] == 4 and record["scenes"] == 2 and record["collections"][0]["seed"] == TINY_ZOO.seed + 1
    load_occupancy_net(entry.path / "model.safetensors")
    # an older zoo (no occupancy entry): --only occupancy adds it from the work folder, other entries untouched
    older = tmp_path / "zoo"
    shutil.copytree(zoo_dir, older)
    shutil.rmtree(older / "occupancy")
    doc = json.loads((older / MANIFEST).read_text())
    others = [e for e in doc["entries"] if e["kind"] != "occupancy"]
    write_manifest(older, others, **{k: v for k, v in doc.items() if k not in ("format", "entries", "total_bytes")})
    add_occupancy(TINY_ZOO, older, zoo_dir.parent / "work")
    again = json.loads((older / MANIFEST).read_text())
    assert [e for e in again["entries"] if e["kind"] != "occupancy"] == others
    assert load_zoo(older).occupancy.files == entry.files
    # another recipe, or an occupancy/ folder the manifest does not list: refused, nothing changed
    with pytest.raises(ConfigError, match="built with another recipe"):
        add_occupancy(TINY_ZOO.__class__(**{**TINY_ZOO.__dict__, "views": 5}), older, zoo_dir.parent / "work")
    write_manifest(older, others, **{k: v for k, v in doc.items() if k not in ("format", "entries", "total_bytes")})
    before = sha256_file(older / "occupancy" / "model.safetensors")
    with pytest.raises(ConfigError, match="does not list it"):
        add_occupancy(TINY_ZOO, older, zoo_dir.parent / "work")
    assert sha256_file(older / "occupancy" / "model.safetensors") == before


def test_the_shipped_zoo_has_the_measured_network():
    """model_zoo/'s network is the one BENCHMARKS.md measures: width 16, 33k weights, trained on seeds 1 and 2; its
    record names the threshold the start uses."""
    zoo = load_zoo(Path(__file__).resolve().parents[1] / "model_zoo")
    net = load_occupancy_net(zoo.occupancy_net)
    assert net.net[0].out_channels == 16 and sum(p.numel() for p in net.parameters()) == zoo.occupancy.metrics["weights"]
    assert [c["seed"] for c in zoo.occupancy.config["collections"]] == [1, 2]
    assert zoo.occupancy.config["threshold"] == THRESHOLD
