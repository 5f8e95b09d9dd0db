"""A phone video as the capture: frames kept (the sharpest of each stretch), turned upright, posed, fitted.

What must hold: the windows cut the video into equal stretches; the kept frame of each is its sharpest; a
rotated video's frames come out as shown; ``nerfmeta poses VIDEO`` and ``nerfmeta fit VIDEO`` pose the kept frames
(checked against the true cameras) and cache them; a file ffmpeg cannot read is one line, exit 2, nothing cached.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from PIL import Image, ImageFilter

imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")

import sfm_scenes  # noqa: E402

from nerfmeta.cli import main  # noqa: E402
from nerfmeta.data.video import FrameConfig, extract_frames, frame_windows, sharpness  # noqa: E402


def write_video(path: Path, frames: np.ndarray, fps: int = 10) -> Path:
    """``frames`` (n, h, w, 3) uint8 as an H.264 MP4 of high quality."""
    writer = imageio_ffmpeg.write_frames(str(path), (frames.shape[2], frames.shape[1]), fps=fps, quality=10,
                                         macro_block_size=1)
    writer.send(None)
    for frame in frames:
        writer.send(np.ascontiguousarray(frame).tobytes())
    writer.close()
    return path


def _checker(height: int = 64, width: int = 96, cell: int = 8) -> np.ndarray:
    y, x = np.mgrid[:height, :width]
    board = (((y // cell) + (x // cell)) % 2 * 200 + 30).astype(np.uint8)
    return np.repeat(board[..., None], 3, axis=2)


def test_windows_are_equal_stretches() -> None:
    assert frame_windows(10, 3) == [0, 0, 0, 0, 1, 1, 1, 2, 2, 2]
    assert frame_windows(4, 10) == [0, 1, 2, 3]  # fewer frames than asked: every frame
    assert frame_windows(0, 5) == []
    for total, count in [(900, 100), (101, 100), (7, 7)]:
        windows = frame_windows(total, count)
        sizes = np.bincount(windows)
        assert len(sizes) == count and sizes.min() >= 1 and sizes.max() - sizes.min() <= 1
        assert windows == sorted(windows)


def test_sharpness_orders_a_blurred_copy_below_the_sharp_one() -> None:
    sharp = _checker()[..., 0].astype(np.float64)
    blurred = np.asarray(Image.fromarray(_checker()).filter(ImageFilter.GaussianBlur(2)))[..., 0]
    assert sharpness(np.full((16, 16), 7.0)) == 0.0
    assert sharpness(sharp) > 4 * sharpness(blurred) > 0
    assert sharpness(np.zeros((2, 9))) == 0.0  # too small to have an inside


def test_the_sharpest_frame_of_each_stretch_is_kept(tmp_path: Path) -> None:
    sharp = _checker()
    blur = np.asarray(Image.fromarray(sharp).filter(ImageFilter.GaussianBlur(2.5)))
    sharp_at = [1, 5, 6, 11]  # one sharp frame in each stretch of three
    frames = np.stack([sharp if k in sharp_at else blur for k in range(12)])
    frames[:, :4, :4] = np.arange(12, dtype=np.uint8)[:, None, None, None] * 20  # tell the frames apart
    video = write_video(tmp_path / "walk.mp4", frames)
    out = tmp_path / "frames"
    out.mkdir()
    report = extract_frames(video, out, FrameConfig(frames=4))
    assert [k["frame"] for k in report["kept"]] == sharp_at
    assert report["frames_in_video"] == 12 and report["size"] == [96, 64]
    assert sorted(p.name for p in out.glob("*.jpg")) == [f"frame_{k:06d}.jpg" for k in sharp_at]
    assert json.loads((out / "frames.json").read_text())["kept"] == report["kept"]


def test_a_header_without_duration_has_its_frames_counted(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import nerfmeta.data.video as video_mod

    frames = np.stack([_checker()] * 12)
    frames[:, :4, :4] = np.arange(12, dtype=np.uint8)[:, None, None, None] * 20
    video = write_video(tmp_path / "stream.mkv", frames)
    real = video_mod.probe
    monkeypatch.setattr(video_mod, "probe", lambda path: {**real(path), "duration": 0.0})
    out = tmp_path / "frames"
    out.mkdir()
    report = extract_frames(video, out, FrameConfig(frames=4))
    assert len(report["kept"]) == 4 and [k["frame"] // 3 for k in report["kept"]] == [0, 1, 2, 3]


def test_a_rotated_phone_video_gives_upright_frames_within_max_side(tmp_path: Path) -> None:
    stored = np.zeros((6, 64, 96, 3), np.uint8)
    stored[:, :, :48, 0] = 255  # the stored left half red
    plain = write_video(tmp_path / "plain.mp4", stored)
    turned = tmp_path / "portrait.mp4"  # the same stream, shown turned a quarter (as a phone held upright marks it)
    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-v", "error", "-display_rotation", "90", "-i", str(plain),
                    "-c", "copy", str(turned)], check=True)
    out = tmp_path / "frames"
    out.mkdir()
    report = extract_frames(turned, out, FrameConfig(frames=3, max_side=48))
    frame = np.asarray(Image.open(out / report["kept"][0]["file"]))
    assert frame.shape == (48, 32, 3) and report["source_size"] == [64, 96]  # shown 64 wide, 96 tall; scaled to 48
    assert frame[-8:, :, 0].mean() > 200 and frame[:8, :, 0].mean() < 50  # the red half turned to the bottom


def test_poses_and_fit_from_a_video_of_a_walk(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("pycolmap")
    import nerfmeta.data.video as video_mod

    monkeypatch.setenv("NERFMETA_CACHE", str(tmp_path / "cache"))
    poses = sfm_scenes.ring_poses(20, turn=0.4)
    video = write_video(tmp_path / "IMG_0001.MOV", sfm_scenes.render(poses, 0.8 * 256, 192, 256))
    before = video.read_bytes()
    scene = tmp_path / "scene"
    assert main(["poses", str(video), "--out", str(scene), "--video-frames", "10", "--threads", "1"]) == 0
    assert "a video; keeping the sharpest frame of each of 10" in capsys.readouterr().err
    doc = json.loads((scene / "transforms.json").read_text())
    kept = [int(Path(f["file_path"]).stem.split("_")[1]) for f in doc["frames"]]
    assert len(kept) == 10 and [k // 2 for k in kept] == list(range(10))  # one frame of each pair of the 20
    rotation_deg, centre = sfm_scenes.pose_errors(np.array([f["transform_matrix"] for f in doc["frames"]]), poses[kept])
    assert rotation_deg.max() < 1.0 and centre.max() < 0.08  # 1 % of the ground's 8 units

    run = tmp_path / "run"
    args = ["fit", str(video), "--out", str(run), "--init", "scratch", "--iters", "2", "--eval-views", "1", "--renders",
            "0", "--downscale", "4"]
    assert main(args) == 0
    fitted = Path(json.loads((run / "config.json").read_text())["scene"])
    assert fitted.parent == tmp_path / "cache" / "poses"
    assert video.read_bytes() == before  # the video was only read

    def no_second_extraction(*a, **k):
        raise AssertionError("the frames were extracted again")

    monkeypatch.setattr(video_mod, "extract_frames", no_second_extraction)
    assert main(args + ["--overwrite"]) == 0
    assert "frames from the cache" in capsys.readouterr().err


def test_a_file_ffmpeg_cannot_read_is_one_line_and_nothing_is_cached(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("pycolmap")
    monkeypatch.setenv("NERFMETA_CACHE", str(tmp_path / "cache"))
    bad = tmp_path / "clip.mp4"
    bad.write_bytes(b"\x00\x00\x00\x20ftypisom" + b"\x00" * 200)
    assert main(["poses", str(bad), "--out", str(tmp_path / "scene")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("nerfmeta poses: error: ") and "clip.mp4: not a video ffmpeg can read" in err[-1]
    assert not (tmp_path / "scene").exists()
    assert not any((tmp_path / "cache" / "frames").glob("*/frame_*.jpg"))
    assert main(["poses", str(bad), "--out", str(tmp_path / "scene"), "--video-frames", "2"]) == 2
    assert "--video-frames 2: must be at least 3" in capsys.readouterr().err


def test_classify_and_inspect_take_a_video(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("NERFMETA_CACHE", str(tmp_path / "cache"))
    video = write_video(tmp_path / "walk.mp4", np.stack([_checker()] * 8))
    assert main(["classify", str(video), "--zoo", str(Path(__file__).resolve().parents[1] / "model_zoo")]) == 0
    out = capsys.readouterr()
    assert json.loads(out.out)["views"] == 8 and "8 of its 8 frames kept" in out.err
    assert main(["inspect", str(video)]) == 2
    assert f"'nerfmeta poses {video} --out SCENE' makes a scene of its frames" in capsys.readouterr().err
