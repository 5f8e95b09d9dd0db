"""``nerfmeta render``: videos of a tiny fitted run (smoke), the file rules, and the writer's atomicity."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from nerfmeta.cli import main
from nerfmeta.commands.render import frame_scene, load_run, parse_resolution
from nerfmeta.errors import ConfigError
from nerfmeta.fit.evaluate import render_view
from nerfmeta.render.video import VideoWriter, even_size, made_by_nerfmeta

pytest.importorskip("imageio_ffmpeg")


@pytest.fixture(scope="module")
def fitted(tiny_scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("render") / "run"
    assert main(["fit", str(tiny_scene), "--out", str(out), "--init", "scratch", "--iters", "3", "--batch-rays", "256",
                 "--eval-views", "1", "--renders", "0", "--set", "coarse_iters=2", "--set", "growth_steps=[]"]) == 0
    return out


def test_orbit_mp4(fitted: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "orbit.mp4"
    assert main(["render", str(fitted), "--out", str(out), "--path", "orbit", "--frames", "5", "--resolution", "16x12"]) == 0
    frames = iio.imread(out)
    assert frames.shape == (5, 12, 16, 3) and frames.std() > 0
    assert made_by_nerfmeta(out) and "5 frames, orbit path, 16x12" in capsys.readouterr().out
    assert [p.name for p in tmp_path.iterdir()] == ["orbit.mp4"]  # no temporary file left


def test_auto_picks_orbit_and_test_gif_has_every_test_view(fitted: Path, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "test.gif"
    assert main(["render", str(fitted), "--out", str(out), "--path", "test", "--resolution", "0.5"]) == 0
    frames = iio.imread(out, index=None)
    assert frames.shape[:3] == (4, 16, 16)  # the tiny scene's 4 test views at half its 32x32
    assert made_by_nerfmeta(out)
    assert main(["render", str(fitted), "--out", str(tmp_path / "auto.gif"), "--frames", "2", "--resolution", "8x8"]) == 0
    assert "orbit path" in capsys.readouterr().out  # the tiny scene's cameras surround the spheres


def test_path_frames_are_rendered_by_the_test_view_renderer(fitted: Path) -> None:
    model, scene, config = load_run(fitted, None)
    view = int(scene.split_indices("test")[0])
    background = torch.tensor(config.background)
    expected = render_view(model, scene, view, background).rgb
    frames = frame_scene(scene, scene.poses[view:view + 1].double(), scene.height, scene.width)
    torch.testing.assert_close(render_view(model, frames, 0, background).rgb, expected)


def test_files_nerfmeta_did_not_write_are_never_replaced(fitted: Path, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    mine = tmp_path / "holiday.gif"
    mine.write_bytes(b"GIF89a a user's own animation")
    args = ["render", str(fitted), "--frames", "2", "--resolution", "8x8"]
    assert main([*args, "--out", str(mine)]) == 2
    assert "exists; pass --overwrite" in capsys.readouterr().err
    assert main([*args, "--out", str(mine), "--overwrite"]) == 2
    assert "was not written by 'nerfmeta render'; it is never replaced" in capsys.readouterr().err
    assert mine.read_bytes() == b"GIF89a a user's own animation"
    ours = tmp_path / "ours.gif"
    assert main([*args, "--out", str(ours)]) == 0
    first = ours.read_bytes()
    assert main([*args, "--out", str(ours), "--frames", "3", "--overwrite"]) == 0
    assert ours.read_bytes() != first and iio.imread(ours, index=None).shape[0] == 3


@pytest.mark.parametrize("args,message", [
    (["--out", "v.avi"], "must end in .mp4 or .gif"),
    (["--out", "v.gif", "--resolution", "big"], "expected WxH"),
    (["--out", "v.gif", "--frames", "0"], "--frames 0: must be >= 1"),
])
def test_bad_options_are_one_line(fitted: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], args, message) -> None:
    args = [a if not a.startswith("v.") else str(tmp_path / a) for a in args]
    assert main(["render", str(fitted), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not any(tmp_path.iterdir())


def test_not_a_run_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["render", str(tmp_path), "--out", str(tmp_path / "v.gif")]) == 2
    assert "not a 'nerfmeta fit' run folder" in capsys.readouterr().err


def test_parse_resolution() -> None:
    assert parse_resolution("640x360", 100, 200) == (360, 640)
    assert parse_resolution("0.5", 100, 200) == (50, 100)
    with pytest.raises(ConfigError):
        parse_resolution("0", 100, 200)
    assert even_size(13, 9) == (12, 8)


@pytest.mark.parametrize("suffix", [".mp4", ".gif"])
def test_a_failure_mid_video_leaves_nothing(tmp_path: Path, suffix: str) -> None:
    target = tmp_path / f"v{suffix}"
    with pytest.raises(RuntimeError, match="render failed"):
        with VideoWriter(target, 10) as writer:
            writer.append(np.zeros((2, 8, 8, 3), np.uint8))
            raise RuntimeError("render failed")
    assert not any(tmp_path.iterdir())
    with VideoWriter(target, 10) as writer:
        writer.append(np.stack([np.full((8, 8, 3), 0.25, np.float32), np.full((8, 8, 3), 0.75, np.float32)]))
        writer.close()
    assert made_by_nerfmeta(target) and iio.imread(target, index=None).shape[0] == 2


def test_auto_follows_the_walk_of_an_unbounded_capture(tiny_scene: Path) -> None:
    import dataclasses

    from test_paths_camera import ring

    from nerfmeta.commands.render import path_poses
    from nerfmeta.data import load_scene
    from nerfmeta.data.scene_type import SceneType

    scene = load_scene(tiny_scene)
    n = scene.poses.shape[0]
    walk = ring(n, turn=0.75).to(scene.poses.dtype)  # 22.5-degree steps (12 views): a walk
    unbounded = dataclasses.replace(scene, poses=walk, scene_type=SceneType("unbounded", "test"))
    name, poses = path_poses(unbounded, "auto", 7)
    assert name == "walk" and poses.shape == (7, 4, 4)
    assert path_poses(dataclasses.replace(unbounded, scene_type=SceneType("object", "test")), "auto", 7)[0] == "orbit"
    around = dataclasses.replace(unbounded, poses=ring(n, turn=3.0).to(scene.poses.dtype))  # 90-degree steps
    assert path_poses(around, "auto", 7)[0] == "orbit"
