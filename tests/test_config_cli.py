"""Options generated from the config dataclasses: the typed parser, one-line errors, the memory estimate."""

from __future__ import annotations

import argparse
import dataclasses
import re
from dataclasses import dataclass, replace
from typing import Literal

import pytest
import torch

from nerfmeta import config as options
from nerfmeta.budget import (
    MemoryEstimate,
    check_fit_memory,
    estimate_fit_memory,
    grid_parameter_count,
    nerf_parameter_count,
)
from nerfmeta.config import Bounds, bounded, parse_value
from nerfmeta.errors import ConfigError
from nerfmeta.fields.nerf_mlp import NerfMLP, NerfMLPConfig
from nerfmeta.fields.registry import build_model, default_config
from nerfmeta.fields.voxel_grid import VoxelGridConfig
from nerfmeta.fit.loop import FitConfig


# ----- the typed parser ------------------------------------------------------------------------------

@pytest.mark.parametrize("text,hint,expected", [
    ("3", int, 3),
    ("1e6", int, 1_000_000),
    ("-2", int, -2),
    ("0.25", float, 0.25),
    ("1e-3", float, 1e-3),
    ("true", bool, True),
    ("Off", bool, False),
    ("cuda:0", str, "cuda:0"),
    ('"auto"', str, "auto"),
    ("none", float | None, None),
    ("2.5", float | None, 2.5),
    ("true", bool | str, True),
    ("auto", bool | str, "auto"),
    ("100,200", tuple[int, ...], (100, 200)),
    ("[100, 200]", tuple[int, ...], (100, 200)),
    ("", tuple[int, ...], ()),
    ("[]", tuple[int, ...], ()),
    ("a,b", tuple[str, ...], ("a", "b")),
    ("0.5,1,0", tuple[float, float, float], (0.5, 1.0, 0.0)),
    ("fomaml", Literal["maml", "fomaml"], "fomaml"),
    ('{"a": 1}', dict, {"a": 1}),
])
def test_parse_value_exact_cases(text, hint, expected):
    value = parse_value(text, hint)
    assert value == expected and type(value) is type(expected)


@pytest.mark.parametrize("text,hint,needle", [
    ("abc", float, "expected a number"),
    ("1.5", int, "whole number"),
    ("1e400", int, "whole number"),
    ("inf", float, "finite"),
    ("nan", float, "finite"),
    ("-inf", float | None, "finite"),
    ("maybe", bool, "true or false"),
    ("1,x", tuple[int, ...], "whole number"),
    ("1,2", tuple[float, float, float], "3 comma-separated"),
    ("sgd", Literal["maml", "fomaml"], "one of maml, fomaml"),
    ("abc", float | None, "a number or none"),
])
def test_parse_value_refuses_with_what_was_expected(text, hint, needle):
    with pytest.raises(ValueError, match=needle):
        parse_value(text, hint)


def test_bounds_are_checked_and_nonfinite_only_where_allowed():
    assert parse_value("inf", float, bounds=Bounds(nonfinite=True)) == float("inf")
    assert parse_value("0", int, bounds=Bounds(low=0)) == 0
    with pytest.raises(ValueError, match="must be > 0"):
        parse_value("0", float, bounds=Bounds(low=0, low_open=True))
    with pytest.raises(ValueError, match=r"must be in \(0, 1\]"):
        parse_value("1.5", float, bounds=Bounds(low=0, high=1, low_open=True))
    with pytest.raises(ValueError, match="must be > 0"):  # the right type, out of range: not "expected a number or none"
        parse_value("-1", float | None, bounds=Bounds(low=0, low_open=True))


@dataclass(frozen=True)
class _Demo:
    """A config for the generator's tests."""

    name: str
    """The name."""
    iters: int = bounded(10, low=1)
    """Iterations."""
    rate: float | None = None
    """A rate; unset: the default."""
    flag: bool = True
    """Do the thing."""
    sizes: tuple[int, ...] = (1, 2)
    """Sizes,   spread over
    two lines with :class:`Markup`."""
    extra: dict = dataclasses.field(default_factory=dict)
    """Not an option (a dict)."""


def _demo_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="demo", exit_on_error=False)
    assert options.add_config_options(parser, _Demo, flags={"iters": "--steps"}) == ["name", "iters", "rate", "flag", "sizes"]
    return parser


def test_field_docs_are_one_line_plain_text():
    docs = options.field_docs(_Demo)
    assert docs["iters"] == "Iterations."
    assert docs["sizes"] == "Sizes, spread over two lines with Markup."


def test_generated_options_parse_typed_values_and_keep_not_given_apart():
    parser = _demo_parser()
    args = parser.parse_args(["--name", "x", "--steps", "5", "--no-flag", "--sizes", "3,4"])
    assert options.given_values(args, _Demo) == {"name": "x", "iters": 5, "flag": False, "sizes": (3, 4)}
    assert options.build_config(_Demo, options.given_values(args, _Demo)) == _Demo("x", 5, None, False, (3, 4))
    help_text = parser.format_help()
    assert "Iterations.; default 10" not in help_text and "Iterations; default 10" in help_text
    assert "--no-flag" in help_text and "--extra" not in help_text


def test_generated_option_refuses_out_of_range_value_in_argparse():
    with pytest.raises(argparse.ArgumentError, match="must be >= 1"):
        _demo_parser().parse_args(["--name", "x", "--steps", "0"])


def test_check_fields_catches_configs_built_in_code_or_from_json():
    with pytest.raises(ConfigError, match=r"fit config iters=0: must be >= 1"):
        FitConfig(iters=0)
    with pytest.raises(ConfigError, match="lr_decay"):
        FitConfig(lr_decay=float("nan"))
    assert FitConfig(time_budget_s=None, eval_every=0).eval_every == 0
    with pytest.raises(ConfigError, match=r"fit config batch_rays='abc': expected int"):
        FitConfig(batch_rays="abc")  # e.g. an untyped zoo manifest
    with pytest.raises(ConfigError, match=r"iters=True: expected int"):
        FitConfig(iters=True)
    assert FitConfig(time_budget_s=60).time_budget_s == 60  # an int is a float


@pytest.mark.parametrize("value,hint,ok", [
    (3, int, True), (3.0, int, False), (True, int, False), (3, float, True), (None, float | None, True),
    ("auto", bool | str, True), ((1, 2), tuple[int, ...], True), ([1, 2], tuple[int, ...], True),
    ((1, "a"), tuple[int, ...], False), ((1.0, 0.5), tuple[float, float, float], False), ("maml", Literal["maml"], True),
])
def test_is_instance_follows_the_parser(value, hint, ok):
    assert options._is_instance(value, hint) is ok


def test_overrides_are_typed_and_unknown_keys_get_a_suggestion():
    got = options.parse_overrides(["num_voxels=1e6", "growth_steps=[10, 20]", "view_dependent=auto", "tighten_box=false"],
                                  VoxelGridConfig)
    assert got == {"num_voxels": 1_000_000, "growth_steps": (10, 20), "view_dependent": "auto", "tighten_box": False}
    with pytest.raises(ConfigError, match="did you mean 'lr_features'"):
        options.parse_overrides(["lr_featurs=0.1"], VoxelGridConfig)
    with pytest.raises(ConfigError, match=r"--set lr=abc: expected a number"):
        options.parse_overrides(["lr=abc"], NerfMLPConfig)
    with pytest.raises(ConfigError, match="KEY=VALUE"):
        options.parse_overrides(["lr"], NerfMLPConfig)


# ----- the memory estimate ---------------------------------------------------------------------------

BOX = torch.tensor([[-1.0, -1.2, -0.8], [1.0, 1.2, 0.8]])


@pytest.mark.parametrize("overrides", [
    {"coarse_iters": 0, "num_voxels": 20**3, "growth_steps": ()},
    {"coarse_iters": 0, "num_voxels": 12**3, "growth_steps": (), "feature_dim": 9, "mlp_width": 16, "mlp_depth": 2},
    {"coarse_iters": 0, "num_voxels": 16**3, "growth_steps": (), "view_dependent": False},
])
def test_grid_parameter_estimate_matches_a_built_grid(overrides):
    config = replace(default_config("grid"), **overrides)
    model = build_model("grid", config, BOX, seed=0)
    real = sum(p.numel() for p in model.parameters())
    assert grid_parameter_count(config, BOX) == pytest.approx(real, rel=0.03)


@pytest.mark.parametrize("config", [default_config("nerf"), NerfMLPConfig(depth=3, width=32, skips=(1,), view_dependent=False)])
def test_nerf_parameter_estimate_is_exact(config):
    model = NerfMLP(config, BOX)
    assert nerf_parameter_count(config) == sum(p.numel() for p in model.parameters())


def test_memory_check_refuses_with_the_estimate_and_what_is_available():
    config = replace(default_config("grid"), num_voxels=10**12, coarse_num_voxels=64**3)
    estimate = estimate_fit_memory("grid", config, BOX, batch_rays=4096, train_pixels=8 * 32 * 32)
    assert estimate.parameters >= 4 * 10**12 * 10 * 0.95  # 10 channels of float32 per voxel
    assert estimate.optimizer == 3 * estimate.parameters
    with pytest.raises(ConfigError, match=r"needs about .*TiB.*only 16.0 GiB is available"):
        check_fit_memory(estimate, 16 * 2**30, what="grid config")
    small = MemoryEstimate(parameters=10, optimizer=30, batch=50, rays=10)
    check_fit_memory(small, 100, what="x")  # fits exactly: allowed
    check_fit_memory(small, None, what="x")  # unknown: allowed
    with pytest.raises(ConfigError):
        check_fit_memory(small, 99, what="x")


def test_backbone_configs_refuse_nonfinite_rates_from_json_too():
    from nerfmeta.fields.registry import config_from_dict

    with pytest.raises(ConfigError, match="lr_features=inf"):
        config_from_dict("grid", {"lr_features": float("inf")})
    with pytest.raises(ConfigError, match="lr=nan"):
        config_from_dict("nerf", {"lr": float("nan")})


@pytest.mark.parametrize("backbone,values,needle", [
    ("grid", {"render_phases": True}, "grid config render_phases=True: expected int"),  # a bool is no count
    ("grid", {"stepsize": "0.5"}, "grid config stepsize='0.5': expected float"),
    ("grid", {"growth_steps": [100, "x"]}, "expected tuple[int, ...]"),
    ("grid", {"feature_dim": 2.5}, "grid config feature_dim=2.5: expected int"),
    ("sdf", {"width": True}, "sdf config width=True: expected int"),
    ("nerf", {"skips": ["4"]}, "nerf config skips=('4',): expected tuple[int, ...]"),
])
def test_backbone_configs_refuse_wrong_types_from_json(backbone, values, needle):
    from nerfmeta.fields.registry import config_from_dict

    with pytest.raises(ConfigError, match=re.escape(needle)) as err:
        config_from_dict(backbone, values)  # a hand-edited config.json or init.json: one line, not a TypeError
    assert "\n" not in str(err.value)


def test_fit_help_documents_every_backbone_field():
    from nerfmeta.commands.fit import backbone_fields_help

    text = backbone_fields_help()
    for cls in (VoxelGridConfig, NerfMLPConfig):
        for f in dataclasses.fields(cls):
            assert f"  {f.name} (" in text, f.name
    assert "num_voxels (int, default 0): Voxels in the fine grids" in text
    assert "skips (tuple[int, ...], default [2])" in text  # the nerf default of a fit is the small preset
