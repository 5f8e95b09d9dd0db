"""Writing rendered frames as an MP4 (``imageio-ffmpeg``, imageio's ffmpeg plugin, with its own ffmpeg binary) or a GIF (Pillow).

Frames arrive in chunks (:class:`VideoWriter.append`), so a long video never holds every frame
as floats. The file is written under a temporary name beside the target and renamed when
complete (a failure or a kill never leaves half a video under the user's name). Each file carries
:data:`SIGNATURE` in its metadata (MP4 comment, GIF comment), which is how :func:`made_by_nerfmeta`
tells a video nerfmeta rendered (that ``--overwrite`` may replace) from a user's file (never replaced).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

SIGNATURE = "rendered by nerfmeta render"
"""Written into every video's metadata."""
FORMATS = (".mp4", ".gif")
SCAN_BYTES = 1 << 16
"""How much of each end of a file :func:`made_by_nerfmeta` reads (MP4 keeps its metadata at one end)."""


def video_format(path: str | os.PathLike) -> str:
    """``.mp4`` or ``.gif`` from ``path``'s suffix (any case); ValueError for anything else."""
    suffix = Path(path).suffix.lower()
    if suffix not in FORMATS:
        raise ValueError(f"{path}: the video must end in .mp4 or .gif")
    return suffix


def made_by_nerfmeta(path: str | os.PathLike) -> bool:
    """True when the file at ``path`` holds :data:`SIGNATURE` near its start or end (a video this module wrote)."""
    try:
        with open(path, "rb") as f:
            head = f.read(SCAN_BYTES)
            f.seek(0, os.SEEK_END)
            size = f.tell()
            f.seek(max(0, size - SCAN_BYTES))
            tail = f.read()
    except OSError:
        return False
    marker = SIGNATURE.encode()
    return marker in head or marker in tail


def even_size(height: int, width: int) -> tuple[int, int]:
    """The largest even ``(height, width)`` not above the given one (H.264 in yuv420p needs even sides)."""
    return max(2, height - height % 2), max(2, width - width % 2)


def to_uint8(frames: np.ndarray) -> np.ndarray:
    """(n, H, W, 3) float in [0, 1] -> uint8, rounded."""
    return (np.clip(frames, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


class VideoWriter:
    """Append (n, H, W, 3) frames, then :meth:`close` to rename the finished file into place.

    Used as a context manager: leaving the block by an exception removes the temporary file and
    leaves ``path`` untouched.
    """

    def __init__(self, path: str | os.PathLike, fps: float):
        self.path = Path(path)
        self.format = video_format(self.path)
        self.fps = float(fps)
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=self.path.parent)
        os.close(fd)
        self.tmp = Path(tmp)
        self._gif_frames: list = []
        self._mp4 = None
        self.frames = 0

    def append(self, frames: np.ndarray) -> None:
        """Add frames: (n, H, W, 3) uint8 or float in [0, 1], all of one size."""
        frames = to_uint8(frames) if frames.dtype != np.uint8 else frames
        if self.format == ".gif":
            from PIL import Image

            self._gif_frames.extend(Image.fromarray(f).convert("P", palette=Image.Palette.ADAPTIVE) for f in frames)
        else:
            h, w = even_size(*frames.shape[1:3])
            if self._mp4 is None:
                import imageio_ffmpeg

                # the temporary name has no .mp4 suffix: the container is named (-f mp4)
                self._mp4 = imageio_ffmpeg.write_frames(str(self.tmp), (w, h), fps=self.fps, codec="libx264", quality=8,
                                                        macro_block_size=2, pix_fmt_out="yuv420p",
                                                        output_params=["-metadata", f"comment={SIGNATURE}", "-f", "mp4"])
                self._mp4.send(None)
            for frame in frames:
                self._mp4.send(np.ascontiguousarray(frame[:h, :w]))
        self.frames += len(frames)

    def close(self) -> Path:
        """Finish the file and rename it onto ``path``; returns ``path``."""
        if self.frames == 0:
            raise ValueError("no frames to write")
        if self.format == ".gif":
            first, *rest = self._gif_frames
            first.save(self.tmp, format="GIF", save_all=True, append_images=rest, duration=round(1000 / self.fps),
                       loop=0, comment=SIGNATURE.encode())
        else:
            self._mp4.close()
            self._mp4 = None
        os.chmod(self.tmp, 0o644)
        os.replace(self.tmp, self.path)
        return self.path

    def abort(self) -> None:
        """Drop the unfinished file."""
        if self._mp4 is not None:
            try:
                self._mp4.close()
            except Exception:  # the writer is being thrown away after another error: that one is reported
                pass
            self._mp4 = None
        self.tmp.unlink(missing_ok=True)

    def __enter__(self) -> "VideoWriter":
        return self

    def __exit__(self, kind, value, trace) -> None:
        if kind is not None:
            self.abort()
