"""The default route on the voxel grid: a scratch grid route becomes the zoo's learned occupancy start where it applies."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

import nerfmeta.route as route_module
from nerfmeta.cli import main
from nerfmeta.route import OCCUPANCY_PX, Route, occupancy_route
from nerfmeta.zoo import load_zoo

NET = Path("/zoo/occupancy/model.safetensors")
SCRATCH = Route("scratch", "scratch", 0, "the model zoo holds no grid prior (only nerf ones): fitting the grid from scratch",
                backbone="grid")


def facts(side: int, alpha: bool = True) -> tuple[int, bool]:
    return side, alpha


def test_an_object_scene_within_the_sizes_gets_the_learned_start():
    route = occupancy_route(SCRATCH, NET, facts(128))
    assert (route.route, route.init, route.freeze, route.backbone) == ("occupancy", f"occupancy:{NET}", 0, "grid")
    assert [(c.name, c.prior, c.passed) for c in route.checks] == [("resolution", "occupancy", True),
                                                                    ("background", "occupancy", True)]
    assert "learned occupancy" in route.reason and str(NET) in route.reason


@pytest.mark.parametrize("side", [OCCUPANCY_PX[0] - 1, OCCUPANCY_PX[1] + 1, 64, 800])
def test_views_outside_the_measured_sizes_keep_scratch_and_say_why(side):
    route = occupancy_route(SCRATCH, NET, facts(side))
    assert (route.route, route.init) == ("scratch", "scratch")
    failed = [c for c in route.checks if not c.passed]
    assert [c.name for c in failed] == ["resolution"] and failed[0].figures == {"scene_px": side, "allowed_px": list(OCCUPANCY_PX)}
    assert route.reason.startswith(SCRATCH.reason) and f"{side} px views are outside" in route.reason


@pytest.mark.parametrize("side", OCCUPANCY_PX)
def test_the_sizes_include_their_ends(side):
    assert occupancy_route(SCRATCH, NET, facts(side)).route == "occupancy"


def test_a_photograph_keeps_scratch():
    route = occupancy_route(SCRATCH, NET, facts(128, alpha=False))
    assert route.route == "scratch" and [c.name for c in route.checks if not c.passed] == ["background"]
    assert "opaque" in route.reason


def test_other_routes_and_a_zoo_without_a_network_are_left_alone():
    for route in (Route("category", "category:/z/c", 1, "chair", backbone="grid"), Route("meta", "meta:/z/m", 0, "?", backbone="grid"),
                  Route("scratch", "scratch", 0, "nerf scratch", backbone="nerf")):
        assert occupancy_route(route, NET, facts(128)) == route
    assert occupancy_route(SCRATCH, None, facts(128)) == SCRATCH
    assert occupancy_route(SCRATCH, NET, None) == SCRATCH  # no readable image: the loader will say why


GRID = ["--set", "num_voxels=1728", "--set", "coarse_num_voxels=512", "--set", "coarse_iters=2", "--set", "growth_steps=[]"]
FAST = ["--iters", "3", "--batch-rays", "32", "--eval-every", "0", "--no-eval-ssim"]


def test_a_plain_fit_with_the_zoo_routes_to_the_learned_start_and_compares_with_scratch(tiny_scene, tmp_path, zoo_dir,
                                                                                          monkeypatch, capsys):
    monkeypatch.setattr(route_module, "OCCUPANCY_PX", (16, 64))  # the tiny scene's 32 px views
    out = tmp_path / "run"
    assert main(["fit", str(tiny_scene), "--out", str(out), "--zoo", str(zoo_dir), "--compare", "scratch", *GRID, *FAST]) == 0
    summary = json.loads((out / "summary.json").read_text())
    net = load_zoo(zoo_dir).occupancy_net
    assert summary["route"]["route"] == "occupancy" and summary["route"]["init"] == f"occupancy:{net}"
    assert summary["init"] == "occupancy" and summary["init_path"] == str(net.resolve())
    assert summary["init_source"]["kind"] == "occupancy"
    assert json.loads((out / "config.json").read_text())["init"] == f"occupancy:{net}"
    assert (out / "compare" / "scratch" / "summary.json").is_file()  # the scratch grid beside it, not skipped
    assert summary["comparison"]["baseline"] == "scratch"
    assert "learned occupancy" in capsys.readouterr().out


def test_a_plain_fit_of_small_views_keeps_the_scratch_grid_without_loading_the_scene_to_route_it(tiny_scene, tmp_path,
                                                                                                   zoo_dir, monkeypatch):
    def no_load(config):
        raise AssertionError("the route loaded the scene")

    monkeypatch.setattr(route_module, "scene_facts", no_load)
    out = tmp_path / "run"
    assert main(["fit", str(tiny_scene), "--out", str(out), "--zoo", str(zoo_dir), *GRID, *FAST]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["route"]["route"] == "scratch" and summary["init"] == "scratch"
    assert {c["name"]: c["passed"] for c in summary["route"]["checks"] if c["prior"] == "occupancy"} == {
        "resolution": False, "background": True}
    assert "no learned occupancy start" in summary["route"]["reason"] and "32 px views are outside" in summary["route"]["reason"]


def test_the_views_are_read_from_one_header_as_the_loader_sizes_them(tiny_scene, tmp_path):
    from PIL import Image

    from nerfmeta.data import load_scene
    from nerfmeta.fit.run import RunConfig
    from nerfmeta.route import scene_facts, view_facts

    def config(scene, **kw):
        return RunConfig(scene=str(scene), backbone="grid", **kw)

    for downscale in (1.0, 2.0, 3.0):  # the loader's own size, without loading
        loaded = load_scene(tiny_scene, downscale=downscale)
        assert view_facts(config(tiny_scene, downscale=downscale)) == (max(loaded.height, loaded.width), True)
    given = scene_facts(config(tiny_scene))
    assert view_facts(config(tiny_scene), given) == (max(given.resolution), True)
    big = tmp_path / "big"
    (big / "train").mkdir(parents=True)
    Image.new("RGBA", (128, 100)).save(big / "train" / "r_0.png")
    assert view_facts(config(big)) == (128, True) and view_facts(config(big, downscale=1.3)) == (98, True)
    Image.new("RGB", (128, 128)).save(big / "train" / "r_0.png")
    assert view_facts(config(big)) == (128, False)  # opaque: a photograph
    Image.new("RGBA", (4000, 3000)).save(big / "train" / "r_0.png")
    assert view_facts(config(big)) == (1000, True)  # --max-side 1600 halves until it fits: 1/4
    assert view_facts(config(big, max_side=150)) == (125, True)
    (big / "train" / "r_0.png").write_bytes(b"not a png")
    assert view_facts(config(big)) is None  # unreadable: the loader says so, not the route
    assert view_facts(config(tmp_path / "clip.mp4")) is None
