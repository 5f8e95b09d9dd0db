"""Smoke test of the README's main job (`nerfmeta demo`) on a small configuration."""

import json

import pytest

from nerfmeta.cli import build_parser, main
from nerfmeta.demo import DemoConfig, run_demo
from nerfmeta.errors import ConfigError


def test_demo_generates_inspects_and_fits(tmp_path):
    out = tmp_path / "demo"
    result = run_demo(DemoConfig(resolution=16, views=6, test_views=2, time_budget_s=1.5), out)
    assert (out / "inspect" / "cameras.png").is_file()
    for name in ("summary.json", "metrics.jsonl", "psnr_vs_iter.png", "psnr_vs_time.png"):
        assert (out / "fit" / name).is_file(), name
    summary = json.loads((out / "fit" / "summary.json").read_text())
    assert summary == result.summary
    assert summary["category"] == "chair" and summary["test_views"] == 2
    assert summary["stop_reason"].startswith("time budget")
    with pytest.raises(ConfigError, match="--overwrite"):
        run_demo(DemoConfig(resolution=16, views=6, test_views=2, time_budget_s=1.0), out)


def test_help_lists_every_command(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--help"])
    assert exit_.value.code == 0
    text = capsys.readouterr().out
    for command in ("inspect", "fit", "make-collection", "demo"):
        assert command in text
    assert build_parser().prog == "nerfmeta"
