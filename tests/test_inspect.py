"""``nerfmeta inspect`` and the library behind it (nerfmeta.inspect)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import imageio.v3 as iio
import pytest

from nerfmeta.cli import main
from nerfmeta.data import LoadOptions, load_scene
from nerfmeta.inspect import SceneSummary, format_summary, inspect_scene, summarize_scene
from nerfmeta.io import to_jsonable

LEGO = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "nerf_synthetic" / "lego"


def test_summary_of_tiny_scene(tiny_scene: Path) -> None:
    summary = summarize_scene(load_scene(tiny_scene))
    assert isinstance(summary, SceneSummary)
    assert summary.format == "blender" and summary.source == str(tiny_scene)
    assert summary.n_views == 12 and summary.views_per_split == {"train": 8, "test": 4}
    assert summary.holdout == "from file"
    assert (summary.height, summary.width, summary.downscale) == (32, 32, 1.0)
    focal = 16 / math.tan(0.35)
    assert summary.focal == pytest.approx((focal, focal), rel=1e-6)
    assert summary.principal_point == (16.0, 16.0) and not summary.intrinsics_vary
    assert (summary.near, summary.far, summary.category) == (2.0, 6.0, "spheres")
    assert summary.background == (1.0, 1.0, 1.0)
    lo, mid, hi = summary.camera_distance
    assert 3.5 < lo <= mid <= hi < 4.5  # cameras at radius 4 around a box near the origin
    text = format_summary(summary)
    assert "views            12 (train 8, test 4)" in text
    assert "near / far       2 / 6" in text and "category         spheres" in text


def test_inspect_smoke_with_out(tiny_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "report"
    assert main(["inspect", str(tiny_scene), "--out", str(out), "--downscale", "2", "--background", "black"]) == 0
    stdout = capsys.readouterr().out
    assert "resolution       16 x 16 (downscale 2)" in stdout and "background       0, 0, 0" in stdout
    assert sorted(p.name for p in out.iterdir()) == ["cameras.png", "inspect.json"]
    png = iio.imread(out / "cameras.png")
    assert png.ndim == 3 and png.shape[0] > 300 and png.shape[1] > 300
    assert png[..., :3].min() < 100  # something was drawn
    doc = json.loads((out / "inspect.json").read_text())
    assert doc["n_views"] == 12 and doc["width"] == 16 and doc["background"] == [0.0, 0.0, 0.0]


def test_inspect_json_equals_the_summary(tiny_scene: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["inspect", str(tiny_scene), "--json", "--background", "0.5,0.25,1"]) == 0
    printed = json.loads(capsys.readouterr().out)
    summary = inspect_scene(tiny_scene, LoadOptions(background=(0.5, 0.25, 1.0)))
    assert printed == json.loads(json.dumps(to_jsonable(summary)))
    assert printed["views_per_split"] == {"train": 8, "test": 4}


def test_inspect_scene_writes_nothing_without_out(
    tiny_scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    before = sorted(p.name for p in tiny_scene.rglob("*"))
    summary = inspect_scene(tiny_scene)
    assert sorted(p.name for p in tiny_scene.rglob("*")) == before
    assert summary.n_views == 12
    assert not any(tmp_path.iterdir())


@pytest.mark.slow
@pytest.mark.skipif(not LEGO.is_dir(), reason=f"NeRF-synthetic lego not found at {LEGO}")
def test_lego(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Full resolution: every header is checked and every image decoded.
    full = summarize_scene(load_scene(LEGO))
    assert (full.n_views, full.width, full.height) == (100, 800, 800)
    # every 8th view from 0: 0, 8, ..., 96 is 13 views
    assert full.views_per_split == {"train": 87, "test": 13}
    assert full.holdout == "every 8th view (no test split in the files)"
    assert full.focal[0] == pytest.approx(1111.111, rel=1e-4)
    assert (full.near, full.far) == (2.0, 6.0)
    assert main(["inspect", str(LEGO), "--downscale", "8", "--json", "--out", str(tmp_path / "o")]) == 0
    small = json.loads(capsys.readouterr().out)
    assert (small["width"], small["height"]) == (100, 100)
    assert small["focal"][0] == pytest.approx(1111.111 / 8, rel=1e-4)
    assert (tmp_path / "o" / "cameras.png").is_file()


@pytest.mark.parametrize("folded", [False, True])
def test_pose_jumps_name_a_folded_walk(tmp_path: Path, folded: bool) -> None:
    import numpy as np
    import sfm_scenes

    poses = sfm_scenes.ring_poses(24, turn=1.5)  # a walk of 22.5-degree steps, one and a half times round
    if folded:  # views 8-13 put on the far side, as beer's shipped COLMAP poses put three stretches of its walk
        half_turn = np.diag([-1.0, -1.0, 1.0, 1.0])
        poses[8:14] = half_turn @ poses[8:14]
    sfm_scenes.write_blender(tmp_path / "walk", np.zeros((24, 8, 8, 3), np.uint8), poses, 8.0)
    summary = summarize_scene(load_scene(tmp_path / "walk"))
    assert summary.pose_jumps == ([8, 14] if folded else [])
    assert ("views 8, 14 turn over 90 degrees" in format_summary(summary)) == folded


def test_fit_warns_of_a_folded_walk(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    import numpy as np
    import sfm_scenes

    poses = sfm_scenes.ring_poses(24, turn=1.5)
    poses[8:14] = np.diag([-1.0, -1.0, 1.0, 1.0]) @ poses[8:14]
    sfm_scenes.write_blender(tmp_path / "walk", np.zeros((24, 8, 8, 3), np.uint8), poses, 8.0)
    assert main(["fit", str(tmp_path / "walk"), "--out", str(tmp_path / "run"), "--iters", "1", "--eval-every", "0",
                 "--renders", "0", "--checkpoint-every", "0"]) == 0
    assert "views 8, 14 turn over 90 degrees" in caplog.text and "'nerfmeta poses'" in caplog.text
