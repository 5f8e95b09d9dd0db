"""Frames from a phone video, for structure from motion: ``VIDEO`` -> a folder of ``frame_NNNNNN.jpg``.

A capture is often a video (a walk round an object) rather than photos. The frames kept are
spread evenly over its time: the video is cut into ``frames`` windows of equal length and the
sharpest frame of each is kept (variance of the Laplacian of its gray copy, :func:`sharpness`:
a walking phone blurs some frames, and a blurred frame gives SfM few features and a fit a soft
view). Frames are named by their index in the video, so file-name order is time order, which is
what the sequential matcher and the walk checks of :mod:`nerfmeta.data.sfm` expect.

Decoding is ffmpeg's (through ``imageio-ffmpeg``, which ships its own binary; the ``video``
extra): one pass, frames turned upright as the video's rotation says (a portrait phone video is
stored sideways), scaled by ffmpeg to at most ``max_side`` pixels a side, one window's best frame
held in memory at a time.

``nerfmeta fit VIDEO`` and ``nerfmeta poses VIDEO`` extract into the cache
(:func:`cached_frames`, keyed by the video's contents and the options), written aside and
swapped in complete; the video is only read.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from PIL import Image

from nerfmeta.config import bounded
from nerfmeta.data.images import MAX_SIDE
from nerfmeta.errors import ConfigError, SceneError, message_line
from nerfmeta.io import write_json
from nerfmeta.runfolder import run_folder

log = logging.getLogger(__name__)

VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm")
"""Files read as videos (a phone's MP4/MOV, and the common containers ffmpeg reads)."""
REPORT = "frames.json"
MIN_FRAMES = 3
"""Fewest frames a video must give (as structure from motion needs photos)."""
SHARPNESS_SIDE = 320
"""Longest side of the gray copy a frame's sharpness is measured on (the measure is relative, within a window)."""

Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class FrameConfig:
    """Which frames of a video are kept."""

    frames: int = bounded(100, low=MIN_FRAMES)
    """Frames kept: the sharpest of each of this many equal stretches of the video (all frames when it has fewer).
    About 70 frames of a walk one and a half times round an object made beer's poses; every second frame of those
    (36) folded the walk, so keep enough that neighbours overlap well."""
    max_side: int = bounded(MAX_SIDE, low=16)
    """Longest side of the frames written (ffmpeg scales larger videos down, area filter)."""


def is_video(path: str | os.PathLike) -> bool:
    """True for a file whose suffix is a video container's (:data:`VIDEO_SUFFIXES`)."""
    path = Path(path)
    return path.suffix.lower() in VIDEO_SUFFIXES and path.is_file()


def frame_windows(total: int, count: int) -> list[int]:
    """The window of each of ``total`` frames when they are cut into ``count`` stretches of equal length:
    ``window[i]`` in ``0 .. min(count, total) - 1``, non-decreasing, each window non-empty."""
    if total <= 0:
        return []
    count = min(count, total)
    return [i * count // total for i in range(total)]


def sharpness(gray: np.ndarray) -> float:
    """Variance of the 4-neighbour Laplacian over the inside of a 2-D image (higher: sharper)."""
    g = np.asarray(gray, dtype=np.float64)
    if g.ndim != 2 or min(g.shape) < 3:
        return 0.0
    lap = g[:-2, 1:-1] + g[2:, 1:-1] + g[1:-1, :-2] + g[1:-1, 2:] - 4.0 * g[1:-1, 1:-1]
    return float(lap.var())


def _gray_copy(frame: np.ndarray) -> np.ndarray:
    """A small gray copy of an RGB frame (strided, then averaged), for :func:`sharpness`."""
    step = max(1, math.ceil(max(frame.shape[:2]) / SHARPNESS_SIDE))
    return frame[::step, ::step].astype(np.float32).mean(axis=2)


def scaled_size(width: int, height: int, max_side: int) -> tuple[int, int]:
    """``(width, height)`` with the longest side at most ``max_side``, both even (ffmpeg's scaler wants no odd
    chroma size); unchanged when already within."""
    scale = min(1.0, max_side / max(width, height))
    if scale == 1.0:
        return width, height
    return max(2, 2 * round(width * scale / 2)), max(2, 2 * round(height * scale / 2))


def _ffmpeg():
    try:
        import imageio_ffmpeg
    except ImportError:
        raise ConfigError("reading a video needs imageio-ffmpeg: pip install 'nerfmeta[video]'") from None
    # it warns that a rotated video's frames differ in size from the stored ones: that is the rotation, applied
    logging.getLogger("imageio_ffmpeg").setLevel(logging.ERROR)
    return imageio_ffmpeg


def probe(video: Path) -> dict:
    """``{"size": (w, h) as shown (rotation applied), "fps", "duration"}`` of ``video``.

    Raises:
        SceneError: ffmpeg cannot read it as a video.
    """
    ffmpeg = _ffmpeg()
    try:
        reader = ffmpeg.read_frames(str(video))
        meta = next(reader)
        reader.close()
    except (RuntimeError, OSError, StopIteration, ValueError, IndexError, AttributeError) as err:
        raise SceneError(f"{video}: not a video ffmpeg can read ({message_line(err, last=True, limit=200)})") from err
    size = meta.get("size")
    if not size or min(size) < 1:
        raise SceneError(f"{video}: has no video stream")
    return {"size": tuple(size), "fps": float(meta.get("fps") or 0.0), "duration": float(meta.get("duration") or 0.0)}


def extract_frames(video: str | os.PathLike, out: Path, config: FrameConfig = FrameConfig(), *,
                   progress: Progress | None = None) -> dict:
    """Write the sharpest frame of each of ``config.frames`` equal stretches of ``video`` into the existing folder
    ``out`` as ``frame_NNNNNN.jpg`` (index in the video); returns the report (also the content of ``frames.json``).

    The stretches are cut on the frame count the header gives (duration x frame rate; counted by ffmpeg when the
    header has neither); frames past it join the last stretch, and a video that ends early leaves its last
    stretches empty.

    Raises:
        SceneError: unreadable, or fewer than :data:`MIN_FRAMES` frames.
    """
    video = Path(video)
    progress = progress or (lambda phase, done, total: None)
    meta = probe(video)
    width, height = meta["size"]
    out_w, out_h = scaled_size(width, height, config.max_side)
    ffmpeg = _ffmpeg()
    expected = round(meta["duration"] * meta["fps"])
    if expected < MIN_FRAMES:  # a header without duration or rate (some streams): count the frames, one more pass
        try:
            expected = ffmpeg.count_frames_and_secs(str(video))[0]
        except (RuntimeError, OSError, ValueError) as err:
            raise SceneError(f"{video}: cannot count its frames ({message_line(err, last=True, limit=200)})") from err
    expected = max(1, expected)
    windows = frame_windows(expected, config.frames)
    n_windows = min(config.frames, expected)  # every window holds a frame (frame_windows)
    params = ["-vf", f"scale={out_w}:{out_h}:flags=area"] if (out_w, out_h) != (width, height) else None
    t0 = time.perf_counter()
    kept: list[dict] = []
    best: tuple[float, int, np.ndarray] | None = None
    window = -1
    total = 0

    def flush() -> None:
        if best is not None:
            score, index, frame = best
            name = f"frame_{index:06d}.jpg"
            Image.fromarray(frame).save(out / name, quality=95)
            kept.append({"file": name, "frame": index, "sharpness": round(score, 3)})

    reader = ffmpeg.read_frames(str(video), output_params=params)
    try:
        next(reader)
        for index, raw in enumerate(reader):
            frame = np.frombuffer(raw, np.uint8)
            if frame.size != out_w * out_h * 3:
                raise SceneError(f"{video}: frame {index} is {frame.size} bytes, not {out_w}x{out_h} RGB")
            frame = frame.reshape(out_h, out_w, 3)
            this = windows[min(index, expected - 1)]
            if this != window:
                flush()
                best, window = None, this
                progress("frames", len(kept), n_windows)
            score = sharpness(_gray_copy(frame))
            if best is None or score > best[0]:
                best = (score, index, frame.copy())
            total = index + 1
        flush()
    except (RuntimeError, OSError) as err:
        raise SceneError(f"{video}: decoding failed after {total} frames ({message_line(err, last=True, limit=200)})") from err
    finally:
        reader.close()
    progress("frames", len(kept), len(kept))
    if len(kept) < MIN_FRAMES:
        raise SceneError(f"{video}: {total} frame(s); structure from motion needs at least {MIN_FRAMES} views of the "
                         "scene from different places")
    report = {"video": str(video), "frames_in_video": total, "size": [out_w, out_h], "source_size": [width, height],
              "fps": meta["fps"], "duration": meta["duration"], "kept": kept,
              "seconds": round(time.perf_counter() - t0, 3), "config": asdict(config)}
    write_json(out / REPORT, report)
    return report


def video_hash(video: Path, config: FrameConfig) -> str:
    """A hex key of the video's contents and ``config`` (what cached frames were made from)."""
    digest = hashlib.sha256(json.dumps(asdict(config), sort_keys=True).encode())
    with open(video, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()[:32]


def frames_root() -> Path:
    """Where extracted frames are cached: beside the SfM cache (``$NERFMETA_CACHE/frames``, else
    ``$XDG_CACHE_HOME/nerfmeta/frames``)."""
    from nerfmeta.data.sfm import cache_root

    return cache_root().parent / "frames"


def cached_frames(video: str | os.PathLike, config: FrameConfig = FrameConfig(), *,
                  progress: Progress | None = None) -> tuple[Path, bool]:
    """``(frames folder, was cached)``: the frames of ``video`` from the cache, extracted there when missing."""
    video = Path(video)
    folder = frames_root() / video_hash(video, config)
    if (folder / REPORT).is_file():
        return folder, True
    folder.parent.mkdir(parents=True, exist_ok=True)
    with run_folder(folder, "frames", overwrite=True, aside=True, protect=(video,)) as run:
        extract_frames(video, run.dir, config, progress=progress)
    return folder, False
