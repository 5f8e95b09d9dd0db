"""The stress table in its reduced (CI) form: every extreme case fits without NaN to a sane PSNR.

One module-scoped run of :func:`benchlib.stress.run_table` with :data:`~benchlib.stress.QUICK`
(the same library functions and cases as ``scripts/stress.py``, tiny sizes); each case is then
checked by its own test so a failure names the case.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from benchlib.stress import (
    CASES,
    MAX_PSNR_GAP,
    QUICK,
    CaseResult,
    NanWatch,
    check_results,
    format_table,
    grazing_poses,
    run_table,
    write_grazing_scene,
    write_inside_box_scene,
    write_uniform_scene,
)
from nerfmeta.data import load_scene
from nerfmeta.fit.loop import StepRecord

QUICK_CASES = [c for c in CASES if c.quick]
TABLE_CPU_BUDGET_S = 45.0
"""CPU seconds the reduced table may use (about 30 s on one thread, i.e. about 30 s of wall time on an
idle machine). CPU time, not wall time, so that other jobs on the shared machine do not fail the test."""


@pytest.fixture(scope="module")
def table(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[CaseResult], float]:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        start = time.process_time()
        results = run_table(QUICK, tmp_path_factory.mktemp("stress"))
        return results, time.process_time() - start
    finally:
        torch.set_num_threads(threads)


@pytest.mark.parametrize("name", [c.name for c in QUICK_CASES])
def test_case_fits_without_nan_to_a_sane_psnr(table, name: str) -> None:
    results, _ = table
    case = next(c for c in QUICK_CASES if c.name == name)
    rows = [r for r in results if r.case == name]
    assert sorted(r.backbone for r in rows) == sorted(case.backbones)
    for r in rows:
        assert r.ok, f"{name} ({r.backbone}): {r.outcome}"
        assert not r.nan_seen
        if case.expect_error is not None:  # the right outcome is a clear error, e.g. a scene with no view to train on
            assert r.note.startswith("expected error: ") and r.test_psnr is None
            continue
        assert r.test_psnr is not None and math.isfinite(r.test_psnr) and r.test_psnr >= case.min_psnr
        if case.reference is not None:
            assert r.psnr_gap is not None and abs(r.psnr_gap) <= MAX_PSNR_GAP


def test_table_is_quick_and_formats(table) -> None:
    results, cpu_s = table
    assert cpu_s < TABLE_CPU_BUDGET_S, f"the reduced stress table used {cpu_s:.0f} CPU seconds"
    lines = format_table(results)
    assert len(lines) == 2 + len(results)
    assert all(line.count("|") == 10 for line in lines)


# ----- the scene writers and the checks, exactly -------------------------------------------------


def test_uniform_scene_is_one_colour_with_frustum_bounds(tmp_path: Path) -> None:
    scene = load_scene(write_uniform_scene(tmp_path / "u", (0.0, 0.5, 1.0), n_train=3, n_test=1, size=8))
    assert scene.images.shape == (4, 8, 8, 3) and scene.background is None
    torch.testing.assert_close(scene.images, torch.tensor([0.0, 128 / 255, 1.0]).expand(4, 8, 8, 3))
    assert bool((scene.bounds[1] - scene.bounds[0] > 4.0).all())  # the frusta's box, not the spheres' (about 1.9 wide)


def test_inside_box_scene_has_its_cameras_inside_the_box(tmp_path: Path) -> None:
    scene = load_scene(write_inside_box_scene(tmp_path / "i", n_train=3, n_test=1, size=8))
    centres = scene.poses[:, :3, 3]
    assert bool(((centres > scene.bounds[0]) & (centres < scene.bounds[1])).all())
    assert scene.near == pytest.approx(0.05) and scene.normalization.is_identity


def test_grazing_cameras_centre_rays_lie_in_the_box_faces(tmp_path: Path) -> None:
    scene = load_scene(write_grazing_scene(tmp_path / "g", n_train=2, n_test=3, size=9))
    (x0, y0, _), (x1, y1, z1) = scene.bounds.tolist()
    # test views 0 and 1 are grazing cameras 3 (top-down over the (x1, y1) edge) and 7 (along -x at the (y1, z1) edge)
    from nerfmeta.fit.sampler import view_rays

    for view, axes, values in ((scene.splits["test"][0], (0, 1), (x1, y1)), (scene.splits["test"][1], (1, 2), (y1, z1))):
        rays = view_rays(scene, view, "cpu")
        centre = 4 * 9 + 4  # pixel (4, 4) of a 9 x 9 image
        for axis, value in zip(axes, values):
            assert float(rays.directions[centre, axis]) == 0.0
            assert float(rays.origins[centre, axis]) == pytest.approx(value, abs=1e-6)
    assert grazing_poses([[0, 0, 0], [1, 1, 1]]).shape == (8, 4, 4)
    rot = grazing_poses([[0, 0, 0], [1, 1, 1]])[:, :3, :3]
    torch.testing.assert_close(rot @ rot.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(8, 3, 3))
    assert bool((torch.linalg.det(rot) > 0).all())


def test_check_results_flags_nan_low_and_mismatched_psnr() -> None:
    def row(case: str, psnr: float | None) -> CaseResult:
        return CaseResult(case, "grid", "ok", psnr, None, False, 0.1)

    results = [row("original (reference)", 20.0), row("poses x 1e3", 20.3), row("poses x 1e-3", 21.0),
               row("uniform white images", 25.0), row("1 training view", float("nan"))]
    check_results(results)
    outcome = {r.case: r for r in results}
    assert outcome["poses x 1e3"].ok and outcome["poses x 1e3"].psnr_gap == pytest.approx(0.3)
    assert "more than 0.5 dB" in outcome["poses x 1e-3"].outcome
    assert "below the sane floor 30" in outcome["uniform white images"].outcome
    assert "test PSNR is nan" in outcome["1 training view"].outcome and outcome["1 training view"].nan_seen
    # guard events: missing key -> n/a, a list -> its count and reasons
    rows = [CaseResult("a", "grid", "ok", 1.0, None, False, 0.0),
            CaseResult("b", "grid", "ok", 1.0, [{"iter": 3, "reason": "loss not finite", "rolled_back_to": 0, "lr_scale": 0.5}], True, 0.0)]
    lines = format_table(rows)
    assert "| n/a |" in lines[2] and "| 1 (loss not finite) | yes |" in lines[3]
    json.dumps([r.__dict__ for r in rows])  # plain data
    assert np.isfinite(rows[0].time_s)


def test_scaled_surface_rows_must_keep_the_reference_chamfer() -> None:
    """A scaled chair's surface row is checked against the unscaled one's Chamfer as well as its PSNR."""

    def row(case: str, psnr: float, chamfer: float) -> CaseResult:
        return CaseResult(case, "sdf", "ok", psnr, [], False, 0.1, chamfer_pct=chamfer)

    results = [row("sdf, a generated chair (reference)", 20.0, 1.0), row("sdf, chair x 1e-3", 20.1, 1.3),
               row("sdf, chair x 1e3", 20.1, 1.7)]
    check_results(results)
    outcome = {r.case: r for r in results}
    assert outcome["sdf, chair x 1e-3"].ok and outcome["sdf, chair x 1e-3"].chamfer_gap == pytest.approx(0.3)
    assert "Chamfer +0.70 points" in outcome["sdf, chair x 1e3"].outcome and not outcome["sdf, chair x 1e3"].ok
    assert "Chamfer +0.30 points" in format_table(results)[3]


def test_a_scaled_generated_scene_carries_its_scaled_exact_surface(tmp_path: Path) -> None:
    """The x1e3 chair's truth is the chair's exact SDF scaled by 1e3: its zero set is the original's times 1e3."""
    import dataclasses

    from nerfmeta.geometry.truth import sample_sdf_surface

    case = next(c for c in CASES if c.name == "sdf, chair x 1e3")
    reference = next(c for c in CASES if c.name == "sdf, a generated chair (reference)")
    settings = dataclasses.replace(QUICK, n_train=2, n_test=1)
    folder = case.build(tmp_path / "large", settings)
    ref_folder = reference.build(tmp_path / "ref", settings)
    (sdf, box), (sdf1, box1) = case.truth(folder), reference.truth(ref_folder)
    np.testing.assert_allclose(box, 1e3 * box1)
    large = sample_sdf_surface(sdf, box, 2000, resolution=48, seed=0)
    small = sample_sdf_surface(sdf1, box1, 2000, resolution=48, seed=0)
    np.testing.assert_allclose(large.points, 1e3 * small.points, rtol=1e-5, atol=1e-3)
    assert float(sdf1(torch.as_tensor(small.points)).abs().max()) < 1e-4 * float(np.linalg.norm(box1[1] - box1[0]))
    poses = [json.loads((f / "transforms_train.json").read_text())["frames"][0]["transform_matrix"] for f in (folder, ref_folder)]
    np.testing.assert_allclose(np.asarray(poses[0])[:3, 3], 1e3 * np.asarray(poses[1])[:3, 3], rtol=1e-6)


def test_nan_watch_notes_the_first_non_finite_loss_or_parameter() -> None:
    model = torch.nn.Linear(2, 1)
    watch = NanWatch()
    watch(StepRecord(iter=1, time_s=0.0, train_psnr=float("inf"), samples_per_ray=1.0, lr_scale=1.0), model, None)
    assert watch.first is None  # a perfect batch (+inf) is not a NaN
    with torch.no_grad():
        model.bias.fill_(float("nan"))
    watch(StepRecord(iter=2, time_s=0.0, train_psnr=20.0, samples_per_ray=1.0, lr_scale=1.0), model, None)
    assert watch.first == "iter 2: non-finite bias"
    other = NanWatch()
    other(StepRecord(iter=5, time_s=0.0, train_psnr=float("nan"), samples_per_ray=1.0, lr_scale=1.0), torch.nn.Linear(2, 1), None)
    assert other.first == "iter 5: training PSNR nan"


def test_a_case_scene_below_its_folder_is_found_again_by_the_next_backbone(tmp_path: Path) -> None:
    """A generated chair is written once (collection root = the case folder) and its scene path, one level
    below, is what every backbone fits (the second backbone used to get the collection root)."""
    import dataclasses

    from benchlib.stress import _built_scene

    case = next(c for c in CASES if c.name == "thin parts (a chair)")
    settings = dataclasses.replace(QUICK, n_train=2, n_test=1)
    first = _built_scene(case, tmp_path / "chair", settings)
    again = _built_scene(case, tmp_path / "chair", settings)
    assert first == again == tmp_path / "chair" / "chair" / "chair_000"
    assert load_scene(again).n_views == 3
