"""Seeded fuzzing of scene files: mutate valid scenes and check that ``nerfmeta inspect`` either loads
them or refuses them in one line (exit 2), never a traceback or extra lines on stderr.

Used by ``tests/test_hostile_inputs.py`` (a few cases per kind) and ``scripts/fuzz_inputs.py`` (as
many as asked). Kinds: ``blender`` and ``nerfstudio`` (JSON values replaced by extreme numbers,
wrong types, hostile paths), ``llff`` (entries of ``poses_bounds.npy``), ``npz`` (poses, focal,
pixel values and types) and ``image`` (bytes of PNG/JPEG files in every pixel mode flipped or cut).
"""

from __future__ import annotations

import contextlib
import io
import json
import random
import shutil
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
from PIL import Image

from nerfmeta.cli import main
from nerfmeta.data.synthetic import tiny_cameras, write_tiny_scene

JSON_VALUES: tuple[Any, ...] = (0, -1, 1e-300, 1e300, -1e300, float("nan"), float("inf"), "abc", None, [], {}, [1, 2], True,
                                2**70, 1e-320, -0.0, "OPENCV_FISHEYE", "../x", "/etc/passwd")
NUMBERS = (0.0, -1.0, 1e-300, 1e300, -1e300, float("nan"), float("inf"), 1e-320, 2.0**70, 1e6, -0.0)
KINDS = ("blender", "nerfstudio", "llff", "npz", "image")


@dataclass(frozen=True)
class Outcome:
    """One fuzzed scene: its kind and number, the exit code and the stderr lines."""

    kind: str
    case: int
    code: int | str
    stderr: tuple[str, ...]

    @property
    def broken(self) -> bool:
        """Not a load (0) and not a one-line refusal (2): a traceback, an exception or extra stderr lines."""
        if self.code == 0:
            return any("Traceback" in line for line in self.stderr)
        return self.code != 2 or len(self.stderr) != 1 or not self.stderr[0].startswith("nerfmeta inspect: error: ")


def _json_paths(doc: Any, prefix: tuple = ()) -> Iterator[tuple]:
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield prefix + (k,)
            yield from _json_paths(v, prefix + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield prefix + (i,)
            yield from _json_paths(v, prefix + (i,))


def _mutate_json(doc: Any, rng: random.Random) -> None:
    paths = list(_json_paths(doc))
    for _ in range(rng.randint(1, 3)):
        node, path = doc, rng.choice(paths)
        try:
            for key in path[:-1]:
                node = node[key]
            node[path[-1]] = rng.choice(JSON_VALUES)
        except (KeyError, IndexError, TypeError):  # an earlier mutation replaced a parent
            pass


def _blender(folder: Path, rng: random.Random) -> Path:
    scene = write_tiny_scene(folder, n_train=3, n_test=1, size=8)
    file = scene / rng.choice(["transforms_train.json", "transforms_test.json"])
    doc = json.loads(file.read_text())
    _mutate_json(doc, rng)
    file.write_text(json.dumps(doc))
    return scene


def _nerfstudio(folder: Path, rng: random.Random) -> Path:
    scene = write_tiny_scene(folder, n_train=4, n_test=0, size=8)
    doc = json.loads((scene / "transforms_train.json").read_text())
    (scene / "transforms_train.json").unlink()
    doc.update(fl_x=9.0, fl_y=9.0, cx=4.0, cy=4.0, w=8, h=8, k1=0.0, camera_model="OPENCV")
    doc["frames"][1].update(fl_x=8.5, cx=3.9)
    _mutate_json(doc, rng)
    (scene / "transforms.json").write_text(json.dumps(doc))
    return scene


def llff_rows(folder: Path, n: int = 3, *, height: int = 4, width: int = 6) -> np.ndarray:
    """Write ``n`` small images into ``folder/images`` and return a matching (n, 17) ``poses_bounds``
    (identity-rotation cameras 0.1 apart, focal 5, depths 1 to 5), not yet saved."""
    (folder / "images").mkdir(parents=True)
    rows = np.zeros((n, 17))
    for k in range(n):
        mat = np.zeros((3, 5))
        mat[:, :3] = [[0, 1, 0], [-1, 0, 0], [0, 0, 1]]  # LLFF [down, right, back] of an identity camera
        mat[:, 3] = [k * 0.1, 0.0, 0.0]
        mat[:, 4] = [height, width, 5.0]
        rows[k, :15] = mat.reshape(-1)
        rows[k, 15:] = [1.0, 5.0]
        Image.new("RGB", (width, height), (k * 50, 20, 30)).save(folder / "images" / f"{k}.png")
    return rows


def _llff(folder: Path, rng: random.Random) -> Path:
    rows = llff_rows(folder)
    for _ in range(rng.randint(1, 3)):
        rows[rng.randrange(3), rng.randrange(17)] = rng.choice(NUMBERS)
    np.save(folder / "poses_bounds.npy", rows)
    return folder


def _npz(folder: Path, rng: random.Random) -> Path:
    folder.mkdir(parents=True)
    poses, intrinsics = tiny_cameras(4, 0.5, 8)
    poses_np, focal = poses.numpy().copy(), np.float64(intrinsics[0])
    dtype = rng.choice([np.uint8, np.float32, np.float64, np.int64])
    images = np.random.default_rng(rng.randrange(1 << 30)).integers(0, 255, (4, 8, 8, 3)).astype(dtype)
    with np.errstate(all="ignore"):
        for _ in range(rng.randint(1, 3)):
            r = rng.random()
            if r < 0.6:
                poses_np[rng.randrange(4), rng.randrange(4), rng.randrange(4)] = rng.choice(NUMBERS)
            elif r < 0.8:
                focal = np.float64(rng.choice(NUMBERS))
            else:
                images = images.astype(np.float64) * rng.choice(NUMBERS)
    np.savez(folder / "scene.npz", images=images, poses=poses_np, focal=focal)
    return folder / "scene.npz"


def _image_bytes(mode: str, fmt: str) -> bytes:
    pixels = np.random.default_rng(0).integers(0, 255, (8, 8, 3), dtype=np.uint8)  # the size of the other views
    buf, exif = io.BytesIO(), Image.Exif()
    exif[0x0112] = 6
    Image.fromarray(pixels).convert(mode).save(buf, fmt, exif=exif)
    return buf.getvalue()


def _image(folder: Path, rng: random.Random) -> Path:
    mode, fmt = rng.choice([("RGB", "PNG"), ("RGBA", "PNG"), ("P", "PNG"), ("LA", "PNG"), ("I;16", "PNG"), ("1", "PNG"),
                            ("L", "JPEG"), ("RGB", "JPEG"), ("CMYK", "JPEG")])
    data = bytearray(_image_bytes(mode, fmt))
    for _ in range(rng.randint(1, 6)):
        data[rng.randrange(len(data))] = rng.randrange(256)
    if rng.random() < 0.2:
        data = data[: rng.randrange(len(data))]
    scene = write_tiny_scene(folder, n_train=2, n_test=1, size=8)
    (scene / "train" / "r_0.png").write_bytes(bytes(data))  # the loader reads by content, not by name
    return scene


BUILDERS: dict[str, Callable[[Path, random.Random], Path]] = {
    "blender": _blender, "nerfstudio": _nerfstudio, "llff": _llff, "npz": _npz, "image": _image,
}


def fuzz(kind: str, cases: int, workdir: Path, *, seed: int = 0) -> list[Outcome]:
    """Build ``cases`` mutated scenes of ``kind`` (seeded) and run ``nerfmeta inspect`` on each."""
    rng = random.Random(f"{kind}-{seed}")
    outcomes = []
    for case in range(cases):
        folder = workdir / f"{kind}_{case}"
        scene = BUILDERS[kind](folder, rng)
        err = io.StringIO()
        with warnings.catch_warnings():
            warnings.simplefilter("always")  # printed on stderr as a user would see them
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                try:
                    code: int | str = main(["inspect", str(scene)])
                except BaseException as exc:  # noqa: BLE001 - what the fuzzer is looking for
                    code = f"exception {exc!r}"[:200]
        outcomes.append(Outcome(kind, case, code, tuple(err.getvalue().strip().splitlines())))
        shutil.rmtree(folder, ignore_errors=True)
    return outcomes
