"""Smoke test of the README's main job (`nerfmeta demo`) on a small configuration with a real tiny zoo."""

import dataclasses
import json

import pytest

from nerfmeta.cli import build_parser, main
from nerfmeta.commands.demo import demo_verdict
from nerfmeta.demo import DemoConfig, run_demo
from nerfmeta.errors import ConfigError
from nerfmeta.zoo import load_zoo

SMALL = DemoConfig(known_category="chair", unseen_category="vase", resolution=16, downscale=1.0, views=4, test_views=2, iters=6,
                   eval_every=3, grid_iters=4, grid_eval_every=2)


def test_demo_routes_both_objects_and_compares_with_scratch(tmp_path, zoo_dir):
    out = tmp_path / "demo"
    result = run_demo(SMALL, out, zoo=load_zoo(zoo_dir))
    assert set(result.runs) == {"chair_000", "vase_000", "chair_000_grid", "vase_000_grid"}
    for name in ("chair_000_grid", "vase_000_grid"):  # the plain fit: the grid, whose 16 px views keep the scratch route
        summary = json.loads((result.runs[name] / "summary.json").read_text())
        assert summary["backbone"] == "grid" and summary["iters"] == 4 and summary["route"]["route"] == "scratch"
        assert "comparison" not in summary and not (result.runs[name] / "compare").exists()
    for name in ("chair_000", "vase_000"):
        run = result.runs[name]
        summary = json.loads((run / "summary.json").read_text())
        assert summary == result.summaries[name]
        assert summary["route"]["route"] in ("category", "meta") and summary["iters"] == 6
        grid = json.loads((run / "compare" / "scratch" / "summary.json").read_text())
        assert grid["backbone"] == "grid" and grid["init"] == "scratch"  # the fair baseline: the tuned scratch grid
        assert json.loads((run / "compare" / "scratch-nerf" / "summary.json").read_text())["backbone"] == "nerf"
        assert "comparison" in summary and (run / "psnr_vs_time.png").is_file()
        assert summary["comparison"]["baseline"] == "scratch" and "voxel grid" in summary["comparison"]["headline"][0]
    with pytest.raises(ConfigError, match="--overwrite"):
        run_demo(SMALL, out, zoo=load_zoo(zoo_dir))


def test_demo_fits_each_object_as_a_plain_fit_would_with_the_learned_start(tmp_path, zoo_dir, monkeypatch):
    import nerfmeta.route as route_module

    monkeypatch.setattr(route_module, "OCCUPANCY_PX", (8, 32))  # the small demo's 16 px views
    result = run_demo(dataclasses.replace(SMALL, compare=("scratch",)), tmp_path / "demo", zoo=load_zoo(zoo_dir))
    for name in ("chair_000_grid", "vase_000_grid"):
        run = result.runs[name]
        summary = json.loads((run / "summary.json").read_text())
        assert summary["route"]["route"] == "occupancy" and summary["init"] == "occupancy" and summary["iters"] == 4
        assert summary["comparison"]["baseline"] == "scratch" and (run / "compare" / "scratch" / "summary.json").is_file()
    report = (tmp_path / "demo" / "report" / "report.md").read_text()
    assert "| occupancy | 2 |" in report  # the report groups the plain fits under their route
    # the runs are named from the report's folder: the folder was built aside and moved after the report was written
    assert "| ../chair_000_grid | chair_000 |" in report and ".partial-" not in report


def test_demo_verdict_says_when_the_scratch_grid_wins():
    def summary(routed, grid):
        return {"comparison": {"methods": {"routed": {"final_test_psnr": routed}, "scratch": {"final_test_psnr": grid}}}}

    assert demo_verdict({"a": summary(25.0, 24.0)}).startswith("verdict: the routed fits end at or above")
    lost = demo_verdict({"a": summary(25.0, 24.0), "b": summary(20.0, 27.0)})
    assert "ends above the routed fit on b:" in lost and lost.endswith("; the routed fit ends at or above it on a")
    assert "at or above it" not in demo_verdict({"b": summary(20.0, 27.0)})
    assert demo_verdict({"a": {"route": {}}}) is None


def test_demo_without_a_zoo_fits_from_scratch(tmp_path):
    result = run_demo(SMALL, tmp_path / "demo", zoo=None)
    assert set(result.summaries) == {"chair_000", "vase_000"}  # no zoo: no second, plain grid fit to show
    assert all(s["route"]["route"] == "scratch" and "comparison" not in s for s in result.summaries.values())


def test_help_lists_every_command(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--help"])
    assert exit_.value.code == 0
    text = capsys.readouterr().out
    for command in ("inspect", "fit", "make-collection", "demo", "classify", "meta-train", "pretrain"):
        assert command in text
    assert build_parser().prog == "nerfmeta"
