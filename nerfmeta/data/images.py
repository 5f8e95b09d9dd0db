"""Reading, compositing and downscaling images.

Images are handled as float32 tensors in [0, 1]: ``(H, W, 3)`` RGB or ``(H, W, 4)`` RGBA
(straight, not premultiplied, alpha). Grayscale is expanded to RGB. 8-bit values are divided by
255 and 16-bit values by 65535.

Files are opened with Pillow, which reads the header (size, mode, EXIF) without decoding the
pixels. HEIC/HEIF photos (an iPhone's default format) are read through pillow-heif's Pillow
plugin, which applies the photo's rotation as it decodes and resets its EXIF orientation to 1.
Every pixel mode is converted explicitly (:func:`pixel_array`): 1-bit, grayscale (8 and 16
bit), grayscale + alpha, palette (with its transparency), RGB, RGBA, CMYK and YCbCr; a
transparency key (PNG ``tRNS``) becomes an alpha channel; EXIF orientation is applied, so sizes
and pixels are those a viewer shows (a pose tool that ignored the tag saw the other size; the
parsers' size checks, LLFF's aspect and nerfstudio's ``w``/``h``, then refuse the scene rather than
fit it on its side). Other modes (32-bit integer or float images) are refused.
Known limit: Pillow reads 16-bit *colour* PNGs as 8-bit (it keeps the high byte), so those come
back correctly scaled but with 8-bit precision; a warning is logged. 16-bit grayscale PNGs keep
their full precision.
"""

from __future__ import annotations

import functools
import logging
import os
import warnings
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image, ImageOps

from nerfmeta.errors import SceneError, message_line

log = logging.getLogger(__name__)

DEFAULT_MAX_PIXELS = 64_000_000
MAX_SIDE = 1600
"""Default longest image side nerfmeta works at: the photos ``nerfmeta poses`` prepares, and the images a fit reads
(``RunConfig.max_side``); nerfstudio's automatic downscale target. A grid of at most 160 voxels a side cannot use
more, and a full-size evaluation of a 4032 x 3024 capture would render 12 M rays a view."""
HEIF_SUFFIXES = (".heic", ".heif")
"""Phone photos in HEIF (an iPhone's default since iOS 11): read with pillow-heif (libheif)."""
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg") + HEIF_SUFFIXES
OTHER_IMAGE_SUFFIXES = (".webp", ".avif", ".tif", ".tiff", ".bmp", ".gif", ".jxl", ".dng", ".cr2", ".cr3", ".nef",
                        ".arw", ".raf", ".orf", ".rw2")
"""Image files nerfmeta does not read, named in the error for a folder that holds only those (convert them first)."""
EXIF_ORIENTATION = 0x0112
TRANSPOSING_ORIENTATIONS = (5, 6, 7, 8)
"""EXIF orientations that turn the picture by 90 degrees (the shown size is the stored one transposed)."""
DIRECT_MODES = ("L", "LA", "RGB", "RGBA", "I;16", "I;16L", "I;16B", "I;16N")
"""Pillow modes whose pixels are used as stored (8-bit, or 16-bit grayscale)."""
CONVERTED_MODES = {"1": "L", "P": "RGB", "PA": "RGBA", "La": "LA", "RGBa": "RGBA", "RGBX": "RGB", "CMYK": "RGB",
                   "YCbCr": "RGB", "LAB": "RGB", "HSV": "RGB"}
"""Pillow modes converted to an 8-bit mode before use (a palette becomes its colours, CMYK its RGB)."""


@contextmanager
def _pillow_warnings_logged(path: Path) -> Iterator[None]:
    """Pillow's warnings about a damaged file (corrupt EXIF, ...) logged at INFO instead of printed;
    its decompression-bomb warning dropped (nerfmeta applies its own pixel limit before decoding)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        yield
    for w in caught:
        log.info("%s: %s", path, w.message)


@functools.cache
def _register_heif() -> bool:
    """Register pillow-heif's HEIC/HEIF opener with Pillow (once); False when pillow-heif is not installed."""
    try:
        import pillow_heif
    except ImportError:
        return False
    pillow_heif.register_heif_opener()
    return True


@contextmanager
def _open(path: Path) -> Iterator[Image.Image]:
    """The image at ``path`` opened lazily (header only); one-line SceneError for anything unreadable."""
    if not path.is_file():
        raise SceneError(f"{path}: image file not found")
    if path.suffix.lower() in HEIF_SUFFIXES and not _register_heif():
        raise SceneError(f"{path}: a HEIC/HEIF photo, and reading one needs pillow-heif (pip install pillow-heif), "
                         "which is not installed; or convert the photos to JPEG")
    try:
        with _pillow_warnings_logged(path):
            image = Image.open(path)
    except Image.DecompressionBombError as err:
        raise SceneError(f"{path}: image is too large to open safely ({message_line(err)})") from err
    except Exception as err:  # Pillow raises many types for a bad file
        raise SceneError(f"{path}: not a readable PNG, JPEG or HEIC image ({message_line(err)})") from err
    with image:
        yield image


def _exif(image: Image.Image) -> Image.Exif | None:
    """The EXIF block of an opened image; None without one, or with a damaged one.

    A PNG's EXIF is read only from an eXIf chunk before the pixel data (where the PNG specification
    places it, and where Pillow writes it): Pillow's ``getexif`` on a PNG without one decodes the
    whole image to look behind the pixels, which made reading a scene decode every PNG twice.
    """
    if image.format == "PNG" and "exif" not in image.info:
        return None
    with _pillow_warnings_logged(Path(getattr(image, "filename", "") or "image")):
        try:
            exif = image.getexif()
        except Exception:  # a damaged EXIF block: as if there were none
            return None
    return exif if len(exif) else None


def _orientation(image: Image.Image) -> int:
    """The EXIF orientation tag (1 = as stored) of an opened image; 1 without EXIF or for a damaged block."""
    exif = _exif(image)
    value = 1 if exif is None else exif.get(EXIF_ORIENTATION, 1)
    return value if isinstance(value, int) and 1 <= value <= 8 else 1


def read_exif(path: str | os.PathLike) -> Image.Exif | None:
    """The EXIF block of the image file ``path`` (header only); None without one or with a damaged one.

    Raises:
        SceneError: the file is missing or is not an image Pillow can open.
    """
    with _open(Path(path)) as image:
        return _exif(image)


def image_shape(path: str | os.PathLike) -> tuple[int, int]:
    """``(height, width)`` of an image file as shown (EXIF orientation applied), from its header
    without decoding the pixels.

    Raises:
        SceneError: the file is missing or is not an image Pillow can open.
    """
    path = Path(path)
    with _open(path) as image:
        width, height = image.size
        if _orientation(image) in TRANSPOSING_ORIENTATIONS:
            width, height = height, width
    if min(height, width) < 1:
        raise SceneError(f"{path}: not a 2-D image (size {width}x{height})")
    return int(height), int(width)


def image_has_alpha(path: str | os.PathLike) -> bool:
    """Whether an image file carries an alpha channel (or a transparent palette entry), from its header.

    Raises:
        SceneError: the file is missing or is not an image Pillow can open.
    """
    with _open(Path(path)) as image:
        return image.mode in ("RGBA", "RGBa", "LA", "La", "PA") or "transparency" in image.info


def check_pixel_limit(path: str | os.PathLike, height: int, width: int, max_pixels: int) -> None:
    """Raise :class:`SceneError` naming ``path`` when ``height * width`` exceeds ``max_pixels``."""
    if height * width > max_pixels:
        raise SceneError(
            f"{path}: image is {width}x{height} = {height * width / 1e6:.1f} megapixels, over the "
            f"limit of {max_pixels / 1e6:g} megapixels (resize the file or raise max_pixels)"
        )


def read_image(path: str | os.PathLike, *, max_pixels: int = DEFAULT_MAX_PIXELS) -> torch.Tensor:
    """Read one image file as float32 in [0, 1].

    The size is checked against ``max_pixels`` from the file header before the pixels are
    decoded.

    Args:
        path: a PNG (8 or 16 bit), JPEG or HEIC/HEIF file; grayscale, gray+alpha, RGB or RGBA.
        max_pixels: largest accepted ``height * width``.

    Returns:
        (H, W, 3) RGB or (H, W, 4) RGBA float32 tensor (straight alpha).

    Raises:
        SceneError: the file is missing, unreadable, too large or of an unsupported pixel type.
    """
    path = Path(path)
    height, width = image_shape(path)
    check_pixel_limit(path, height, width, max_pixels)
    return decode_image(path)


def decode_image(path: Path) -> torch.Tensor:
    """:func:`read_image` without the header and size checks (for files already checked)."""
    return to_float_image(decode_array(path), name=str(path))


def decode_array(path: Path) -> np.ndarray:
    """The pixels of an image file, oriented as EXIF says and converted by :func:`pixel_array`
    (no size check: the caller checked the header)."""
    if _is_16bit_colour_png(path):
        log.warning("%s: 16-bit colour PNG read with 8-bit precision (Pillow limitation)", path)
    with _open(path) as image:
        try:
            with _pillow_warnings_logged(path):  # the size was checked by the caller
                image.load()
                if _orientation(image) != 1:
                    image = ImageOps.exif_transpose(image)
                return pixel_array(image, name=str(path))
        except SceneError:
            raise
        except Exception as err:  # Pillow raises many types for a bad file
            raise SceneError(f"{path}: cannot decode image ({message_line(err)})") from err


def pixel_array(image: Image.Image, *, name: str = "image") -> np.ndarray:
    """A decoded Pillow image as a uint8 or uint16 array (H, W), (H, W, 2|3|4) for :func:`to_float_image`.

    A transparency key (``image.info["transparency"]``: palette entries or a colour) becomes an
    alpha channel; other modes are converted as :data:`CONVERTED_MODES` says.

    Raises:
        SceneError: a mode that has no faithful 8- or 16-bit reading (32-bit integer or float).
    """
    mode = image.mode
    if "transparency" in image.info and mode in ("1", "L", "P", "RGB"):
        image = image.convert("LA" if mode in ("1", "L") else "RGBA")
    elif mode in CONVERTED_MODES:
        image = image.convert(CONVERTED_MODES[mode])
    elif mode == "I":  # older Pillow reads 16-bit grayscale PNGs as 32-bit integers
        array = np.asarray(image)
        if array.size and (array.min() < 0 or array.max() > 65535):
            raise SceneError(f"{name}: 32-bit integer pixels outside the 16-bit range are not supported")
        return array.astype(np.uint16)
    elif mode not in DIRECT_MODES:
        raise SceneError(f"{name}: unsupported pixel mode {mode} (expected 1-bit, 8- or 16-bit gray, palette, RGB(A) or CMYK)")
    array = np.array(image)  # a writable copy (torch.from_numpy warns on Pillow's read-only buffer)
    if array.dtype.kind == "u" and array.dtype.itemsize == 2:
        array = array.astype(np.uint16)  # big-endian 16-bit to native
    return array


def to_float_image(array: np.ndarray, *, name: str = "image") -> torch.Tensor:
    """Convert a decoded image array to a float32 (H, W, 3|4) tensor in [0, 1].

    Args:
        array: (H, W), (H, W, 1|2|3|4) of dtype bool, uint8, uint16 or float (already in [0, 1]).
        name: used in error messages.
    """
    if array.ndim == 2:
        array = array[..., None]
    if array.ndim != 3 or array.shape[-1] not in (1, 2, 3, 4):
        raise SceneError(f"{name}: unsupported image layout {array.shape} (expected gray, RGB or RGBA)")
    if array.dtype == np.uint8:
        image = torch.from_numpy(np.ascontiguousarray(array)).float().div_(255.0)
    elif array.dtype == np.uint16:
        image = torch.from_numpy(array.astype(np.float32)).div_(65535.0)
    elif array.dtype == np.bool_:
        image = torch.from_numpy(array.astype(np.float32))
    elif np.issubdtype(array.dtype, np.floating):
        if not bool(np.isfinite(array).all()) or array.min() < 0.0 or array.max() > 1.0:  # before a cast that could overflow
            raise SceneError(f"{name}: float pixel values must be finite and within [0, 1]")
        image = torch.from_numpy(array.astype(np.float32))
    else:
        raise SceneError(f"{name}: unsupported pixel type {array.dtype} (expected 8- or 16-bit)")
    channels = image.shape[-1]
    if channels == 1:
        image = image.expand(*image.shape[:2], 3)
    elif channels == 2:
        image = torch.cat([image[..., :1].expand(*image.shape[:2], 3), image[..., 1:]], dim=-1)
    return image.contiguous()


def to_float_images(arrays: list[np.ndarray], *, names: list[str] | None = None) -> torch.Tensor:
    """Convert decoded images of one size to a float32 batch (B, H, W, 3|4) in [0, 1].

    The batch has 4 channels when any image has alpha (images without get alpha 1). A batch of
    same-layout 8-bit RGB(A) images (the usual case) is converted in one operation.
    """
    names = names or [f"image {k}" for k in range(len(arrays))]
    first = arrays[0]
    if first.dtype == np.uint8 and first.ndim == 3 and first.shape[-1] in (3, 4) and all(
        a.dtype == first.dtype and a.shape == first.shape for a in arrays
    ):
        return torch.from_numpy(np.stack(arrays)).float().div_(255.0)
    images = [to_float_image(a, name=n) for a, n in zip(arrays, names)]
    if any(im.shape[-1] == 4 for im in images):
        images = [im if im.shape[-1] == 4 else torch.cat([im, torch.ones_like(im[..., :1])], -1) for im in images]
    return torch.stack(images)


def composite(
    image: torch.Tensor, background: tuple[float, float, float]
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Composite straight-alpha RGBA on a constant background.

    Args:
        image: (..., 3) RGB or (..., 4) RGBA in [0, 1].
        background: RGB in [0, 1].

    Returns:
        rgb (..., 3) ``= rgb * a + background * (1 - a)`` and alpha (...), or the RGB unchanged
        and None when there is no alpha channel.
    """
    if image.shape[-1] == 3:
        return image, None
    rgb, alpha = image[..., :3], image[..., 3]
    bg = torch.tensor(background, dtype=image.dtype, device=image.device)
    a = alpha.unsqueeze(-1)
    return rgb * a + bg * (1.0 - a), alpha


def composite_(image: torch.Tensor, background: tuple[float, float, float]) -> torch.Tensor:
    """In-place :func:`composite` of (..., 4) RGBA: channels 0-2 become the composite, alpha stays.

    Returns ``image`` (modified), which avoids allocating full-size temporaries for large batches.
    """
    if image.shape[-1] != 4:
        raise ValueError(f"composite_ needs (..., 4) RGBA, got {tuple(image.shape)}")
    bg = torch.tensor(background, dtype=image.dtype, device=image.device)
    image[..., :3].sub_(bg).mul_(image[..., 3:]).add_(bg)
    return image


def downscaled_size(height: int, width: int, factor: float) -> tuple[int, int]:
    """``(round(height / factor), round(width / factor))``, at least 1 pixel each."""
    return max(1, round(height / factor)), max(1, round(width / factor))


def downscale_image(image: torch.Tensor, factor: float) -> torch.Tensor:
    """Reduce an image, or a batch of images, by ``factor`` with area filtering.

    The output is ``downscaled_size(H, W, factor)``; each output pixel is the mean of the input
    area it covers, so for an integer factor dividing the size it is the exact block mean.
    Composite before downscaling (see :func:`composite`): averaging straight-alpha colours would
    be wrong at the edges of transparent regions.

    Args:
        image: (H, W, C) or (B, H, W, C) float.
        factor: >= 1; a factor that keeps the size returns the input.

    Returns:
        (round(H / factor), round(W / factor), C), with the leading B when given.
    """
    if factor < 1:
        raise ValueError(f"downscale factor must be >= 1, got {factor}")
    batched = image.dim() == 4
    batch = image if batched else image.unsqueeze(0)
    height, width = batch.shape[1:3]
    size = downscaled_size(height, width, factor)
    if size == (height, width):
        return image
    out = F.interpolate(batch.permute(0, 3, 1, 2), size=size, mode="area").permute(0, 2, 3, 1).contiguous()
    return out if batched else out.squeeze(0)


def list_images(folder: str | os.PathLike) -> list[Path]:
    """Image files (PNG, JPEG, HEIC/HEIF; any case) directly in ``folder``, sorted by name."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def list_photos(folder: str | os.PathLike) -> list[Path]:
    """The images of a folder of photos: directly in ``folder``, else in its ``images/`` (:func:`list_images`)."""
    folder = Path(folder)
    return list_images(folder) or list_images(folder / "images")


def unread_images(folder: str | os.PathLike) -> dict[str, int]:
    """How many image files of each kind nerfmeta does not read (:data:`OTHER_IMAGE_SUFFIXES`) are directly in
    ``folder``, by lower-case suffix (empty for a missing folder)."""
    folder = Path(folder)
    if not folder.is_dir():
        return {}
    counts: dict[str, int] = {}
    for p in folder.iterdir():
        if p.is_file() and p.suffix.lower() in OTHER_IMAGE_SUFFIXES:
            counts[p.suffix.lower()] = counts.get(p.suffix.lower(), 0) + 1
    return dict(sorted(counts.items()))


def _is_16bit_colour_png(path: Path) -> bool:
    """True for a PNG whose header says 16 bits per channel and RGB or RGBA colour."""
    try:
        with open(path, "rb") as f:
            head = f.read(26)
    except OSError:
        return False
    return head[:8] == b"\x89PNG\r\n\x1a\n" and len(head) == 26 and head[24] == 16 and head[25] in (2, 6)
