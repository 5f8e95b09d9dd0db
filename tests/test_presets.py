"""Named recipes (``nerfmeta fit --preset``): valid values, the command line's own values win, docs that match."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from nerfmeta.cli import main
from nerfmeta.errors import ConfigError
from nerfmeta.fields.registry import config_from_dict, default_config
from nerfmeta.fit.loop import FitConfig
from nerfmeta.presets import PRESETS, Preset, describe, get_preset, preset_backbone

README = Path(__file__).resolve().parents[1] / "README.md"
TINY_SDF = ["--set", "depth=2", "--set", "width=16", "--set", "n_samples=16", "--set", "color_grid=4"]
"""A tiny SDF on top of the preset (``--set`` wins), so the fit takes a second."""


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_preset_builds_its_backbone_and_fit_configs_and_changes_only_named_fields(name):
    preset = PRESETS[name]
    default = default_config(preset.backbone)
    config = config_from_dict(preset.backbone, {**dataclasses.asdict(default), **preset.model})
    for key, value in preset.model.items():
        assert getattr(config, key) == value and getattr(default, key) != value, key  # a preset never repeats a default
    fit = FitConfig(**preset.fit)
    assert all(getattr(fit, key) == value != getattr(FitConfig(), key) for key, value in preset.fit.items())


def test_the_concave_preset_is_the_recipe_the_benchmarks_measured():
    """The settings of BENCHMARKS.md's 10-minute mug fits (sections 9-16), every one of them: leaving out three of them
    is what made session 16's cups stay closed."""
    preset = get_preset("concave")
    # holdout_tile 0: the 10-minute fits were measured training on every pixel, to their last step
    assert preset.backbone == "sdf" and dict(preset.fit) == {"batch_rays": 512, "lr_decay": 0.3, "holdout_tile": 0.0}
    assert dict(preset.model) == {"view_dependent": False, "init_variance": 0.1, "variance_lr": 1e-2, "color_grid": 64,
                                  "eikonal_start_weight": 1e-3, "eikonal_ramp": (3500, 5000), "occupancy_margin": 1.0,
                                  "shell_weight": 5e-3}  # session 49's thin-shell prior (section 23)


def test_describe_spells_the_options_a_user_would_type_and_the_readme_shows_them():
    line = describe("concave", get_preset("concave"))
    assert line == ("--preset concave: --backbone sdf --batch-rays 512 --lr-decay 0.3 --holdout-tile 0 --set view_dependent=false "
                    "--set init_variance=0.1 --set variance_lr=0.01 --set color_grid=64 --set eikonal_start_weight=0.001 "
                    "--set eikonal_ramp=[3500,5000] --set occupancy_margin=1 --set shell_weight=0.005")
    overridden = describe("concave", get_preset("concave"), {"lr_decay", "occupancy_margin", "not_in_the_preset"})
    assert overridden == ("--preset concave: --backbone sdf --batch-rays 512 --holdout-tile 0 --set view_dependent=false --set init_variance=0.1 "
                          "--set variance_lr=0.01 --set color_grid=64 --set eikonal_start_weight=0.001 "
                          "--set eikonal_ramp=[3500,5000] --set shell_weight=0.005 (--lr-decay, --set occupancy_margin: the options given)")
    readme = " ".join(README.read_text().split())
    assert "--preset concave" in readme
    assert line.split(": ", 1)[1] in readme  # the README spells out what the preset sets


def test_backbone_may_repeat_the_presets_but_not_contradict_it():
    preset = Preset(backbone="sdf", model={}, fit={}, about="")
    assert preset_backbone("p", preset, None) == "sdf" and preset_backbone("p", preset, "sdf") == "sdf"
    with pytest.raises(ConfigError, match="--preset p is a recipe for --backbone sdf, not --backbone grid"):
        preset_backbone("p", preset, "grid")
    with pytest.raises(ConfigError, match="unknown preset; choose one of concave"):
        get_preset("convex")


def test_fit_with_a_preset_saves_its_values_under_the_options_given(tiny_scene, tmp_path, capsys):
    out = tmp_path / "run"
    code = main(["fit", str(tiny_scene), "--out", str(out), "--init", "scratch", "--preset", "concave", "--iters", "3",
                 "--eval-views", "1", "--renders", "0", *TINY_SDF])
    assert code == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first == describe("concave", get_preset("concave"), {"color_grid", "width", "depth", "n_samples"})
    assert "color_grid=" not in first and first.endswith("(--set color_grid: the options given)")  # never a value not used
    config = json.loads((out / "config.json").read_text())
    assert config["backbone"] == "sdf" and config["fit"]["batch_rays"] == 512 and config["fit"]["lr_decay"] == 0.3
    model = config["model"]
    assert model["eikonal_ramp"] == [3500, 5000] and model["eikonal_start_weight"] == 0.001
    assert model["view_dependent"] is False and model["occupancy_margin"] == 1.0
    assert model["color_grid"] == 4 and model["width"] == 16  # --set wins over the preset

    again = tmp_path / "again"
    assert main(["fit", str(tiny_scene), "--out", str(again), "--init", "scratch", "--preset", "concave", "--iters", "2",
                 "--batch-rays", "32", "--lr-decay", "0.1", "--eval-views", "1", "--renders", "0", *TINY_SDF]) == 0
    fit = json.loads((again / "config.json").read_text())["fit"]
    assert fit["batch_rays"] == 32 and fit["lr_decay"] == 0.1  # an option given wins, even one that repeats a default


def test_the_readme_ramp_in_fractions_of_the_fit_is_a_valid_change_of_the_concave_preset():
    preset = get_preset("concave")
    config = config_from_dict("sdf", {**dataclasses.asdict(default_config("sdf")), **preset.model,
                                      "eikonal_ramp": (0, 0), "eikonal_ramp_progress": (0.4, 0.55)})
    assert config.eikonal_ramp_progress == (0.4, 0.55) and config.eikonal_start_weight == 1e-3


def test_the_default_route_takes_the_preset_too(tiny_scene, tmp_path):
    """``--init auto`` (the default) with no zoo of the preset's backbone fits it from scratch with the preset's values."""
    out = tmp_path / "run"
    assert main(["fit", str(tiny_scene), "--out", str(out), "--zoo", "none", "--preset", "concave", "--iters", "2",
                 "--eval-views", "1", "--renders", "0", *TINY_SDF]) == 0
    config = json.loads((out / "config.json").read_text())
    assert config["backbone"] == "sdf" and config["model"]["eikonal_ramp"] == [3500, 5000]
    assert config["fit"]["batch_rays"] == 512 and config["route"]["route"] == "scratch"
