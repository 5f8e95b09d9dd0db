"""Load-time scene normalisation (nerfmeta.data.normalize) and the scene perturbations it undoes."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from benchlib.stress import FAR_OFF, transform_blender_scene
from nerfmeta.cli import main
from nerfmeta.data import LoadOptions, Normalization, load_scene
from nerfmeta.data.normalize import CANONICAL_FAR, normalization_for
from nerfmeta.fields.registry import build_model, config_from_dict, default_config
from nerfmeta.fit.loop import FitConfig, fit
from nerfmeta.fit.sampler import view_rays
from nerfmeta.inspect import format_summary, inspect_scene, summarize_scene

LEGO = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "nerf_synthetic" / "lego"
UNIT_BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


@pytest.fixture(scope="module")
def moved(tiny_scene: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The tiny scene with its poses scaled by 1e-3 and 1e3, and translated by +1e3 along x."""
    root = tmp_path_factory.mktemp("moved")
    return {
        "small": transform_blender_scene(tiny_scene, root / "small", scale=1e-3),
        "large": transform_blender_scene(tiny_scene, root / "large", scale=1e3),
        "far": transform_blender_scene(tiny_scene, root / "far", offset=FAR_OFF),
    }


# ----- the rule ----------------------------------------------------------------------------------


def test_rule_is_identity_in_range() -> None:
    # NeRF-synthetic / tiny scene / collections: far 6 (radius 4 + 2), boxes inside [-1, 1]^3
    assert normalization_for(UNIT_BOX, 6.0).is_identity
    assert normalization_for(UNIT_BOX * 0.3 + 0.5, 3.5).is_identity
    # the ends of the sane range, and a box centre exactly ``far`` from the origin
    assert normalization_for(UNIT_BOX * 0.01, 0.1).is_identity
    assert normalization_for(UNIT_BOX, 100.0).is_identity
    assert normalization_for(UNIT_BOX + torch.tensor([6.0, 0.0, 0.0]), 6.0).is_identity


def test_rule_scales_far_to_canonical_and_moves_far_off_boxes_to_the_origin() -> None:
    norm = normalization_for(UNIT_BOX * 1e-3, 6e-3)
    assert norm.scale == pytest.approx(1000.0) and norm.offset == (0.0, 0.0, 0.0)
    assert 6e-3 * norm.scale == pytest.approx(CANONICAL_FAR)
    norm = normalization_for(UNIT_BOX * 1e3, 6e3)
    assert norm.scale == pytest.approx(1e-3) and norm.offset == (0.0, 0.0, 0.0)
    box = UNIT_BOX + torch.tensor([1000.0, 2.0, -3.0])
    norm = normalization_for(box, 6.0)
    assert norm.scale == 1.0 and norm.offset == (-1000.0, -2.0, 3.0)
    centre = norm.apply_points(box.double()).mean(0)
    torch.testing.assert_close(centre, torch.zeros(3, dtype=torch.float64))
    # both: the offset is in loaded units
    norm = normalization_for(UNIT_BOX * 1e3 + torch.tensor([0.0, 0.0, 1e5]), 6e3)
    assert norm.scale == pytest.approx(1e-3) and norm.offset == pytest.approx((0.0, 0.0, -100.0))


def test_all_scenes_of_a_collection_get_the_same_transform() -> None:
    # Same far, different boxes inside the canonical box: identity for radius 4, one shared scale for radius 500.
    boxes = [UNIT_BOX * s + torch.tensor(c) for s, c in ((0.5, (0.2, -0.3, 0.1)), (0.9, (0.0, 0.0, 0.0)), (0.3, (-0.6, 0.6, 0.6)))]
    assert all(normalization_for(b, 6.0).is_identity for b in boxes)
    transforms = {normalization_for(b, 502.0) for b in boxes}
    assert len(transforms) == 1 and next(iter(transforms)).offset == (0.0, 0.0, 0.0)


def test_normalization_maps_points_and_poses_and_back() -> None:
    norm = Normalization(scale=0.25, offset=(1.0, -2.0, 3.0))
    points = torch.tensor([[0.0, 0.0, 0.0], [4.0, 8.0, -4.0]], dtype=torch.float64)
    expected = torch.tensor([[1.0, -2.0, 3.0], [2.0, 0.0, 2.0]], dtype=torch.float64)
    torch.testing.assert_close(norm.apply_points(points), expected)
    torch.testing.assert_close(norm.invert_points(expected), points)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    pose[:3, 3] = torch.tensor([4.0, 8.0, -4.0])
    moved = norm.apply_poses(pose)
    assert torch.equal(moved[:3, :3], pose[:3, :3]) and torch.equal(moved[3], pose[3])
    torch.testing.assert_close(moved[:3, 3], expected[1])
    torch.testing.assert_close(norm.invert_poses(moved), pose)
    assert Normalization().is_identity and not norm.is_identity


# ----- loading -----------------------------------------------------------------------------------


def test_tiny_scene_loads_unchanged(tiny_scene: Path) -> None:
    scene = load_scene(tiny_scene)
    raw = load_scene(tiny_scene, normalize=False)
    assert scene.normalization.is_identity and raw.normalization.is_identity
    assert torch.equal(scene.poses, raw.poses) and torch.equal(scene.bounds, raw.bounds)
    assert (scene.near, scene.far) == (raw.near, raw.far) == (2.0, 6.0)


def test_moved_scenes_load_back_to_the_original(tiny_scene: Path, moved: dict[str, Path]) -> None:
    original = load_scene(tiny_scene)
    centre = original.bounds.double().mean(0)
    for key, shift in (("small", torch.zeros(3)), ("large", torch.zeros(3)), ("far", centre)):
        scene = load_scene(moved[key])
        assert not scene.normalization.is_identity, key
        assert (scene.near, scene.far) == (pytest.approx(2.0, rel=1e-9), pytest.approx(6.0, rel=1e-9)), key
        torch.testing.assert_close(scene.poses[:, :3, :3], original.poses[:, :3, :3], atol=0, rtol=0, msg=key)
        torch.testing.assert_close(scene.poses[:, :3, 3].double(), original.poses[:, :3, 3].double() - shift,
                                   atol=1e-5, rtol=1e-5, msg=key)
        torch.testing.assert_close(scene.bounds.double(), original.bounds.double() - shift, atol=1e-5, rtol=1e-5, msg=key)
        # the recorded transform maps the file's cameras onto the loaded ones
        raw = load_scene(moved[key], normalize=False)
        assert raw.normalization.is_identity
        torch.testing.assert_close(scene.normalization.apply_poses(raw.poses.double()).float(), scene.poses, atol=1e-4, rtol=1e-5)
    # rays of a translated view are the original's, moved
    a, b = view_rays(original, 0, "cpu"), view_rays(load_scene(moved["far"]), 0, "cpu")
    torch.testing.assert_close(b.directions, a.directions, atol=0, rtol=0)
    torch.testing.assert_close(b.origins.double(), a.origins.double() - centre, atol=1e-5, rtol=0)


def test_normalize_switch_keeps_the_files_frame(moved: dict[str, Path]) -> None:
    scene = load_scene(moved["large"], normalize=False)
    assert (scene.near, scene.far) == (2000.0, 6000.0)
    assert float(torch.linalg.vector_norm(scene.poses[:, :3, 3], dim=-1).min()) > 3000.0
    assert LoadOptions(normalize=False).normalize is False


def test_inspect_reports_the_normalisation(tiny_scene: Path, moved: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    text = format_summary(summarize_scene(load_scene(tiny_scene)))
    assert "normalisation    none (identity)" in text
    summary = inspect_scene(moved["far"])
    assert summary.normalization["scale"] == 1.0
    assert summary.normalization["offset"][0] == pytest.approx(-1000.0, abs=0.2)
    assert main(["inspect", str(moved["small"])]) == 0
    out = capsys.readouterr().out
    assert "normalisation    scale 1000, offset [0, 0, 0] (loaded = scale * file + offset)" in out
    assert "near / far       2 / 6" in out
    assert main(["inspect", str(moved["small"]), "--no-normalize", "--json"]) == 0
    assert '"scale": 1.0' in capsys.readouterr().out


# ----- fitting -----------------------------------------------------------------------------------


def _grid_psnr(scene) -> float:
    overrides = {"coarse_iters": 10, "coarse_lr_density": 1.0, "growth_steps": [20], "num_voxels": 4096, "coarse_num_voxels": 1000}
    config = config_from_dict("grid", {**_asdict(default_config("grid")), **overrides})
    model = build_model("grid", config, scene.bounds, seed=0)
    result = fit(model, scene, FitConfig(iters=60, batch_rays=256, eval_every=0, final_ssim=False), background=torch.ones(3))
    assert result.final is not None
    return result.final.psnr


def _asdict(config) -> dict:
    import dataclasses

    return dataclasses.asdict(config)


def test_moved_scenes_fit_like_the_original(tiny_scene: Path, moved: dict[str, Path]) -> None:
    reference = _grid_psnr(load_scene(tiny_scene))
    assert math.isfinite(reference) and reference > 12.0
    for key, path in moved.items():
        psnr = _grid_psnr(load_scene(path))
        assert abs(psnr - reference) < 0.5, (key, psnr, reference)


@pytest.mark.slow
@pytest.mark.skipif(not LEGO.is_dir(), reason=f"NeRF-synthetic lego not found at {LEGO}")
def test_lego_is_loaded_unchanged() -> None:
    scene = load_scene(LEGO, downscale=8)
    assert scene.normalization.is_identity
    raw = load_scene(LEGO, downscale=8, normalize=False)
    assert torch.equal(scene.bounds, raw.bounds) and torch.equal(scene.poses, raw.poses)
    assert (scene.near, scene.far) == (2.0, 6.0)
