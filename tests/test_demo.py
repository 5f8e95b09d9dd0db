"""Smoke test of the README's main job (`nerfmeta demo`) on a small configuration with a real tiny zoo."""

import json

import pytest

from nerfmeta.cli import build_parser, main
from nerfmeta.commands.demo import demo_verdict
from nerfmeta.demo import DemoConfig, run_demo
from nerfmeta.errors import ConfigError
from nerfmeta.zoo import load_zoo

SMALL = DemoConfig(known_category="chair", unseen_category="vase", resolution=16, downscale=1.0, views=4, test_views=2, iters=6,
                   eval_every=3)


def test_demo_routes_both_objects_and_compares_with_scratch(tmp_path, zoo_dir):
    out = tmp_path / "demo"
    result = run_demo(SMALL, out, zoo=load_zoo(zoo_dir))
    assert set(result.runs) == {"chair_000", "vase_000"}
    for name, run in result.runs.items():
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


def test_demo_verdict_says_when_the_scratch_grid_wins():
    def summary(routed, grid):
        return {"comparison": {"methods": {"routed": {"final_test_psnr": routed}, "scratch": {"final_test_psnr": grid}}}}

    assert demo_verdict({"a": summary(25.0, 24.0)}).startswith("verdict: the routed fits end at or above")
    lost = demo_verdict({"a": summary(25.0, 24.0), "b": summary(20.0, 27.0)})
    assert "ends above the routed fit on b:" in lost
    assert demo_verdict({"a": {"route": {}}}) is None


def test_demo_without_a_zoo_fits_from_scratch(tmp_path):
    result = run_demo(SMALL, tmp_path / "demo", zoo=None)
    assert all(s["route"]["route"] == "scratch" and "comparison" not in s for s in result.summaries.values())


def test_help_lists_every_command(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--help"])
    assert exit_.value.code == 0
    text = capsys.readouterr().out
    for command in ("inspect", "fit", "make-collection", "demo", "classify", "meta-train", "pretrain"):
        assert command in text
    assert build_parser().prog == "nerfmeta"
