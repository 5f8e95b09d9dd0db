"""Hostile input files (issue 15): each case is a real CLI call that must end in a complete run or in
one line on stderr with exit code 2, never a traceback after work was done or a silently wrong result."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from nerfmeta.cli import main
from nerfmeta.data.synthetic import write_tiny_scene


def one_line_error(capsys: pytest.CaptureFixture[str], code: int, command: str) -> str:
    """The single stderr line of a refused command (exit 2, no traceback)."""
    err = capsys.readouterr().err
    lines = err.rstrip("\n").split("\n")
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith(f"nerfmeta {command}: error: "), err
    assert "Traceback" not in err
    return lines[0]


# --- images too small for a metric ----------------------------------------------------------------


@pytest.mark.parametrize(("size", "extra"), [(8, []), (32, ["--downscale", "4"]), (32, ["--downscale", "64"])])
def test_images_smaller_than_the_ssim_window_fit_and_record_why_ssim_is_missing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], size: int, extra: list[str]
) -> None:
    scene = write_tiny_scene(tmp_path / "small", n_train=2, n_test=1, size=size)
    out = tmp_path / "run"
    code = main(["fit", str(scene), "--out", str(out), "--init", "scratch", "--iters", "2", *extra])
    assert code == 0, capsys.readouterr().err
    summary: dict[str, Any] = json.loads((out / "summary.json").read_text())
    assert summary["test_ssim"] is None
    decision = summary["decisions"]["final_ssim"]
    assert decision["value"] is False and "smaller than its 11x11 window" in decision["reason"]
    assert (out / "checkpoint.safetensors").is_file()
