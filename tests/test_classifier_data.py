"""classifier.data and classifier.inputs: premultiplied views, augmentations, reading any images."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from classifier.config import NO_AUGMENT, AugmentConfig
from classifier.data import (ViewSet, augment_views, chimera_partners, chimera_views, composite, normalize, scene_premultiplied,
                             to_input_size)
from classifier.inputs import image_premultiplied, read_scene_views
from nerfmeta.data import load_scene
from nerfmeta.errors import SceneError



def _rgba(h: int = 8, w: int = 8) -> torch.Tensor:
    """(h, w, 4) straight RGBA: a red opaque square on a transparent field."""
    image = torch.zeros(h, w, 4)
    image[2:6, 2:6] = torch.tensor([1.0, 0.0, 0.0, 1.0])
    image[0, 0] = torch.tensor([0.0, 1.0, 0.0, 0.5])  # half-transparent green
    return image


def test_premultiplied_recomposites_exactly_on_any_background():
    image = _rgba()
    views = image_premultiplied(image)[None]  # (1, 4, H, W)
    for bg in [(1.0, 1.0, 1.0), (0.2, 0.4, 0.6)]:
        expected = image[..., :3] * image[..., 3:] + torch.tensor(bg) * (1 - image[..., 3:])
        assert torch.allclose(composite(views, bg)[0].permute(1, 2, 0), expected, atol=1e-6)
    # a scene composited on white and read back gives the same premultiplied views
    assert views[0, :, 0, 0].tolist() == pytest.approx([0.0, 0.5, 0.0, 0.5])


def test_scene_premultiplied_undoes_the_loader_background(tiny_scene: Path):
    white = scene_premultiplied(load_scene(tiny_scene, background=(1.0, 1.0, 1.0)))
    black = scene_premultiplied(load_scene(tiny_scene, background=(0.0, 0.0, 0.0)))
    assert white.shape[1] == 4 and white.shape[0] >= 8
    assert torch.allclose(white, black, atol=2e-6)


def test_to_input_size_pads_to_square_with_transparency():
    views = torch.ones(1, 4, 4, 8)  # wide opaque white image
    out = to_input_size(views, 8)
    assert out.shape == (1, 4, 8, 8)
    assert out[0, 3, :2].sum() == 0 and out[0, 3, 6:].sum() == 0  # transparent bands top and bottom
    assert torch.all(out[0, 3, 2:6] == 1)
    small = to_input_size(torch.ones(2, 4, 32, 32), 16)
    assert small.shape == (2, 4, 16, 16) and torch.allclose(small, torch.ones_like(small))


def test_augment_without_changes_is_compositing_on_the_background():
    views = image_premultiplied(_rgba())[None].repeat(3, 1, 1, 1)
    out = augment_views(views, NO_AUGMENT, (1.0, 1.0, 1.0), torch.Generator().manual_seed(0))
    assert torch.allclose(out, composite(views, (1.0, 1.0, 1.0)), atol=1e-6)


def test_augment_is_seeded_and_stays_in_range():
    views = image_premultiplied(_rgba(16, 16))[None].repeat(6, 1, 1, 1)
    a = augment_views(views, AugmentConfig(hue=0.05), (1.0, 1.0, 1.0), torch.Generator().manual_seed(3))
    b = augment_views(views, AugmentConfig(hue=0.05), (1.0, 1.0, 1.0), torch.Generator().manual_seed(3))
    c = augment_views(views, AugmentConfig(hue=0.05), (1.0, 1.0, 1.0), torch.Generator().manual_seed(4))
    assert a.shape == (6, 3, 16, 16)
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert a.min() >= 0 and a.max() <= 1
    assert not torch.allclose(a[0], a[1])  # each view gets its own draw


def test_background_augmentation_changes_only_transparent_pixels():
    views = image_premultiplied(_rgba())[None].repeat(8, 1, 1, 1)
    only_bg = AugmentConfig(scale=(1.0, 1.0), translate=0.0, rotate_degrees=0.0, hflip=0.0, background=1.0,
                            brightness=0.0, contrast=0.0, saturation=0.0, hue=0.0)
    out = augment_views(views, only_bg, (1.0, 1.0, 1.0), torch.Generator().manual_seed(0))
    assert torch.allclose(out[:, :, 3, 3], torch.tensor([1.0, 0.0, 0.0]).expand(8, 3))  # the opaque object
    corners = out[:, :, 7, 7]
    assert corners.std(dim=0).sum() > 0.1  # random colours behind it


def test_view_set_subset_takes_evenly_spaced_views_of_each_scene():
    scene_index = torch.tensor([0] * 9 + [1] * 2)
    views = torch.arange(11, dtype=torch.uint8).view(11, 1, 1, 1).expand(11, 4, 2, 2).contiguous()
    vs = ViewSet(views, torch.zeros(11, dtype=torch.long), scene_index, scenes=("a", "b"))  # type: ignore[arg-type]
    sub = vs.subset(3)
    assert sub.views[:, 0, 0, 0].tolist() == [0, 4, 8, 9, 10]  # 3 of scene a (ends and middle), both of b
    assert sub.scene_index.tolist() == [0, 0, 0, 1, 1]


def test_normalize():
    rgb = torch.full((1, 3, 2, 2), 0.5)
    out = normalize(rgb, (0.5, 0.25, 0.0), (1.0, 0.5, 0.25))
    assert out[0, :, 0, 0].tolist() == pytest.approx([0.0, 0.5, 2.0])


# --- reading what classify is given -------------------------------------------------------------


def test_reads_8_and_16_bit_png_rgb_rgba_and_jpeg_of_any_size(tmp_path: Path):
    folder = tmp_path / "photos"
    folder.mkdir()
    rgba8 = (np.asarray(_rgba(20, 30)) * 255).astype(np.uint8)
    iio.imwrite(folder / "a.png", rgba8)
    iio.imwrite(folder / "b.png", (np.asarray(_rgba(40, 16))[..., 0] * 65535).astype(np.uint16))  # 16-bit gray
    iio.imwrite(folder / "c.jpg", np.full((50, 50, 3), 128, np.uint8))
    iio.imwrite(folder / "d.png", np.full((7, 9, 3), 255, np.uint8))
    views = read_scene_views(folder, size=16, background=(1.0, 1.0, 1.0))
    assert views.shape == (4, 4, 16, 16)
    assert torch.allclose(views[2, :3], torch.full((3, 16, 16), 128 / 255), atol=0.02)  # JPEG grey, opaque
    assert torch.allclose(views[2, 3], torch.ones(16, 16))
    single = read_scene_views(folder / "a.png", size=16, background=(1.0, 1.0, 1.0))
    assert torch.equal(single[0], views[0])


def test_reads_a_scene_folder_with_all_its_views(tiny_scene: Path):
    scene = load_scene(tiny_scene)
    views = read_scene_views(tiny_scene, size=16, background=(1.0, 1.0, 1.0))
    assert views.shape == (scene.n_views, 4, 16, 16)


def test_no_readable_images_is_a_one_line_scene_error(tmp_path: Path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(SceneError, match="empty"):
        read_scene_views(empty, size=16, background=(1.0, 1.0, 1.0))
    with pytest.raises(SceneError, match="not found"):
        read_scene_views(tmp_path / "nowhere", size=16, background=(1.0, 1.0, 1.0))
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "x.png").write_bytes(b"not a png")
    with pytest.raises(SceneError, match="x.png") as err:
        read_scene_views(bad, size=16, background=(1.0, 1.0, 1.0))
    assert "\n" not in str(err.value)
    other = tmp_path / "notes"
    other.mkdir()
    (other / "readme.txt").write_text("hello")
    with pytest.raises(SceneError):
        read_scene_views(other, size=16, background=(1.0, 1.0, 1.0))


def test_chimera_partners_always_mix_two_classes_and_are_seeded():
    labels = torch.tensor([0, 0, 0, 1, 2, 2, 2, 2])
    first, second = chimera_partners(labels, 200, torch.Generator().manual_seed(0))
    assert (labels[first] != labels[second]).all()
    assert set(labels[second].tolist()) == {0, 1, 2}  # every other class is drawn, the rare one too
    again = chimera_partners(labels, 200, torch.Generator().manual_seed(0))
    assert torch.equal(first, again[0]) and torch.equal(second, again[1])
    with pytest.raises(ValueError, match="two classes"):
        chimera_partners(torch.zeros(5, dtype=torch.long), 3, torch.Generator())


def test_chimera_is_two_views_joined_along_one_straight_cut():
    n, size = 64, 20
    a = torch.rand(n, 4, size, size)
    b = a + 2.0  # every pixel tells which view it came from
    out = chimera_views(a, b, torch.Generator().manual_seed(1))
    from_b = out >= 2.0
    assert torch.equal(torch.where(from_b, out, b), b) and torch.equal(torch.where(from_b, a, out), a)
    directions = set()
    for m in from_b:
        assert (m == m[:1]).all()  # the four channels agree: premultiplied colour and alpha travel together
        m = m[0]
        by_column = (m == m[:1]).all()  # every row the same: a vertical cut
        line = m[0] if by_column else m[:, 0]
        assert by_column or (m == m[:, :1]).all()
        k = int(line.sum())
        assert 0.35 * size - 1 <= k <= 0.65 * size + 1  # the cut lies near the middle: each side a real part
        assert torch.equal(line, line.sort(descending=bool(line[0]))[0])  # one side, then the other
        directions.add((bool(by_column), bool(line[0])))
    assert len(directions) == 4  # both directions, either view on either side
