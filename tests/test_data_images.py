"""Image reading, compositing and downscaling (nerfmeta.data.images)."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from PIL import Image

from nerfmeta.data import images as images_mod
from nerfmeta.data.images import (
    composite,
    composite_,
    downscale_image,
    downscaled_size,
    image_shape,
    read_image,
    to_float_images,
)
from nerfmeta.errors import SceneError


def write_png16(path: Path, array: np.ndarray) -> None:
    """A minimal 16-bit PNG writer (Pillow cannot write 16-bit colour)."""
    h, w = array.shape[:2]
    channels = 1 if array.ndim == 2 else array.shape[2]
    colour_type = {1: 0, 2: 4, 3: 2, 4: 6}[channels]
    raw = b"".join(b"\x00" + array[y].astype(">u2").tobytes() for y in range(h))

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", w, h, 16, colour_type, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def test_rgb8_png_reads_value_over_255(tmp_path: Path) -> None:
    pixels = np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3) * 3
    iio.imwrite(tmp_path / "a.png", pixels)
    image = read_image(tmp_path / "a.png")
    assert image.dtype == torch.float32 and image.shape == (4, 5, 3)
    torch.testing.assert_close(image, torch.from_numpy(pixels).float() / 255.0, rtol=0, atol=0)


def test_gray16_png_reads_value_over_65535(tmp_path: Path) -> None:
    pixels = (np.arange(12, dtype=np.uint16).reshape(3, 4) * 5000 + 17).astype(np.uint16)
    iio.imwrite(tmp_path / "g.png", pixels)
    image = read_image(tmp_path / "g.png")
    expected = torch.from_numpy(pixels.astype(np.float32) / 65535.0)
    assert image.shape == (3, 4, 3)
    for c in range(3):
        torch.testing.assert_close(image[..., c], expected, rtol=0, atol=1e-7)


def test_rgb16_png_is_read_with_8bit_precision(tmp_path: Path) -> None:
    # Documented Pillow limitation: the scale is right, the precision is 8 bits.
    pixels = (np.arange(2 * 3 * 3, dtype=np.uint16).reshape(2, 3, 3) * 3000 + 7).astype(np.uint16)
    write_png16(tmp_path / "c.png", pixels)
    image = read_image(tmp_path / "c.png")
    expected = torch.from_numpy(pixels.astype(np.float32) / 65535.0)
    assert (image - expected).abs().max() <= 1.0 / 255.0


def test_gray8_expands_to_rgb_and_gray_alpha_keeps_alpha(tmp_path: Path) -> None:
    gray = np.array([[0, 128], [255, 64]], dtype=np.uint8)
    iio.imwrite(tmp_path / "l.png", gray)
    image = read_image(tmp_path / "l.png")
    assert image.shape == (2, 2, 3)
    assert torch.equal(image[..., 0], image[..., 2])
    assert image[1, 0, 1] == 1.0
    la = np.stack([gray, np.full_like(gray, 51)], axis=-1)
    iio.imwrite(tmp_path / "la.png", la)
    image = read_image(tmp_path / "la.png")
    assert image.shape == (2, 2, 4)
    torch.testing.assert_close(image[..., 3], torch.full((2, 2), 0.2), rtol=0, atol=1e-7)
    torch.testing.assert_close(image[..., 1], torch.from_numpy(gray).float() / 255, rtol=0, atol=0)


def test_jpeg_reads_close_to_written(tmp_path: Path) -> None:
    pixels = np.full((16, 16, 3), (200, 100, 50), dtype=np.uint8)
    iio.imwrite(tmp_path / "a.jpg", pixels, quality=95)
    image = read_image(tmp_path / "a.jpg")
    assert image.shape == (16, 16, 3)
    assert (image - torch.tensor([200, 100, 50]) / 255.0).abs().max() < 4 / 255


def test_composite_exact_on_hand_made_pixels() -> None:
    rgba = torch.tensor([[[0.2, 0.4, 0.6, 0.25], [1.0, 0.0, 0.5, 1.0], [0.3, 0.9, 0.1, 0.0]]])
    rgb, alpha = composite(rgba, (1.0, 0.5, 0.0))
    expected = torch.tensor([[[0.2 * 0.25 + 0.75, 0.4 * 0.25 + 0.5 * 0.75, 0.6 * 0.25], [1.0, 0.0, 0.5], [1.0, 0.5, 0.0]]])
    torch.testing.assert_close(rgb, expected, rtol=0, atol=1e-7)
    torch.testing.assert_close(alpha, rgba[..., 3], rtol=0, atol=0)
    inplace = composite_(rgba.clone(), (1.0, 0.5, 0.0))
    torch.testing.assert_close(inplace[..., :3], expected, rtol=0, atol=1e-7)
    torch.testing.assert_close(inplace[..., 3], rgba[..., 3], rtol=0, atol=0)
    opaque = torch.rand(2, 2, 3)
    same, none = composite(opaque, (0.0, 0.0, 0.0))
    assert none is None and torch.equal(same, opaque)


def test_read_rgba_png_then_composite(tmp_path: Path) -> None:
    pixels = np.array([[[255, 0, 0, 255], [0, 255, 0, 0]], [[0, 0, 255, 51], [255, 255, 255, 102]]], dtype=np.uint8)
    iio.imwrite(tmp_path / "a.png", pixels)
    rgb, alpha = composite(read_image(tmp_path / "a.png"), (0.0, 0.0, 0.0))
    expected = torch.tensor([[[1.0, 0, 0], [0, 0, 0]], [[0, 0, 0.2], [0.4, 0.4, 0.4]]])
    torch.testing.assert_close(rgb, expected, rtol=0, atol=1e-6)
    torch.testing.assert_close(alpha, torch.tensor([[1.0, 0.0], [0.2, 0.4]]), rtol=0, atol=1e-6)


def test_area_downscale_by_two_equals_block_means() -> None:
    image = torch.arange(4 * 4 * 2, dtype=torch.float32).reshape(4, 4, 2)
    small = downscale_image(image, 2)
    blocks = image.reshape(2, 2, 2, 2, 2).mean(dim=(1, 3))
    assert small.shape == (2, 2, 2)
    torch.testing.assert_close(small, blocks, rtol=0, atol=1e-6)
    # batched form gives the same
    torch.testing.assert_close(downscale_image(image[None], 2)[0], blocks, rtol=0, atol=1e-6)


def test_non_integer_downscale_size_and_mean() -> None:
    assert downscaled_size(10, 7, 3.0) == (3, 2)
    assert downscaled_size(800, 800, 8) == (100, 100)
    image = torch.full((10, 7, 3), 0.3)
    small = downscale_image(image, 3.0)
    assert small.shape == (3, 2, 3)
    torch.testing.assert_close(small, torch.full((3, 2, 3), 0.3))
    assert downscale_image(image, 1.0) is image
    with pytest.raises(ValueError):
        downscale_image(image, 0.5)


def test_to_float_images_mixes_layouts() -> None:
    rgb = np.zeros((2, 2, 3), np.uint8)
    rgba = np.full((2, 2, 4), 255, np.uint8)
    batch = to_float_images([rgb, rgba])
    assert batch.shape == (2, 2, 2, 4)
    assert torch.equal(batch[0, ..., 3], torch.ones(2, 2))
    assert to_float_images([rgb, rgb]).shape == (2, 2, 2, 3)


def test_png_shape_is_read_without_decoding_its_pixels(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Looking for EXIF must not decode a PNG (it did: every scene image was decoded twice)."""
    from PIL import PngImagePlugin

    Image.fromarray(np.zeros((12, 20, 3), np.uint8)).save(tmp_path / "a.png")
    loads: list[int] = []
    real = PngImagePlugin.PngImageFile.load
    monkeypatch.setattr(PngImagePlugin.PngImageFile, "load", lambda self: loads.append(1) or real(self))
    assert image_shape(tmp_path / "a.png") == (12, 20)
    assert loads == []


def test_pixel_limit_checked_before_decoding(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    iio.imwrite(tmp_path / "big.png", np.zeros((16, 16, 3), np.uint8))
    assert image_shape(tmp_path / "big.png") == (16, 16)

    def no_decode(*args: object, **kwargs: object) -> None:
        raise AssertionError("pixels decoded before the size check")

    monkeypatch.setattr(images_mod, "decode_array", no_decode)
    monkeypatch.setattr(images_mod.Image.Image, "load", no_decode)
    with pytest.raises(SceneError, match=r"big\.png.*16x16.*limit"):
        read_image(tmp_path / "big.png", max_pixels=255)


def test_unreadable_and_missing_images_name_the_file(tmp_path: Path) -> None:
    (tmp_path / "bad.png").write_bytes(b"not a png")
    with pytest.raises(SceneError, match=r"bad\.png"):
        read_image(tmp_path / "bad.png")
    with pytest.raises(SceneError, match=r"nope\.png: image file not found"):
        read_image(tmp_path / "nope.png")


# --- every pixel mode converted, EXIF orientation honoured -------------------------------------


def test_cmyk_jpeg_reads_as_its_rgb_colour_not_as_rgba(tmp_path: Path) -> None:
    Image.new("CMYK", (16, 16), (0, 255, 255, 0)).save(tmp_path / "red.jpg", quality=95)  # pure red in CMYK
    image = read_image(tmp_path / "red.jpg")
    assert image.shape == (16, 16, 3)
    assert (image - torch.tensor([1.0, 0.0, 0.0])).abs().max() < 3 / 255


@pytest.mark.parametrize(("orientation", "turn"), [(1, 0), (3, 2), (6, -1), (8, 1)])
def test_exif_orientation_is_applied_to_size_and_pixels(tmp_path: Path, orientation: int, turn: int) -> None:
    stored = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3) * 10
    exif = Image.Exif()
    exif[0x0112] = orientation
    Image.fromarray(stored).save(tmp_path / "o.png", exif=exif)  # PNG: exact pixels
    shown = np.rot90(stored, k=turn)  # k=-1: a quarter turn clockwise, as orientation 6 asks
    assert image_shape(tmp_path / "o.png") == shown.shape[:2]
    torch.testing.assert_close(read_image(tmp_path / "o.png"), torch.from_numpy(shown.copy()).float() / 255, rtol=0, atol=0)


def test_palette_transparency_becomes_alpha(tmp_path: Path) -> None:
    image = Image.new("P", (2, 1))
    image.putpalette([255, 0, 0, 0, 255, 0])
    image.putpixel((1, 0), 1)
    image.save(tmp_path / "p.png", transparency=0)  # palette entry 0 (red) is transparent
    expected = torch.tensor([[[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 1.0]]])
    torch.testing.assert_close(read_image(tmp_path / "p.png"), expected, rtol=0, atol=0)


def test_gray_and_rgb_transparency_keys_become_alpha(tmp_path: Path) -> None:
    gray = Image.new("L", (2, 1), 10)
    gray.putpixel((1, 0), 200)
    gray.save(tmp_path / "l.png", transparency=200)
    torch.testing.assert_close(read_image(tmp_path / "l.png")[..., 3], torch.tensor([[1.0, 0.0]]), rtol=0, atol=0)
    rgb = Image.new("RGB", (2, 1), (1, 2, 3))
    rgb.putpixel((0, 0), (9, 9, 9))
    rgb.save(tmp_path / "c.png", transparency=(1, 2, 3))
    torch.testing.assert_close(read_image(tmp_path / "c.png")[..., 3], torch.tensor([[1.0, 0.0]]), rtol=0, atol=0)


def test_one_bit_image_reads_as_black_and_white(tmp_path: Path) -> None:
    image = Image.new("1", (3, 1), 0)
    image.putpixel((1, 0), 1)
    image.save(tmp_path / "b.png")
    torch.testing.assert_close(read_image(tmp_path / "b.png")[0, :, 0], torch.tensor([0.0, 1.0, 0.0]), rtol=0, atol=0)


def test_modes_without_a_faithful_reading_are_refused(tmp_path: Path) -> None:
    Image.new("F", (2, 1), 0.5).save(tmp_path / "f.tiff")
    with pytest.raises(SceneError, match=r"f\.tiff: unsupported pixel mode F"):
        read_image(tmp_path / "f.tiff")


# --- HEIC/HEIF phone photos (pillow-heif) ------------------------------------------------------


def _blocks(height: int, width: int) -> np.ndarray:
    """Flat 8-pixel blocks of distinct colours (lossy HEVC keeps their means close)."""
    rng = np.random.default_rng(0)
    cells = rng.integers(0, 256, (height // 8, width // 8, 3), dtype=np.uint8)
    return np.repeat(np.repeat(cells, 8, axis=0), 8, axis=1)


@pytest.mark.parametrize("orientation", [1, 6])
def test_heic_photo_reads_as_shown(tmp_path: Path, orientation: int) -> None:
    pytest.importorskip("pillow_heif")
    shown = _blocks(32, 48)
    stored = np.ascontiguousarray(np.rot90(shown, k=1)) if orientation == 6 else shown  # 6: turn clockwise to show
    exif = Image.Exif()
    exif[0x0112] = orientation
    images_mod._register_heif()
    Image.fromarray(stored).save(tmp_path / "IMG_0001.HEIC", exif=exif.tobytes(), quality=95)
    assert image_shape(tmp_path / "IMG_0001.HEIC") == (32, 48)
    image = read_image(tmp_path / "IMG_0001.HEIC")
    assert image.shape == (32, 48, 3)
    assert (image - torch.from_numpy(shown).float() / 255).abs().mean() < 4 / 255
    assert images_mod.list_images(tmp_path) == [tmp_path / "IMG_0001.HEIC"]


def test_heic_without_pillow_heif_is_one_line_naming_the_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "IMG_0002.heic").write_bytes(b"\x00\x00\x00\x18ftypheic")
    monkeypatch.setattr(images_mod, "_register_heif", lambda: False)
    with pytest.raises(SceneError, match=r"IMG_0002\.heic: a HEIC/HEIF photo, and reading one needs pillow-heif"):
        image_shape(tmp_path / "IMG_0002.heic")


def test_a_folder_of_images_nerfmeta_does_not_read_names_them(tmp_path: Path) -> None:
    from nerfmeta.data.registry import load_scene

    for k in range(3):
        (tmp_path / f"DSC_{k}.DNG").write_bytes(b"raw")
    (tmp_path / "cover.webp").write_bytes(b"webp")
    (tmp_path / "notes.txt").write_text("not an image")
    with pytest.raises(SceneError, match=r"holds images nerfmeta does not read \(3 \.dng, 1 \.webp files\); it reads "
                                         r"PNG, JPEG and HEIC/HEIF"):
        load_scene(tmp_path)
