"""Reading, compositing and downscaling images.

Images are handled as float32 tensors in [0, 1]: ``(H, W, 3)`` RGB or ``(H, W, 4)`` RGBA
(straight, not premultiplied, alpha). Grayscale is expanded to RGB. 8-bit values are divided by
255 and 16-bit values by 65535.

Files are read with imageio's Pillow plugin (PNG and JPEG). Known limit: Pillow reads 16-bit
*colour* PNGs as 8-bit (it keeps the high byte), so those come back correctly scaled but with
8-bit precision; a warning is logged. 16-bit grayscale PNGs keep their full precision.
"""

from __future__ import annotations

import logging
import os
import warnings
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

from nerfmeta.errors import SceneError

log = logging.getLogger(__name__)

DEFAULT_MAX_PIXELS = 64_000_000
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def image_shape(path: str | os.PathLike) -> tuple[int, int]:
    """``(height, width)`` of an image file, read from its header without decoding the pixels.

    Raises:
        SceneError: the file is missing or is not an image imageio can open.
    """
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{path}: image file not found")
    try:
        with warnings.catch_warnings():
            # nerfmeta applies its own pixel limit (check_pixel_limit) right after this call
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            props = iio.improps(path, index=0, plugin="pillow")
    except Exception as err:  # imageio/Pillow raise many types for a bad file
        if isinstance(err, Image.DecompressionBombError) or isinstance(err.__cause__, Image.DecompressionBombError):
            bomb = err if isinstance(err, Image.DecompressionBombError) else err.__cause__
            raise SceneError(f"{path}: image is too large to open safely ({_short(bomb)})") from err
        raise SceneError(f"{path}: not a readable PNG or JPEG image ({_short(err)})") from err
    shape = tuple(int(s) for s in props.shape)
    if len(shape) not in (2, 3) or min(shape[:2]) < 1:
        raise SceneError(f"{path}: not a 2-D image (array shape {shape})")
    return shape[0], shape[1]


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
        path: a PNG (8 or 16 bit) or JPEG file; grayscale, gray+alpha, RGB or RGBA.
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
    """The pixels of an image file as imageio decodes them (no conversion, no size check)."""
    if _is_16bit_colour_png(path):
        log.warning("%s: 16-bit colour PNG read with 8-bit precision (Pillow limitation)", path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # size checked by the caller
            return np.asarray(iio.imread(path, index=0, plugin="pillow"))
    except Exception as err:  # imageio/Pillow raise many types for a bad file
        raise SceneError(f"{path}: cannot decode image ({_short(err)})") from err


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
        image = torch.from_numpy(array.astype(np.float32))
        if not bool(torch.isfinite(image).all()) or image.min() < 0.0 or image.max() > 1.0:
            raise SceneError(f"{name}: float pixel values must be finite and within [0, 1]")
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
    """Image files (PNG/JPEG, any case) directly in ``folder``, sorted by name."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def _is_16bit_colour_png(path: Path) -> bool:
    """True for a PNG whose header says 16 bits per channel and RGB or RGBA colour."""
    try:
        with open(path, "rb") as f:
            head = f.read(26)
    except OSError:
        return False
    return head[:8] == b"\x89PNG\r\n\x1a\n" and len(head) == 26 and head[24] == 16 and head[25] in (2, 6)


def _short(err: BaseException) -> str:
    """The first line of an exception message, for one-line errors."""
    text = str(err).strip().splitlines()
    return text[0] if text else type(err).__name__
