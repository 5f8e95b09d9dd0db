"""``nerfmeta poses`` and ``nerfmeta fit PHOTOS`` on small generated textured scenes (seconds each).

What must hold: the poses match the true ones after a similarity (rotation < 1 degree, centres
within 1 % of the scene); the written scene loads through the registry; the photo folder is
never written to; bad input is one line, exit 2, and nothing is left half-written.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

pytest.importorskip("pycolmap")

import sfm_scenes  # noqa: E402

from nerfmeta.cli import main  # noqa: E402
from nerfmeta.data.registry import load_scene  # noqa: E402
from nerfmeta.data.sfm import (SfmConfig, best_draw, cached_poses, compute_poses, match_agreement, prepare_photo,  # noqa: E402
                               read_verified_matches, reconstruct)
from nerfmeta.errors import SceneError  # noqa: E402

HEIGHT, WIDTH, VIEWS, TURN = 192, 256, 10, 0.4
SCENE_SIZE = 8.0  # the ground square's side


def _folder_digest(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


@pytest.fixture(scope="module")
def arc(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    """A folder of 10 photos of the textured cube over 144 degrees of a ring, and their true poses."""
    poses = sfm_scenes.ring_poses(VIEWS, turn=TURN)
    folder = tmp_path_factory.mktemp("arc") / "photos"
    sfm_scenes.write_photos(folder, sfm_scenes.render(poses, 0.8 * WIDTH, HEIGHT, WIDTH))
    return folder, poses


@pytest.fixture(scope="module")
def solved(arc: tuple[Path, np.ndarray], tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object, dict]:
    folder, _ = arc
    before = _folder_digest(folder)
    out = tmp_path_factory.mktemp("solved") / "scene"
    result = compute_poses(folder, out, SfmConfig(threads=1))
    assert _folder_digest(folder) == before  # the photos were only read
    return out, result, json.loads((out / "transforms.json").read_text())


def test_poses_match_the_true_ones(arc, solved) -> None:
    _, true = arc
    out, result, doc = solved
    assert len(result.registered) == VIEWS and not result.unregistered
    estimated = np.array([f["transform_matrix"] for f in doc["frames"]])
    rotation_deg, centre = sfm_scenes.pose_errors(estimated, true)
    assert rotation_deg.max() < 1.0
    assert centre.max() < 0.01 * SCENE_SIZE
    scale = sfm_scenes.umeyama(estimated[:, :3, 3], true[:, :3, 3])[0]  # SfM's unit is arbitrary
    assert doc["camera_model"] == "PINHOLE" and scale * doc["near"] < 3.0 < 6.0 < scale * doc["far"]  # cameras 4.5 from the cube
    assert abs(doc["fl_x"] / doc["w"] - 0.8) < 0.02  # the focal length found is the one rendered with


def test_written_scene_loads_through_the_registry(solved) -> None:
    out, result, doc = solved
    scene = load_scene(out, normalize=False)
    assert scene.format == "nerfstudio" and scene.images.shape[0] == VIEWS
    assert (scene.height, scene.width) == (doc["h"], doc["w"])
    assert sorted(p.name for p in (out / "images").iterdir()) == sorted(result.registered)
    report = json.loads((out / "sfm.json").read_text())
    assert report["registered"] == list(result.registered) and report["config"]["max_side"] == 1600
    assert result.jumps == () and report["jumps"] == []  # the arc is a walk of 16-degree steps, kept whole
    assert result.matcher == report["matcher"] == "exhaustive" and report["config"]["matcher"] == "auto"


def _first_model_folds(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Make the first model's walk look folded at its fourth photo (what every pair does on beer); the matchers used."""
    import nerfmeta.data.sfm as sfm

    real, seen = sfm.model_jumps, []

    def jumps(model, names):
        seen.append(names)
        return [names[3]] if len(seen) == 1 else real(model, names)

    monkeypatch.setattr(sfm, "model_jumps", jumps)
    return seen


def test_auto_matches_neighbours_when_every_pair_folds_a_walk(arc, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                              caplog: pytest.LogCaptureFixture) -> None:
    folder, true = arc
    seen = _first_model_folds(monkeypatch)
    result = compute_poses(folder, tmp_path / "scene", SfmConfig(threads=1))
    # every pair (folded), the seven draws of the neighbours' matches, and the kept draw against the first model
    assert len(seen) == 9 and result.matcher == "sequential" and result.jumps == ()
    assert f"folded the walk at {seen[0][3]}" in caplog.text and "with its next 10 only" in caplog.text
    estimated = np.array([f["transform_matrix"] for f in json.loads((tmp_path / "scene" / "transforms.json").read_text())["frames"]])
    rotation_deg, centre = sfm_scenes.pose_errors(estimated, true)
    assert rotation_deg.max() < 1.0 and centre.max() < 0.01 * SCENE_SIZE
    report = json.loads((tmp_path / "scene" / "sfm.json").read_text())
    assert report["matcher"] == "sequential"
    # the neighbours' matches were mapped six times (seeds 0-5) and once globally, and the best-agreeing draw kept
    assert [(d["mapper"], d["seed"]) for d in result.draws] == [("incremental", k) for k in range(6)] + [("global", 0)]
    assert sum(d["kept"] for d in result.draws) == 1 and all(d["registered"] == VIEWS for d in result.draws)
    kept = next(d for d in result.draws if d["kept"])
    assert kept["registered"] == VIEWS and kept["agreement"] == max(d["agreement"] for d in result.draws) > 0.9
    assert report["draws"] == list(result.draws)


def _bent(model, names: set[str], degrees: float):
    """A copy of ``model`` whose cameras ``names`` are turned by ``degrees`` about the world's z axis (a walk bent
    at one photo, as one COLMAP mapping in four bent beer's)."""
    import pycolmap

    bent = pycolmap.Reconstruction(model)
    turn = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0.0, 0.0, np.radians(degrees)])), np.zeros(3))
    for image in bent.images.values():
        if image.name in names:
            frame = bent.frames[image.frame_id]
            frame.rig_from_world = frame.rig_from_world * turn
    return bent


def test_a_bent_walk_explains_fewer_matches_and_is_not_kept(arc, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import nerfmeta.data.sfm as sfm

    folder, _ = arc
    names = sorted(p.name for p in folder.iterdir())
    config = SfmConfig(threads=1, map_draws=3)
    whole = reconstruct(folder, names, tmp_path, config, lambda *_: None, {})
    database = tmp_path / "database.db"
    bent = _bent(whole, set(names[VIEWS // 2:]), 3.0)
    matches = read_verified_matches(database)
    assert match_agreement(whole, matches) > 0.95  # exact renders: nearly every verified match fits
    assert match_agreement(bent, matches) < match_agreement(whole, matches) - 0.1  # 0.81 against 1.00
    for first, others, expect in ((whole, [bent, bent, bent], 0), (bent, [bent, whole, bent], 2), (bent, [bent, bent, whole], 3)):
        later = iter(others)
        monkeypatch.setattr(sfm, "map_matches", lambda *args, **kwargs: next(later))
        model, draws = best_draw(first, tmp_path, folder, names, database, config, lambda *_: None, {})
        assert model is whole and [d["kept"] for d in draws] == [k == expect for k in range(4)]
        assert [d["mapper"] for d in draws] == ["incremental"] * 3 + ["global"]
    alone = SfmConfig(threads=1, map_draws=1, global_draw=False)
    assert best_draw(bent, tmp_path, folder, names, database, alone, lambda *_: None, {}) == (bent, ())


def test_a_chosen_matcher_is_kept_and_its_fold_named(arc, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                     caplog: pytest.LogCaptureFixture) -> None:
    folder, _ = arc
    seen = _first_model_folds(monkeypatch)
    result = compute_poses(folder, tmp_path / "scene", SfmConfig(threads=1, matcher="exhaustive"))
    assert len(seen) == 1 and result.matcher == "exhaustive" and result.jumps == (seen[0][3],)
    assert f"more than 90 degrees from the previous photo at {seen[0][3]}" in caplog.text and "--matcher sequential" in caplog.text


@pytest.mark.parametrize(("config", "offsets"), [
    (SfmConfig(threads=1, matcher="sequential", overlap=2), {1, 2}),
    (SfmConfig(threads=1, matcher="sequential", overlap=3, far_pairs=True), {1, 2, 4}),  # 2^k, k < 3
    (SfmConfig(threads=1), set(range(1, VIEWS))),
])
def test_which_photos_are_matched(arc, tmp_path: Path, config: SfmConfig, offsets: set[int]) -> None:
    import pycolmap

    folder, _ = arc
    names = sorted(p.name for p in folder.iterdir())
    reconstruct(folder, names, tmp_path, config, lambda *_: None, {})
    database = pycolmap.Database.open(tmp_path / "database.db")
    try:
        name_of = {image.image_id: image.name for image in database.read_all_images()}
        pairs, _ = database.read_all_matches()
    finally:
        database.close()
    found = {abs(names.index(name_of[a]) - names.index(name_of[b])) for a, b in map(pycolmap.pair_id_to_image_pair, pairs)}
    assert found == offsets


def test_sequential_matching_of_neighbours_only(arc, tmp_path: Path) -> None:
    folder, true = arc
    result = compute_poses(folder, tmp_path / "scene", SfmConfig(threads=1, matcher="sequential", overlap=2))
    doc = json.loads((tmp_path / "scene" / "transforms.json").read_text())
    estimated = np.array([f["transform_matrix"] for f in doc["frames"]])
    rotation_deg, centre = sfm_scenes.pose_errors(estimated, true)
    assert len(result.registered) == VIEWS and result.jumps == ()
    assert rotation_deg.max() < 1.0 and centre.max() < 0.01 * SCENE_SIZE
    assert json.loads((tmp_path / "scene" / "sfm.json").read_text())["config"]["overlap"] == 2


def test_out_that_is_not_ours_is_refused(arc, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder, _ = arc
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    assert main(["poses", str(folder), "--out", str(out), "--overwrite"]) == 2
    assert "not a poses run folder" in capsys.readouterr().err
    assert (out / "notes.txt").read_text() == "keep me" and sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    assert main(["poses", str(folder), "--out", str(folder)]) == 2  # never into the photo folder itself


def _fails(args: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    return err[-1]


def test_one_photo(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "one"
    sfm_scenes.write_photos(folder, np.zeros((1, 8, 8, 3), np.uint8))
    line = _fails(["poses", str(folder), "--out", str(tmp_path / "s")], capsys)
    assert "1 photo(s) (view_000.png)" in line and "at least 3" in line
    assert not (tmp_path / "s").exists()


def test_corrupt_photo_is_named(arc, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "bad"
    folder.mkdir()
    for p in sorted(arc[0].iterdir())[:4]:
        (folder / p.name).write_bytes(p.read_bytes())
    (folder / "view_002.png").write_bytes(b"\x89PNG\r\n\x1a\n not really")
    line = _fails(["poses", str(folder), "--out", str(tmp_path / "s")], capsys)
    assert "view_002.png" in line and "not a readable" in line
    assert not (tmp_path / "s").exists()


def test_mixed_sizes_are_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "mixed"
    sfm_scenes.write_photos(folder, np.zeros((3, 8, 12, 3), np.uint8))
    Image.fromarray(np.zeros((8, 10, 3), np.uint8)).save(folder / "view_009.png")
    line = _fails(["poses", str(folder), "--out", str(tmp_path / "s")], capsys)
    assert "view_009.png: is 10x8 but view_000.png is 12x8" in line
    assert not (tmp_path / "s").exists()


def test_portrait_photos_among_landscape_ones_are_turned_and_posed(arc, tmp_path: Path, caplog) -> None:
    """A phone held upright for some shots: those photos are turned a quarter to the others' orientation, and
    each is posed as the camera that took the turned picture (rolled by the turn)."""
    folder, true = arc
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    stored_turn = {2: 1, 5: 1, 7: -1}  # np.rot90's k: a quarter anticlockwise (turned back exactly), or clockwise
    for k, path in enumerate(sorted(folder.glob("view_*.png"))):
        image = np.asarray(Image.open(path).convert("RGB"))
        Image.fromarray(np.ascontiguousarray(np.rot90(image, k=stored_turn.get(k, 0)))).save(mixed / path.name)
    result = compute_poses(mixed, tmp_path / "scene", SfmConfig(threads=1))
    assert result.turned == ("view_002.png", "view_005.png", "view_007.png") and len(result.registered) == VIEWS
    assert "3 of 10 photos are portrait, the rest landscape: turned a quarter clockwise" in caplog.text
    doc = json.loads((tmp_path / "scene" / "transforms.json").read_text())
    assert doc["w"] > doc["h"]
    estimated = np.array([f["transform_matrix"] for f in doc["frames"]])
    estimated[7, :3, :3] = estimated[7, :3, :3] @ np.diag([-1.0, -1.0, 1.0])  # view 7 shows the scene upside down
    rotation_deg, centre = sfm_scenes.pose_errors(estimated, true)
    assert rotation_deg.max() < 1.0 and centre.max() < 0.01 * SCENE_SIZE
    assert json.loads((tmp_path / "scene" / "sfm.json").read_text())["turned"] == list(result.turned)


def test_photos_with_no_overlap(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "noise"
    rng = np.random.default_rng(0)
    sfm_scenes.write_photos(folder, rng.integers(0, 256, (4, 96, 96, 3), dtype=np.uint8))
    line = _fails(["poses", str(folder), "--out", str(tmp_path / "s"), "--threads", "1"], capsys)
    assert "found no two photos that overlap" in line
    assert not (tmp_path / "s").exists() and not any(p.name.startswith(".s.") for p in tmp_path.iterdir())


def test_unregistered_photos_are_named(arc, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "some"
    folder.mkdir()
    for p in arc[0].iterdir():
        (folder / p.name).write_bytes(p.read_bytes())
    rng = np.random.default_rng(1)
    for k in range(3):
        Image.fromarray(rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)).save(folder / f"zz_noise{k}.png")
    # 10 of 13 (0.77) is under the default 0.8: an error naming them, and the command that keeps the rest
    line = _fails(["poses", str(folder), "--out", str(tmp_path / "s"), "--threads", "1"], capsys)
    assert "3 of 13 photos did not register (at least 0.8 must): zz_noise0.png, zz_noise1.png, zz_noise2.png" in line
    assert f"nerfmeta poses {folder} --out SCENE --min-registered 0.76" in line
    assert not (tmp_path / "s").exists()
    (folder / "zz_noise1.png").unlink()
    (folder / "zz_noise2.png").unlink()
    # 10 of 11 by default: the scene is made without the photo that did not register, which is named
    assert main(["poses", str(folder), "--out", str(tmp_path / "s"), "--threads", "1"]) == 0
    assert "left out 1 photo(s) that did not register: zz_noise0.png" in capsys.readouterr().out
    assert json.loads((tmp_path / "s" / "sfm.json").read_text())["unregistered"] == ["zz_noise0.png"]
    assert load_scene(tmp_path / "s").images.shape[0] == VIEWS


def test_exif_orientation_and_downscale_on_load(tmp_path: Path) -> None:
    shown = np.zeros((4, 6, 3), np.uint8)
    shown[0, :] = 255  # the top row white, as a viewer shows it
    exif = Image.Exif()
    exif[0x0112] = 6  # "rotate 90 degrees clockwise to show"
    source = tmp_path / "rotated.png"
    Image.fromarray(np.ascontiguousarray(np.rot90(shown, 1))).save(source, exif=exif)
    prepare_photo(source, tmp_path / "out.png", (4, 6))
    np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / "out.png")), shown)
    prepare_photo(source, tmp_path / "small.png", (2, 3))
    small = np.asarray(Image.open(tmp_path / "small.png"))
    assert small.shape == (2, 3, 3) and small[0].min() > 100 and small[1].max() < 100


def test_fit_on_photos_computes_the_poses_once(arc, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    import nerfmeta.data.sfm as sfm

    monkeypatch.setenv("NERFMETA_CACHE", str(tmp_path / "cache"))
    folder, _ = arc
    before = _folder_digest(folder)
    run = tmp_path / "run"
    assert main(["fit", str(folder), "--out", str(run), "--init", "scratch", "--iters", "2", "--eval-views", "1",
                 "--renders", "0", "--downscale", "4"]) == 0
    assert "computing them by structure from motion" in capsys.readouterr().err
    scene = Path(json.loads((run / "config.json").read_text())["scene"])
    assert scene.parent == tmp_path / "cache" / "poses" and (scene / "transforms.json").is_file()
    assert _folder_digest(folder) == before

    def no_second_run(*args, **kwargs):
        raise AssertionError("structure from motion ran again")

    monkeypatch.setattr(sfm, "compute_poses", no_second_run)
    assert cached_poses(folder) == (scene, True)
    (folder / "view_000.png").rename(folder / "view_000.renamed.png")  # other photos: another key, computed anew
    with pytest.raises(AssertionError, match="ran again"):
        cached_poses(folder)
    (folder / "view_000.renamed.png").rename(folder / "view_000.png")


def test_fit_on_photos_names_the_ones_left_out_each_time(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    import nerfmeta.data.sfm as sfm
    from nerfmeta.commands.poses import poses_for_photos

    monkeypatch.setenv("NERFMETA_CACHE", str(tmp_path / "cache"))
    folder = tmp_path / "photos"
    sfm_scenes.write_photos(folder, np.zeros((3, 8, 12, 3), np.uint8))

    def fake_sfm(photos, out, config, **kwargs):  # what compute_poses leaves when a photo did not register
        Path(out).mkdir(parents=True)
        (Path(out) / sfm.TRANSFORMS).write_text("{}")
        (Path(out) / sfm.REPORT).write_text(json.dumps({"photos": 3, "unregistered": ["view_001.png"]}))

    monkeypatch.setattr(sfm, "compute_poses", fake_sfm)
    for _ in range(2):  # computed, then from the cache
        poses_for_photos(str(folder))
        assert "left out 1 photo(s) that did not register: view_001.png" in capsys.readouterr().err


def test_photo_folder_is_not_a_scene_without_pycolmap_hint(arc, tmp_path: Path) -> None:
    with pytest.raises(SceneError, match="nerfmeta poses PHOTOS --out SCENE"):
        load_scene(arc[0])


def test_heic_phone_photos_are_posed_under_jpeg_names(arc, tmp_path: Path) -> None:
    """An iPhone capture: HEIC files stored sideways with EXIF orientation 6 (as a portrait shot is kept)."""
    pytest.importorskip("pillow_heif")
    from nerfmeta.data import images

    folder, true = arc
    heic = tmp_path / "phone"
    heic.mkdir()
    images._register_heif()
    exif = Image.Exif()
    exif[0x0112] = 6
    for path in sorted(folder.glob("view_*.png")):
        stored = np.ascontiguousarray(np.rot90(np.asarray(Image.open(path).convert("RGB")), k=1))
        Image.fromarray(stored).save(heic / f"{path.stem}.HEIC", exif=exif.tobytes(), quality=95)
    result = compute_poses(heic, tmp_path / "scene", SfmConfig(threads=1))
    doc = json.loads((tmp_path / "scene" / "transforms.json").read_text())
    assert result.registered == tuple(f"view_{k:03d}.jpg" for k in range(VIEWS)) and not result.unregistered
    assert WIDTH - 4 <= doc["w"] <= WIDTH and HEIGHT - 4 <= doc["h"] <= HEIGHT  # upright as shown (undistortion crops)
    rotation_deg, centre = sfm_scenes.pose_errors(np.array([f["transform_matrix"] for f in doc["frames"]]), true)
    assert rotation_deg.max() < 1.0 and centre.max() < 0.01 * SCENE_SIZE
    assert load_scene(tmp_path / "scene").images.shape[0] == VIEWS


def test_one_shot_in_two_formats_is_refused(tmp_path: Path) -> None:
    from nerfmeta.data.sfm import prepared_names

    assert prepared_names([Path("a.png"), Path("IMG_1.heic"), Path("b.HEIF")]) == {
        "a.png": "a.png", "IMG_1.heic": "IMG_1.jpg", "b.HEIF": "b.jpg"}
    with pytest.raises(SceneError, match=r"IMG_1\.jpg and IMG_1\.HEIC would both be IMG_1\.jpg in the scene"):
        prepared_names([Path("IMG_1.jpg"), Path("IMG_1.HEIC")])


def _colmap_project(scene: Path, out: Path, *, model_dir: str = "sparse/0", text: bool = False) -> Path:
    """A COLMAP project (``images/`` beside ``sparse/0/``) made of a poses scene's images and model."""
    import pycolmap
    import shutil

    shutil.copytree(scene / "images", out / "images")
    (out / model_dir).mkdir(parents=True)
    model = pycolmap.Reconstruction(str(scene / "colmap"))
    (model.write_text if text else model.write_binary)(str(out / model_dir))
    return out


@pytest.mark.parametrize(("model_dir", "text"), [("sparse/0", False), ("sparse", True)])
def test_a_colmap_project_is_read_as_it_is(solved, tmp_path: Path, model_dir: str, text: bool) -> None:
    """images/ + sparse/0 (as COLMAP, 3DGS and Mip-NeRF 360 data come): the poses and intrinsics of the same model
    as the nerfstudio scene nerfmeta poses wrote from it, and no structure from motion run again."""
    from nerfmeta.data.registry import is_photo_folder

    out, _, _ = solved
    project = _colmap_project(out, tmp_path / "project", model_dir=model_dir, text=text)
    assert not is_photo_folder(project)
    scene, reference = load_scene(project, normalize=False), load_scene(out, normalize=False)
    assert scene.format == "colmap" and scene.image_names == reference.image_names
    torch.testing.assert_close(scene.poses, reference.poses, rtol=0, atol=1e-9)
    torch.testing.assert_close(scene.intrinsics, reference.intrinsics, rtol=0, atol=1e-9)
    assert (scene.near, scene.far) == pytest.approx((reference.near, reference.far))
    assert scene.splits == reference.splits and "sparse points" in scene.near_far_source


def test_a_colmap_project_with_resized_images_scales_its_intrinsics(solved, tmp_path: Path) -> None:
    out, _, _ = solved
    project = _colmap_project(out, tmp_path / "project")
    for path in (project / "images").iterdir():  # a dataset's images at half the size COLMAP saw
        with Image.open(path) as image:
            image.resize((image.width // 2, image.height // 2)).save(path)
    scene, reference = load_scene(project, normalize=False), load_scene(out, normalize=False)
    torch.testing.assert_close(scene.intrinsics, reference.intrinsics * 0.5, rtol=0.01, atol=0)
    with Image.open(next((project / "images").iterdir())) as image:
        other = image.resize((image.width, image.height // 3))
    for path in (project / "images").iterdir():
        other.save(path)
    with pytest.raises(SceneError, match=r"sparse/0: the model's images are \d+x\d+ but the images are .*another aspect"):
        load_scene(project)


def test_a_damaged_colmap_model_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    project = tmp_path / "project"
    (project / "sparse" / "0").mkdir(parents=True)
    (project / "images").mkdir()
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        (project / "sparse" / "0" / name).write_bytes(b"\x01\x00")
    assert "cameras.bin: not a readable COLMAP model file (no record count in 2 bytes" in _fails(
        ["inspect", str(project)], capsys)
    (project / "sparse" / "0" / "cameras.bin").write_bytes((10**9).to_bytes(8, "little") + b"\x00" * 40)
    assert "cameras.bin: not a readable COLMAP model file (1000000000 records in 48 bytes" in _fails(
        ["inspect", str(project)], capsys)
    (project / "sparse" / "0" / "cameras.bin").write_bytes((0).to_bytes(8, "little"))
    (project / "sparse" / "0" / "images.bin").write_bytes((0).to_bytes(8, "little"))
    (project / "sparse" / "0" / "points3D.bin").write_bytes((0).to_bytes(8, "little"))
    assert "sparse/0: the COLMAP model poses no image" in _fails(["inspect", str(project)], capsys)


def test_prepared_copies_keep_the_exif_focal_length_colmap_starts_from(arc, tmp_path: Path) -> None:
    """A phone photo's EXIF gives COLMAP its focal-length prior; a copy resized for SfM must keep it (and say it
    is upright, its pixels being turned already)."""
    import pycolmap

    folder, _ = arc
    photos, prepared = tmp_path / "photos", tmp_path / "prepared"
    photos.mkdir()
    prepared.mkdir()
    exif = Image.Exif()
    exif[0x010F], exif[0x0110], exif[0x0112] = "Phone", "Model 1", 6
    exif.get_ifd(0x8769)[0xA405] = 29  # 35 mm equivalent focal length (the arc was rendered with 0.8 x the width)
    for path in sorted(folder.glob("view_00[0-2].png")):
        stored = np.ascontiguousarray(np.rot90(np.asarray(Image.open(path).convert("RGB")), k=1))
        Image.fromarray(stored).save(photos / f"{path.stem}.jpg", exif=exif.tobytes(), quality=95)
        prepare_photo(photos / f"{path.stem}.jpg", prepared / f"{path.stem}.jpg", (HEIGHT // 2, WIDTH // 2))
    copy = Image.open(prepared / "view_000.jpg").getexif()
    assert copy[0x0112] == 1 and copy[0x0110] == "Model 1" and copy.get_ifd(0x8769)[0xA405] == 29
    pycolmap.extract_features(tmp_path / "db.db", prepared, camera_mode=pycolmap.CameraMode.SINGLE,
                              device=pycolmap.Device.cpu)
    db = pycolmap.Database.open(tmp_path / "db.db")
    try:
        camera = db.read_all_cameras()[0]
    finally:
        db.close()
    diagonal = np.hypot(WIDTH // 2, HEIGHT // 2)  # COLMAP scales the 35 mm figure by the 43.27 mm film diagonal
    assert camera.has_prior_focal_length and camera.params[0] == pytest.approx(29 / np.hypot(36, 24) * diagonal, rel=0.01)


def test_a_phone_that_switched_lenses_gets_a_camera_per_lens(tmp_path: Path) -> None:
    """Every photo's EXIF gives its focal length: one camera per lens (COLMAP's AUTO mode), each posed with its own
    focal length; without EXIF the photos share one camera (AUTO would give each its own)."""
    from nerfmeta.data.sfm import has_exif_focal

    poses = sfm_scenes.ring_poses(12, turn=0.5)
    wide, tele = sfm_scenes.render(poses, 0.7 * WIDTH, HEIGHT, WIDTH), sfm_scenes.render(poses, 1.0 * WIDTH, HEIGHT, WIDTH)
    photos = tmp_path / "photos"
    photos.mkdir()
    for k in range(12):
        lens = "tele" if k % 3 == 2 else "wide"
        exif = Image.Exif()
        exif[0x010F], exif[0x0110] = "Phone", "Model 1"
        exif.get_ifd(0x8769)[0xA405] = 36 if lens == "tele" else 25  # 35 mm equivalents of the two lenses
        Image.fromarray((tele if lens == "tele" else wide)[k]).save(photos / f"view_{k:03d}.jpg", exif=exif.tobytes(),
                                                                     quality=95)
    assert has_exif_focal(photos / "view_000.jpg")
    Image.fromarray(wide[0]).save(tmp_path / "bare.jpg")
    assert not has_exif_focal(tmp_path / "bare.jpg")  # (a folder with such photos keeps one camera for all)
    result = compute_poses(photos, tmp_path / "scene", SfmConfig(threads=1))
    assert len(result.registered) == 12
    scene = load_scene(tmp_path / "scene", normalize=False)
    focal = scene.intrinsics[:, 0] / scene.width
    for k in range(12):
        assert float(focal[k]) == pytest.approx(1.0 if k % 3 == 2 else 0.7, rel=0.02)
    rotation_deg, centre = sfm_scenes.pose_errors(scene.poses.numpy(), poses)
    assert rotation_deg.max() < 1.0
