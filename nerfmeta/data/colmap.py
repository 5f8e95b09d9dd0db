"""COLMAP projects: ``images/`` beside a sparse model, as COLMAP writes it and as 3D Gaussian Splatting's and
Mip-NeRF 360's data come::

    SCENE/images/NAME                the photos the model was made from (any size: intrinsics are scaled to them)
    SCENE/sparse/0/cameras.bin ...   cameras, images, points3D (.bin or .txt); or directly in SCENE/sparse/

The model is read with pycolmap (the ``poses`` extra) and turned into the nerfstudio document
:func:`nerfmeta.data.sfm.scene_document` writes for ``nerfmeta poses`` (OpenGL camera-to-world, the world turned as
nerfstudio's ``colmap_to_json`` turns it, near/far from the sparse points each camera sees), which
:func:`nerfmeta.data.nerfstudio.load_document` reads: so a capture posed by COLMAP elsewhere is fitted as it
is, not posed again. Only the model's registered images are views, in name order. Lens distortion (``SIMPLE_RADIAL``,
``RADIAL``, ``OPENCV``) is removed on load as for nerfstudio scenes (:mod:`nerfmeta.data.distortion`); COLMAP's
``image_undistorter`` and 3DGS's ``convert.py`` write undistorted images with a PINHOLE model, which need nothing. A
scene with ``poses_bounds.npy`` too (Mip-NeRF 360's) is read as LLFF.

Splits: every 8th view (0, 8, 16, ...) is held out as the test split.
"""

from __future__ import annotations

from pathlib import Path

from nerfmeta.data.common import LoadOptions, find_frame_image
from nerfmeta.data.images import image_shape
from nerfmeta.data.scene import Scene
from nerfmeta.errors import SceneError, message_line

NAME = "colmap"
EXPECTS = "images/ beside COLMAP's sparse model in sparse/0/ or sparse/ (cameras, images, points3D; .bin or .txt)"
MODEL_FOLDERS = ("sparse/0", "sparse")
MODEL_FILES = (("cameras.bin", "images.bin"), ("cameras.txt", "images.txt"))
SIZE_TOLERANCE = 0.01
"""Images resized from the model's size must keep its aspect ratio to this fraction."""


MIN_RECORD_BYTES = {"cameras.bin": 24, "images.bin": 73, "points3D.bin": 51}
"""The fewest bytes one record of each binary model file takes (ids, pose, sizes, one name byte...): a count in a
file's first 8 bytes that these do not fit is a damaged file (pycolmap would read on for minutes)."""


def check_binary_model(folder: Path) -> None:
    """Raise :class:`SceneError` naming a binary model file of ``folder`` too short for the record count it starts
    with (a damaged or truncated file)."""
    for name, record in MIN_RECORD_BYTES.items():
        file = folder / name
        if not file.is_file():
            continue
        size = file.stat().st_size
        with open(file, "rb") as f:
            head = f.read(8)
        count = int.from_bytes(head, "little") if len(head) == 8 else None
        if count is None or 8 + count * record > size:
            told = "no record count" if count is None else f"{count} records"
            raise SceneError(f"{file}: not a readable COLMAP model file ({told} in {size} bytes: damaged or truncated)")


def model_folder(path: Path) -> Path | None:
    """The folder of ``path``'s sparse model (:data:`MODEL_FOLDERS`), or None."""
    for name in MODEL_FOLDERS:
        folder = path / name
        if any(all((folder / f).is_file() for f in files) for files in MODEL_FILES):
            return folder
    return None


def detect(path: Path) -> bool:
    """True for a folder with a COLMAP sparse model (and no other format's pose file: those are tried first)."""
    return path.is_dir() and model_folder(path) is not None


def rescaled_to_images(doc: dict, height: int, width: int, *, where: str) -> dict:
    """``doc`` (a ``transforms.json`` document) with its intrinsics scaled from the model's image size to the images'
    ``height`` x ``width`` (a dataset's images are often a resized copy of what COLMAP saw).

    Raises:
        SceneError: the images' aspect ratio differs from the model's by more than :data:`SIZE_TOLERANCE`.
    """
    sx, sy = width / doc["w"], height / doc["h"]
    if abs(sx / sy - 1) > SIZE_TOLERANCE:
        raise SceneError(f"{where}: the model's images are {doc['w']}x{doc['h']} but the images are {width}x{height} "
                         "(another aspect ratio: not a resized copy)")
    if (sx, sy) == (1.0, 1.0):
        return doc

    def scaled(keys: dict) -> dict:
        out = dict(keys)
        for key, factor in (("fl_x", sx), ("cx", sx), ("fl_y", sy), ("cy", sy)):
            if key in out:
                out[key] = out[key] * factor
        if "w" in out:
            out["w"], out["h"] = round(out["w"] * sx), round(out["h"] * sy)
        return out

    return {**scaled(doc), "frames": [scaled(f) for f in doc["frames"]]}


def load(path: Path, options: LoadOptions) -> Scene:
    """Read a COLMAP project (see the module docstring)."""
    from nerfmeta.data import nerfstudio
    from nerfmeta.data.sfm import posed_images, scene_document

    folder = model_folder(path)
    if folder is None:
        raise SceneError(f"{path}: no COLMAP model in {' or '.join(MODEL_FOLDERS)}")
    try:
        import pycolmap
    except ImportError:
        raise SceneError(f"{folder}: reading a COLMAP model needs pycolmap: pip install 'nerfmeta[poses]'") from None
    check_binary_model(folder)
    try:
        model = pycolmap.Reconstruction(str(folder))
    except Exception as err:  # pycolmap raises its own types for a damaged model
        raise SceneError(f"{folder}: not a readable COLMAP model ({message_line(err, limit=200)})") from err
    names = sorted(posed_images(model))
    if not names:
        raise SceneError(f"{folder}: the COLMAP model poses no image")
    doc, _ = scene_document(model, names)
    height, width = image_shape(find_frame_image(path, doc["frames"][0]["file_path"], where=f"{folder}: {names[0]}"))
    doc = rescaled_to_images(doc, height, width, where=str(folder))
    return nerfstudio.load_document(path, doc, options, file=folder, scene_format=NAME,
                                    near_far_source="from the COLMAP model's sparse points (0.1-99.9 % of their "
                                                    "depths, widened by 10 %)")
