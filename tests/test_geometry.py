"""Geometry metrics, ground truth from exact SDFs, and the eval-geometry command."""

import json
import logging

import numpy as np
import pytest
import torch

from nerfmeta.geometry.metrics import compare_surfaces, nearest, sampling_floor
from nerfmeta.geometry.truth import project_to_zero_set, sample_sdf_surface


def sphere_points(n: int, r: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return r * d, d


def test_nearest_equals_brute_force_including_a_query_equidistant_from_a_ring():
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(300, 3)), rng.normal(size=(500, 3))
    dist, idx = nearest(a, b)
    full = np.linalg.norm(a[:, None] - b[None], axis=-1)
    assert np.array_equal(idx, full.argmin(1)) and np.allclose(dist, full.min(1), rtol=0, atol=1e-12)
    angle = np.linspace(0.0, 2 * np.pi, 720, endpoint=False)
    ring = np.stack([np.cos(angle), np.sin(angle), np.zeros_like(angle)], 1)  # every point 1 from the centre
    dist, idx = nearest(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.5]]), ring)
    assert np.allclose(dist, [1.0, np.sqrt(1.25)], rtol=0, atol=1e-12) and ((idx >= 0) & (idx < len(ring))).all()


def test_identical_point_sets_give_zero():
    p, n = sphere_points(2000, 1.0)
    m = compare_surfaces(p, p, pred_normals=n, gt_normals=n)
    assert m.accuracy == 0 and m.completeness == 0 and m.chamfer == 0
    assert m.fscore == 1.0 and m.normal_consistency == pytest.approx(1.0)


def test_sphere_against_a_larger_sphere_gives_the_radius_offset():
    """Each point scaled radially: its nearest neighbour on the other sphere is its own partner, exactly delta away."""
    p, n = sphere_points(3000, 1.0)
    delta = 0.01
    m = compare_surfaces(p * (1 + delta), p, pred_normals=n, gt_normals=n, threshold=0.05, tolerance=0.001)
    assert m.accuracy == pytest.approx(delta, rel=1e-9)
    assert m.completeness == pytest.approx(delta, rel=1e-9)
    assert m.chamfer == pytest.approx(delta, rel=1e-9)
    assert m.chamfer_pct_diagonal == pytest.approx(100 * delta / m.diagonal)
    assert m.precision == 0.0 and m.fscore == 0.0  # 0.01 > tolerance 0.001 x diagonal ~2


def test_outliers_beyond_the_threshold_are_dropped_from_accuracy_only():
    p, _ = sphere_points(1000, 1.0)
    pred = np.concatenate([p, [[10.0, 0.0, 0.0]]])
    m = compare_surfaces(pred, p, threshold=0.05, tolerance=0.01)
    assert m.accuracy == 0.0 and m.precision == pytest.approx(1000 / 1001)
    assert m.outliers_pred == pytest.approx(1 / 1001) and m.outliers_gt == 0.0  # what the Chamfer left out, said


def test_a_part_moved_beyond_the_threshold_leaves_the_chamfer_and_shows_in_the_outlier_shares():
    """A sphere's top fifth (z > 0.6) lifted far away: the Chamfer drops it (DTU), the outlier shares name it."""
    p, _ = sphere_points(4000, 1.0)
    cap = p[:, 2] > 0.6
    moved = p + np.where(cap[:, None], [0.0, 0.0, 3.0], 0.0)
    m = compare_surfaces(moved, p, threshold=0.05, tolerance=0.01)
    assert m.accuracy == 0.0 and m.completeness < 0.01 * m.diagonal  # the Chamfer barely sees it ...
    assert m.outliers_pred == pytest.approx(cap.mean())  # ... the shares do: every lifted sample,
    assert 0.11 < m.outliers_gt < 0.16  # and the true cap farther than 5 % of the diagonal from what is left (z > ~0.73: 13.6 %)


def test_exact_sdf_samples_lie_on_the_surface_with_radial_normals():
    def sdf(x):
        return x.norm(dim=-1) - 0.6

    s = sample_sdf_surface(sdf, np.array([[-0.7] * 3, [0.7] * 3]), 3000, resolution=32)
    r = np.linalg.norm(s.points, axis=1)
    assert np.abs(r - 0.6).max() < 1e-9
    assert np.allclose(s.normals, s.points / r[:, None], atol=1e-6)


def test_a_twin_sampling_shares_the_mesh_and_equals_a_separate_one():
    """A ground truth and its twin (the sampling floor) come from one marching-cubes mesh: each equals the
    sampling made alone with its seed, and the two are different samplings."""
    from nerfmeta.geometry.truth import sample_sdf_surfaces

    def sdf(x):
        return x.norm(dim=-1) - 0.6

    box = np.array([[-0.7] * 3, [0.7] * 3])
    gt, twin = sample_sdf_surfaces(sdf, box, 2000, resolution=32, seeds=(1, 2))
    for pair, seed in ((gt, 1), (twin, 2)):
        alone = sample_sdf_surface(sdf, box, 2000, resolution=32, seed=seed)
        np.testing.assert_array_equal(pair.points, alone.points)
        np.testing.assert_array_equal(pair.normals, alone.normals)
    assert not np.allclose(gt.points, twin.points)


def test_the_sampling_floor_is_what_an_exact_surface_scores_and_falls_as_one_over_sqrt_n():
    """Two samplings of one sphere are not at distance 0: about half their spacing, ~ sqrt(area / n)."""
    floors = {n: sampling_floor(sphere_points(n, 1.0, seed=1)[0], sphere_points(n, 1.0, seed=2)[0]) for n in (2000, 32000)}
    assert floors[2000] > 0.5  # % of the diagonal (~3.5): 0.5 sqrt(4 pi / 2000) / 3.46 ~ 1.1 %
    assert floors[2000] / floors[32000] == pytest.approx(4.0, rel=0.15)
    exact = compare_surfaces(sphere_points(2000, 1.0, seed=3)[0], sphere_points(2000, 1.0, seed=1)[0])
    assert exact.chamfer_pct_diagonal == pytest.approx(floors[2000], rel=0.1)


def test_projection_onto_a_box_face():
    def sdf(x):
        return (x.abs() - 0.5).max(dim=-1).values  # exact inside, a bound outside: still converges on faces

    p, _ = project_to_zero_set(sdf, np.array([[0.0, 0.1, 0.53], [0.2, 0.45, 0.0]]), 1e-5)
    assert np.allclose(p, [[0.0, 0.1, 0.5], [0.2, 0.5, 0.0]], atol=1e-9)


@pytest.fixture(scope="module")
def mug_scene(tmp_path_factory):
    from nerfmeta.cli import main

    out = tmp_path_factory.mktemp("coll") / "c"
    assert main(["make-collection", str(out), "--categories", "mug", "--scenes-per-category", "2", "--views", "6", "--test-fraction", "0.5", "--val-fraction", "0",
                 "--test-views", "1", "--resolution", "16", "--workers", "1", "--supersample", "1"]) == 0
    return out / "mug" / "mug_000"


def test_a_fit_on_a_generated_scene_reports_geometry_and_eval_geometry_agrees(mug_scene, tmp_path, capsys):
    from nerfmeta.cli import main

    run = tmp_path / "run"
    assert main(["fit", str(mug_scene), "--out", str(run), "--backbone", "sdf", "--iters", "3", "--batch-rays", "64",
                 "--eval-every", "3", "--renders", "0", "--set", "depth=2", "--set", "width=16", "--set", "n_samples=16"]) == 0
    geometry = json.loads((run / "summary.json").read_text())["geometry"]
    assert geometry["ground_truth"] == "exact SDF" and 0 < geometry["chamfer"] < 0.5 and 0 <= geometry["fscore"] <= 1
    capsys.readouterr()
    assert main(["eval-geometry", str(run), "--gt", str(mug_scene), "--points", "5000", "--resolution", "32",
                 "--json-out", str(tmp_path / "g.json")]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc == json.loads((tmp_path / "g.json").read_text())
    assert doc["chamfer"] == pytest.approx(0.5 * (doc["accuracy"] + doc["completeness"]))
    assert 0 < doc["floor_pct_diagonal"] < doc["chamfer_pct_diagonal"]  # an early sphere is far from the mug
    assert doc["topology"]["components"] >= doc["topology"]["main_components"] >= 1
    assert doc["concavity"]["hidden_fraction"] > 0 and 0 <= doc["concavity"]["carved"] <= 1
    assert set(doc["surface_offset"]) <= {"all", "on_hull", "hidden"} and doc["surface_offset"]["all"]["share"] == 1.0
    assert 0.2 < doc["grad_norm"] < 5.0  # an SDF just out of its sphere init
    assert geometry["floor_pct_diagonal"] > 0 and geometry["topology"]["main_components"] >= 1
    # against its own mesh, the run's surface is far closer than against the truth
    assert main(["mesh", str(run), "--out", str(tmp_path / "m.ply"), "--resolution", "32"]) == 0
    capsys.readouterr()
    assert main(["eval-geometry", str(run), "--gt", str(tmp_path / "m.ply"), "--points", "5000", "--resolution", "32"]) == 0
    own = json.loads(capsys.readouterr().out)
    assert own["chamfer"] < 0.25 * doc["chamfer"]


def test_a_field_with_no_surface_yet_is_recorded_in_the_summary_and_not_warned_about(mug_scene, tmp_path, caplog):
    """A short density fit of a generated scene has no surface at the mesh level: an expected outcome, not a warning."""
    from nerfmeta.cli import main

    caplog.set_level(logging.INFO)
    run = tmp_path / "run"
    assert main(["fit", str(mug_scene), "--out", str(run), "--backbone", "grid", "--init", "scratch", "--iters", "1",
                 "--batch-rays", "64", "--eval-every", "0", "--renders", "0", "--no-eval-ssim"]) == 0
    geometry = json.loads((run / "summary.json").read_text())["geometry"]
    assert "never crosses the level" in geometry["error"]
    said = [r for r in caplog.records if "geometry not measured" in r.getMessage()]
    assert said and all(r.levelno < logging.WARNING for r in said)  # logged for -v, not warned


def test_gt_that_is_neither_mesh_nor_generated_scene_is_one_line_exit_2(tiny_scene, tmp_path, capsys):
    from nerfmeta.cli import main

    run = tmp_path / "run"
    assert main(["fit", str(tiny_scene), "--out", str(run), "--backbone", "sdf", "--iters", "1", "--batch-rays", "32",
                 "--renders", "0", "--eval-views", "1", "--set", "depth=1", "--set", "width=8", "--set", "n_samples=8"]) == 0
    assert "geometry" not in json.loads((run / "summary.json").read_text())  # the tiny scene has no known geometry
    capsys.readouterr()
    assert main(["eval-geometry", str(run), "--gt", str(tiny_scene)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no ground-truth geometry" in err[0]


def test_category_pretrain_and_transfer_work_on_the_sdf(mug_scene, tmp_path):
    """The SDF is weight-space: a category model of it trains and a transfer fit starts from it, frozen layers and all."""
    from nerfmeta.cli import main

    prior = tmp_path / "prior"
    assert main(["pretrain", "category", str(mug_scene.parents[1]), "--category", "mug", "--out", str(prior), "--backbone", "sdf",
                 "--iters", "3", "--batch-rays", "64", "--eval-every", "0", "--set", "depth=2", "--set", "width=16"]) == 0
    run = tmp_path / "run"
    assert main(["fit", str(mug_scene), "--out", str(run), "--init", f"category:{prior}", "--backbone", "sdf", "--iters", "2",
                 "--batch-rays", "64", "--renders", "0", "--freeze", "2"]) == 0
    summary = json.loads((run / "summary.json").read_text())
    assert summary["init"] == "category" and summary["frozen_layers"] == ["sdf.0", "sdf.1"]


def test_carved_fraction_exact_small_case():
    from nerfmeta.geometry.concavity import carved_fraction

    in_hull = torch.tensor([True, True, True, True, False, False])
    free = torch.tensor([True, True, False, True, True, False])
    outside = torch.tensor([True, False, False, True, True, True])
    figures = carved_fraction(in_hull, free, outside)
    assert figures.n_hidden == 3 and figures.hidden_fraction == 0.75 and figures.carved == pytest.approx(2 / 3)


class _StubSdf(torch.nn.Module):
    """A 'fitted' SDF that is a given function of world points (what ``surface_function`` reads)."""

    def __init__(self, fn):
        super().__init__()
        self.fn = fn

    def sdf_world(self, points):
        return self.fn(points)


def test_a_mug_has_a_hidden_cavity_the_truth_carves_and_a_filled_cup_does_not(mug_scene):
    from nerfmeta.data.registry import load_scene
    from nerfmeta.geometry.concavity import concavity_figures
    from nerfmeta.geometry.truth import scene_sdf_of

    scene = load_scene(mug_scene)
    sdf, _ = scene_sdf_of(mug_scene)
    norm = scene.normalization

    def truth_loaded(p):  # the exact surface, in the loaded frame, as a perfect fit would hold it
        offset = torch.as_tensor(norm.offset, dtype=torch.float64)
        return (sdf((p.double() - offset) / float(norm.scale)) * float(norm.scale)).float()

    exact = concavity_figures(_StubSdf(truth_loaded), scene, sdf, n_points=20000)
    assert exact.hidden_fraction > 0.2 and exact.n_hidden > 100  # the cup's inside is in every view's silhouette
    assert exact.carved > 0.99
    filled = concavity_figures(_StubSdf(lambda p: torch.full(p.shape[:1], -1.0)), scene, sdf, n_points=20000)
    assert filled.carved == 0.0 and filled.n_hidden == exact.n_hidden


def test_offset_figures_exact_small_case():
    from nerfmeta.geometry.concavity import offset_figures

    offsets = torch.tensor([-0.2, -0.1, 0.1, 0.4])
    hidden = torch.tensor([True, True, False, False])
    figures = offset_figures(offsets, {"on_hull": ~hidden, "hidden": hidden, "none": torch.zeros(4, dtype=torch.bool)}, diagonal=2.0)
    assert set(figures) == {"all", "on_hull", "hidden"}  # an empty part is left out
    assert figures["all"].mean == pytest.approx(0.05) and figures["all"].mean_abs == pytest.approx(0.2)
    assert figures["hidden"].share == 0.5 and figures["hidden"].mean == pytest.approx(-0.15)
    assert figures["hidden"].mean_pct_diagonal == pytest.approx(-7.5) and figures["on_hull"].mean_abs_pct_diagonal == pytest.approx(12.5)


def test_surface_offsets_read_a_uniform_shift_everywhere_and_split_the_cup_from_its_hull(mug_scene):
    from nerfmeta.data.registry import load_scene
    from nerfmeta.geometry.concavity import surface_offsets
    from nerfmeta.geometry.truth import ground_truth, scene_sdf_of

    scene = load_scene(mug_scene)
    sdf, _ = scene_sdf_of(mug_scene)
    norm = scene.normalization
    gt = ground_truth(mug_scene, 4000)

    def truth_loaded(p, shift):  # the exact surface in the loaded frame, made fatter by ``shift`` file units
        offset = torch.as_tensor(norm.offset, dtype=torch.float64)
        return ((sdf((p.double() - offset) / float(norm.scale)) - shift) * float(norm.scale)).float()

    exact = surface_offsets(_StubSdf(lambda p: truth_loaded(p, 0.0)), scene, gt)
    fat = surface_offsets(_StubSdf(lambda p: truth_loaded(p, 0.01)), scene, gt)
    assert exact["on_hull"]["share"] > 0.2 and exact["hidden"]["share"] > 0.1  # the outside, and the cup's inside
    assert exact["on_hull"]["share"] + exact["hidden"]["share"] == pytest.approx(1.0)
    for part in ("all", "on_hull", "hidden"):
        assert abs(exact[part]["mean"]) < 1e-4 and fat[part]["mean"] == pytest.approx(-0.01, abs=1e-4)
    assert surface_offsets(torch.nn.Module(), scene, gt) is None  # no SDF, no figure


def test_surface_gradient_norm_is_one_for_a_distance_and_scales_with_the_field(mug_scene):
    """The exact SDF (through the loaded frame's scale) reads 1 on its own surface; twice it reads 2; no SDF, None."""
    from nerfmeta.data.registry import load_scene
    from nerfmeta.geometry.concavity import surface_gradient_norm
    from nerfmeta.geometry.truth import ground_truth, scene_sdf_of

    scene = load_scene(mug_scene)
    sdf, _ = scene_sdf_of(mug_scene)
    norm = scene.normalization
    gt = ground_truth(mug_scene, 2000)
    offset = torch.as_tensor(norm.offset, dtype=torch.float64)

    def truth_loaded(p):
        return (sdf((p.double() - offset) / float(norm.scale)) * float(norm.scale)).float()

    assert surface_gradient_norm(_StubSdf(truth_loaded), scene, gt) == pytest.approx(1.0, abs=0.01)
    assert surface_gradient_norm(_StubSdf(lambda p: 2.0 * truth_loaded(p)), scene, gt) == pytest.approx(2.0, abs=0.02)
    assert surface_gradient_norm(torch.nn.Module(), scene, gt) is None
