"""Hostile input files (issue 15): each case is a real CLI call that must end in a complete run or in
one line on stderr with exit code 2, never a traceback after work was done or a silently wrong result."""

from __future__ import annotations

import dataclasses
import errno
import hashlib
import io
import json
import re
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.lib import format as npy_format
import torch

from nerfmeta.cli import main
from nerfmeta.data import load_scene
from nerfmeta.data import common
from nerfmeta.data.arrays import npz_headers
from nerfmeta.data.bounds import default_near_far
from nerfmeta.data.synthetic import tiny_cameras, write_tiny_scene
from nerfmeta.errors import ConfigError, SceneError
from nerfmeta.fields.registry import build_model, config_from_dict
from nerfmeta.init import load_init, save_init
from nerfmeta.fit.run import RunConfig, run_fit
from nerfmeta.render.cameras import fibonacci_directions, look_at
from benchlib.stress import MAX_PSNR_GAP, QUICK, transform_blender_scene
from nerfmeta.zoo import ZOO_FORMAT, load_zoo
from fuzz_scenes import KINDS as FUZZ_KINDS, fuzz, llff_rows


def one_line_error(capsys: pytest.CaptureFixture[str], code: int, command: str) -> str:
    """The single stderr line of a refused command (exit 2, no traceback)."""
    err = capsys.readouterr().err
    lines = err.rstrip("\n").split("\n")
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith(f"nerfmeta {command}: error: "), err
    assert "Traceback" not in err
    return lines[0]


# --- images too small for a metric ----------------------------------------------------------------


@pytest.mark.parametrize(("size", "extra"), [(8, []), (32, ["--downscale", "4"]), (32, ["--downscale", "64"])])
def test_images_smaller_than_the_ssim_window_fit_and_record_why_ssim_is_missing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], size: int, extra: list[str]
) -> None:
    scene = write_tiny_scene(tmp_path / "small", n_train=2, n_test=1, size=size)
    out = tmp_path / "run"
    code = main(["fit", str(scene), "--out", str(out), "--init", "scratch", "--iters", "2", *extra])
    assert code == 0, capsys.readouterr().err
    summary: dict[str, Any] = json.loads((out / "summary.json").read_text())
    assert summary["test_ssim"] is None
    decision = summary["decisions"]["final_ssim"]
    assert decision["value"] is False and "smaller than its 11x11 window" in decision["reason"]
    assert (out / "checkpoint.safetensors").is_file()


# --- size bombs in containers ----------------------------------------------------------------------


def npy_bytes(shape: tuple[int, ...], dtype: str, data: bytes = b"") -> bytes:
    """A .npy file whose header declares ``shape`` followed by ``data`` (as many bytes as we like)."""
    buf = io.BytesIO()
    npy_format.write_array_header_1_0(buf, {"descr": np.dtype(dtype).str, "fortran_order": False, "shape": shape})
    return buf.getvalue() + data


def write_npz(path: Path, members: dict[str, bytes], compression: int = zipfile.ZIP_DEFLATED) -> Path:
    with zipfile.ZipFile(path, "w", compression) as archive:
        for name, data in members.items():
            archive.writestr(f"{name}.npy", data)
    return path


def tiny_npz_members(images: tuple[int, ...] = (2, 4, 4, 3), n_poses: int = 2) -> dict[str, bytes]:
    pixels = np.zeros(images, np.uint8)
    poses = np.broadcast_to(np.eye(4), (n_poses, 4, 4)).copy()
    poses[:, 2, 3] = 4.0
    return {"images": npy_bytes(images, "u1", pixels.tobytes()), "poses": npy_bytes(poses.shape, "<f8", poses.tobytes()),
            "focal": npy_bytes((), "<f8", np.float64(5.0).tobytes())}


@pytest.mark.parametrize(
    ("members", "message"),
    [
        ({"images": npy_bytes((1, 60000, 60000, 3), "u1", b"\0" * 64)}, "declares shape (1, 60000, 60000, 3)"),
        ({"images": npy_bytes((1, 9000, 9000, 3), "u1", b"\0" * 64)}, "the file is truncated or forged"),
        ({"poses": npy_bytes((10**9, 4, 4), "<f8", b"\0" * 64)}, "poses: header declares shape (1000000000, 4, 4)"),
        ({"images": npy_bytes((2, 4, 4, 3), "|O", b"\0" * 64)}, "holds Python objects"),
        ({"images": b"not an npy header"}, "images: cannot read as a .npy array (bad header"),
        ({"images": npy_bytes((2, 4, 4), "u1", b"\0" * 32)}, "images must be (N, H, W, 3)"),
        ({"poses": npy_bytes((3, 4, 4), "<f8", b"\0" * 384)}, "poses must be (N, 4, 4) with N = 2"),
    ],
)
def test_npz_declared_shapes_are_checked_before_reading(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], members: dict[str, bytes], message: str
) -> None:
    path = write_npz(tmp_path / "scene.npz", {**tiny_npz_members(), **members})
    line = one_line_error(capsys, main(["inspect", str(path)]), "inspect")
    assert "scene.npz" in line and message in line


def test_npz_pixel_limit_applies_to_the_declared_size_without_reading(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = write_npz(tmp_path / "scene.npz", tiny_npz_members((2, 16, 16, 3)))
    assert load_scene(path).height == 16

    def no_read(*args: object, **kwargs: object) -> None:
        raise AssertionError("arrays read before the declared sizes were checked")

    monkeypatch.setattr(np, "load", no_read)
    with pytest.raises(SceneError, match=r"scene\.npz: images: image is 16x16 .* over the limit"):
        load_scene(path, max_pixels=255)


def test_npz_headers_give_declared_shapes_and_sizes(tmp_path: Path) -> None:
    members = tiny_npz_members()
    path = write_npz(tmp_path / "scene.npz", members)
    headers = npz_headers(path)
    assert headers["images"].shape == (2, 4, 4, 3) and headers["images"].data_bytes == 96
    assert headers["focal"].shape == () and headers["poses"].dtype == np.float64


def test_llff_poses_bounds_header_is_checked_before_reading(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "llff"
    (folder / "images").mkdir(parents=True)
    (folder / "poses_bounds.npy").write_bytes(npy_bytes((10**9, 17), "<f8", b"\0" * 136))
    line = one_line_error(capsys, main(["inspect", str(folder)]), "inspect")
    assert "poses_bounds.npy: header declares shape (1000000000, 17)" in line
    (folder / "poses_bounds.npy").write_bytes(npy_bytes((2, 5), "<f8", b"\0" * 80))
    line = one_line_error(capsys, main(["inspect", str(folder)]), "inspect")
    assert "poses_bounds.npy: expected an (N, 17) array, got shape (2, 5)" in line



# --- extreme numbers in scene files -----------------------------------------------------------------


def edited_tiny_scene(folder: Path, edit: Any = None, frame_edit: Any = None, to_nerfstudio: bool = False) -> Path:
    """The 8 px tiny scene with its JSON documents edited in place (``edit(doc)``, ``frame_edit(frame)``);
    ``to_nerfstudio`` rewrites the training split as a nerfstudio ``transforms.json``."""
    scene = write_tiny_scene(folder, n_train=4, n_test=1, size=8)
    for file in sorted(scene.glob("transforms_*.json")):
        doc = json.loads(file.read_text())
        if edit is not None:
            edit(doc)
        for frame in doc["frames"]:
            if frame_edit is not None:
                frame_edit(frame)
        if to_nerfstudio:
            file.unlink()
            if file.name == "transforms_train.json":
                (scene / "transforms.json").write_text(json.dumps(doc))
        else:
            file.write_text(json.dumps(doc))
    return scene


def shift_x(amount: float) -> Any:
    def edit(frame: dict[str, Any]) -> None:
        frame["transform_matrix"][0][3] += amount

    return edit


@pytest.mark.filterwarnings("error")  # a numpy overflow warning would print extra lines on stderr
@pytest.mark.parametrize(
    ("edit", "frame_edit", "to_nerfstudio", "message"),
    [
        (lambda d: d.update(far=1e300), None, False, "far 1e+300 is outside"),
        (lambda d: d.update(near=1e-301, far=1e-300), None, False, "far 1e-300 is outside"),
        (lambda d: d.update(near=1e-7, far=6.0), None, False, "far / near is 6e+07"),
        (lambda d: d.update(near=1e-7, far=1e-6), None, False, "cameras are spread over"),
        (lambda d: d.update(camera_angle_x=1e-300), None, False, "focal fx 8e+300 px is not between"),
        (lambda d: d.update(aabb=[[-1e300] * 3, [1e300] * 3]), None, False, "aabb of size 2e+300 is out of proportion"),
        (lambda d: d.update(aabb=[[0.0] * 3, [1e-300] * 3]), None, False, "aabb of size 1e-300 is out of proportion"),
        (lambda d: d.update(aabb=[[100.0] * 3, [101.0] * 3]), None, False, "aabb is 1"),
        (None, shift_x(1e300), False, "a camera stands 1e+300 from the origin"),
        (None, lambda f: f["transform_matrix"][0].__setitem__(0, 1e300), False, "rotation entry 1e+300 outside [-1, 1]"),
        (lambda d: d.pop("aabb"), shift_x(1e30), False, "a camera stands 1e+30 from the origin"),
        (lambda d: d.update(cx=1e30), None, True, "principal point cx 1e+30 px"),
        (lambda d: d.update(fl_x=1e-300), None, True, "focal fx 1e-300 px"),
        (lambda d: d.update(fl_y=1e300), None, True, "focal fy 1e+300 px"),
    ],
)
def test_extreme_numbers_are_refused_naming_the_file_and_value(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], edit: Any, frame_edit: Any, to_nerfstudio: bool, message: str
) -> None:
    scene = edited_tiny_scene(tmp_path / "s", edit, frame_edit, to_nerfstudio)
    line = one_line_error(capsys, main(["inspect", str(scene)]), "inspect")
    assert ("transforms.json" if to_nerfstudio else "transforms_train.json") in line and message in line


@pytest.mark.filterwarnings("error")  # a numpy overflow warning would print extra lines on stderr
def test_extreme_npz_focal_and_llff_depths_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    members = {**tiny_npz_members(), "focal": npy_bytes((), "<f8", np.float64(1e300).tobytes())}
    line = one_line_error(capsys, main(["inspect", str(write_npz(tmp_path / "f.npz", members))]), "inspect")
    assert "f.npz: view 0: focal fx 1e+300 px" in line
    poses, intrinsics = tiny_cameras(4, 0.5, 8)
    far_away = poses.numpy().copy()
    far_away[1, 0, 3] = 1e300  # squared in the near/far guess: an overflow warning on stderr before
    np.savez(tmp_path / "p.npz", images=np.zeros((4, 8, 8, 3), np.uint8), poses=far_away, focal=float(intrinsics[0]))
    line = one_line_error(capsys, main(["inspect", str(tmp_path / "p.npz")]), "inspect")
    assert "p.npz: the cameras are spread over" in line
    np.savez(tmp_path / "i.npz", images=np.full((4, 8, 8, 3), 1e300), poses=poses.numpy(), focal=float(intrinsics[0]))
    line = one_line_error(capsys, main(["inspect", str(tmp_path / "i.npz")]), "inspect")
    assert "i.npz: images[0]: float pixel values must be finite and within [0, 1]" in line
    folder = tmp_path / "llff"
    rows = llff_rows(folder, 2)
    rows[:, 15:] = [1e-300, 2e-300]
    np.save(folder / "poses_bounds.npy", rows)
    line = one_line_error(capsys, main(["inspect", str(folder)]), "inspect")
    assert "poses_bounds.npy: far 2.2e-300 is outside" in line
    rows[:, 15:] = [1.0, 5.0]
    rows[0, 4] = 1e-320  # a subnormal image height: 4 / 1e-320 overflowed with a numpy warning on stderr
    np.save(folder / "poses_bounds.npy", rows)
    line = one_line_error(capsys, main(["inspect", str(folder)]), "inspect")
    assert "poses_bounds.npy: image height and width (column 5) must be between 1 and 1e+06 pixels" in line


def test_scenes_in_range_still_load(tmp_path: Path) -> None:
    assert load_scene(edited_tiny_scene(tmp_path / "a", lambda d: d.update(near=0.0, far=6.0))).far == 6.0
    scene = load_scene(edited_tiny_scene(tmp_path / "b", lambda d: d.update(cx=7.9, fl_x=0.5), to_nerfstudio=True))
    assert scene.intrinsics[0, 2] == pytest.approx(7.9)


# --- scenes at another scale without near/far in the file ---------------------------------------------


def as_people_write_it(src: Path, dst: Path, scale: float, offset: tuple[float, float, float]) -> Path:
    """The Blender scene ``src`` moved by ``x -> scale * x + offset``, without nerfmeta's optional
    ``near``, ``far``, ``aabb`` and ``category`` keys (a plain NeRF-synthetic-style file)."""
    transform_blender_scene(src, dst, scale=scale, offset=offset)
    for file in dst.glob("transforms_*.json"):
        doc = {k: v for k, v in json.loads(file.read_text()).items() if k not in ("near", "far", "aabb", "category")}
        file.write_text(json.dumps(doc))
    return dst


def test_near_far_without_file_values_keep_the_synthetic_default_at_its_scale() -> None:
    lego_like = look_at(4.0311 * fibonacci_directions(20), torch.zeros(3, dtype=torch.float64),
                        torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)).numpy()
    near, far, source = default_near_far(lego_like)
    assert (near, far) == (2.0, 6.0) and "NeRF-synthetic default" in source
    for scale in (1e-3, 1e3):
        moved = lego_like.copy()
        moved[:, :3, 3] = scale * moved[:, :3, 3] + np.array([5000.0, -3000.0, 200.0]) * (scale > 1)
        near, far, source = default_near_far(moved)
        assert near == pytest.approx(0.5 * 4.0311 * scale, rel=1e-6) and far == pytest.approx(1.5 * 4.0311 * scale, rel=1e-6)
        assert source.startswith("derived from the cameras")


def test_inspect_says_where_near_far_came_from(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    scene = as_people_write_it(write_tiny_scene(tmp_path / "s", n_train=4, n_test=1, size=8), tmp_path / "small", 1e-3, (0, 0, 0))
    assert main(["inspect", str(scene)]) == 0
    out = capsys.readouterr().out
    assert "near / far       2 / 6 (derived from the cameras" in out and "scale 1000, offset [0, 0, 0]" in out


def test_scenes_without_near_far_fit_alike_at_every_scale(tmp_path: Path) -> None:
    """Issue 15: at scale 1e-3 (cameras 0.004 from a 0.002-unit object) the synthetic default 2/6 fitted at
    9.2 dB against 37.0 dB for the same scene at scale 1; 1e3 and moved by (5000, -3000, 200): 10.1 dB."""
    base = write_tiny_scene(tmp_path / "base", n_train=QUICK.n_train, n_test=QUICK.n_test, size=QUICK.size)
    fit = dataclasses.replace(QUICK.fit, iters=100)
    psnr = {}
    for name, scale, offset in (("unit", 1.0, (0.0, 0.0, 0.0)), ("milli", 1e-3, (0.0, 0.0, 0.0)),
                                ("kilo", 1e3, (5000.0, -3000.0, 200.0))):
        scene = as_people_write_it(base, tmp_path / name, scale, offset)
        config = RunConfig(scene=str(scene), backbone="grid", model=dict(QUICK.models["grid"]), fit=fit)
        psnr[name] = run_fit(config, tmp_path / f"run_{name}")["test_psnr"]
    assert psnr["unit"] > 15.0, psnr
    assert abs(psnr["milli"] - psnr["unit"]) <= MAX_PSNR_GAP and abs(psnr["kilo"] - psnr["unit"]) <= MAX_PSNR_GAP, psnr


# --- manifests: zoo and init.json -------------------------------------------------------------------------


def fake_zoo(root: Path, fit: dict[str, Any] | None = None, **entry: Any) -> Path:
    """A zoo folder with one 'meta' entry listing ``meta/init.json`` (hash right); ``entry`` overrides its fields."""
    (root / "meta").mkdir(parents=True, exist_ok=True)
    (root / "meta" / "init.json").write_text("{}")
    raw = {"name": "meta", "kind": "meta", "path": "meta", "files": {"init.json": hashlib.sha256(b"{}").hexdigest()},
           "bytes": 2, **entry}
    (root / "manifest.json").write_text(json.dumps({"format": ZOO_FORMAT, "fit": fit or {"backbone": "grid"}, "entries": [raw]}))
    return root


def test_fake_zoo_loads(tmp_path: Path) -> None:
    zoo = load_zoo(fake_zoo(tmp_path / "zoo"))
    assert zoo.meta is not None and zoo.meta.path == (tmp_path / "zoo" / "meta").resolve() and zoo.backbone == "grid"


@pytest.mark.parametrize(
    ("fit", "message"),
    [
        ({"backbone": "grid", "batch_rays": "abc"}, "fit.batch_rays must be an integer, got 'abc'"),
        ({"backbone": "grid", "iters": 1e12}, "fit.iters must be an integer, got 1000000000000.0"),
        ({"backbone": "grid", "iters": 0}, "fit.iters must be between 1 and 10000000, got 0"),
        ({"backbone": "grid", "freeze": True}, "fit.freeze must be an integer, got True"),
        ({"backbone": 7}, "fit.backbone must be a non-empty string, got 7"),
        ({"backbone": "resnet"}, "fit.backbone is 'resnet', expected one of"),
        ({"backbone": "grid", "model": "x"}, "fit.model must be a JSON object, got str"),
        ({"backbone": "grid", "model": {"no_such_field": 1}}, "fit.model: grid config has unknown keys ['no_such_field']"),
    ],
)
def test_untyped_zoo_fit_settings_are_one_line_errors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], fit: dict[str, Any], message: str
) -> None:
    zoo = fake_zoo(tmp_path / "zoo", fit)
    scene = write_tiny_scene(tmp_path / "s", n_train=2, n_test=1, size=8)
    line = one_line_error(capsys, main(["fit", str(scene), "--out", str(tmp_path / "run"), "--zoo", str(zoo), "--iters", "2"]), "fit")
    assert "manifest.json" in line and message in line
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    ("entry", "message"),
    [
        ({"path": "../outside"}, "path '../outside' leads out of"),
        ({"path": "/etc"}, "path '/etc' is absolute"),
        ({"path": "link"}, "path 'link' leads out of"),
        ({"files": {"../../manifest.json": "0" * 64}}, "file: path '../../manifest.json' leads out of"),
        ({"files": {"/etc/passwd": "0" * 64}}, "path '/etc/passwd' is absolute"),
        ({"files": ["init.json"]}, "files must be a JSON object, got list"),
        ({"kind": "other"}, "kind is 'other', expected one of classifier, category, meta"),
        ({"kind": "category"}, "category must be a non-empty string, got None"),
        ({"name": 3}, "entries[0].name must be a non-empty string, got 3"),
        ({"config": []}, "config must be a JSON object, got list"),
    ],
)
def test_zoo_entries_are_typed_and_stay_inside_the_zoo(tmp_path: Path, entry: dict[str, Any], message: str) -> None:
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "init.json").write_text("{}")
    root = fake_zoo(tmp_path / "zoo", **entry)
    (root / "link").symlink_to(outside, target_is_directory=True)
    with pytest.raises(ConfigError, match=re.escape(message)) as err:
        load_zoo(root, verify="files" not in entry)
    assert "\n" not in str(err.value)


@pytest.fixture
def saved_init(tmp_path: Path) -> Path:
    model = build_model("nerf", config_from_dict("nerf", {"depth": 2, "width": 8, "skips": [], "n_samples": 4, "pos_freqs": 2}),
                        torch.tensor([[-1.0] * 3, [1.0] * 3]), seed=0)
    return save_init(tmp_path / "init", model, "meta", {"steps": 1})


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d.pop("backbone"), "backbone must be a non-empty string, got None"),
        (lambda d: d.update(backbone="resnet"), "backbone is 'resnet', expected one of"),
        (lambda d: d.update(kind=5), "kind must be a non-empty string, got 5"),
        (lambda d: d.update(model_config="abc"), "model_config must be a JSON object, got str"),
        (lambda d: d.update(model_config={"width": "abc"}), "model_config is not a valid nerf configuration"),
        (lambda d: d.update(structure=[1, 2]), "structure must be a JSON object, got list"),
        (lambda d: d.update(meta="x"), "meta must be a JSON object, got str"),
        (lambda d: d["model_config"].update(width=16), "weights do not fit a nerf model"),
    ],
)
def test_init_json_fields_are_typed(saved_init: Path, edit: Any, message: str) -> None:
    doc = json.loads((saved_init / "init.json").read_text())
    edit(doc)
    (saved_init / "init.json").write_text(json.dumps(doc))
    with pytest.raises(ConfigError, match=re.escape(message)) as err:
        load_init(saved_init).build()
    assert "\n" not in str(err.value)


def test_npz_scene_at_another_scale_gets_near_far_from_its_cameras(tmp_path: Path) -> None:
    poses, intrinsics = tiny_cameras(8, 0.5, 8)
    for scale, expected in ((1.0, (2.0, 6.0)), (1e-3, None)):
        moved = poses.clone()
        moved[:, :3, 3] *= scale
        path = tmp_path / f"scene_{scale}.npz"
        np.savez(path, images=np.zeros((8, 8, 8, 3), np.uint8), poses=moved.numpy(), focal=float(intrinsics[0]))
        scene = load_scene(path, normalize=False)
        if expected is not None:
            assert (scene.near, scene.far) == expected and "NeRF-synthetic default" in scene.near_far_source
        else:
            assert scene.near == pytest.approx(0.002, rel=1e-3) and scene.far == pytest.approx(0.006, rel=1e-3)
            assert scene.near_far_source.startswith("derived from the cameras")


# --- scene JSON that is too big or too deep -----------------------------------------------------------------


def test_scene_json_too_large_or_too_deep_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    scene = write_tiny_scene(tmp_path / "s", n_train=2, n_test=1, size=8)
    (scene / "transforms_train.json").write_text("[" * 200_000 + "]" * 200_000)
    line = one_line_error(capsys, main(["inspect", str(scene)]), "inspect")
    assert "transforms_train.json: JSON nested too deeply" in line
    with open(scene / "transforms_train.json", "wb") as f:
        f.truncate(300 << 20)  # sparse: no disk used
    line = one_line_error(capsys, main(["inspect", str(scene)]), "inspect")
    assert "transforms_train.json: 300 MiB is too large for a scene file" in line


# --- output folders that cannot be written (inspect --out) --------------------------------------------------


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda t: (t / "afile").write_text("x") and t / "afile" / "sub", "cannot be created because"),
        (lambda t: (t / "dangling").symlink_to(t / "nowhere") or t / "dangling", "is a symbolic link to a missing target"),
        (lambda t: (t / "gone").symlink_to(t / "nowhere") or t / "gone" / "sub", "gone is a symbolic link to a missing target"),
    ],
)
def test_inspect_out_that_cannot_be_a_folder_is_refused_before_loading(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], make: Any, message: str
) -> None:
    scene = write_tiny_scene(tmp_path / "s", n_train=2, n_test=1, size=8)
    out = make(tmp_path)
    before = sorted(p.name for p in tmp_path.iterdir())
    line = one_line_error(capsys, main(["inspect", str(scene), "--out", str(out)]), "inspect")
    assert f"--out {out}" in line and message in line
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_inspect_out_on_a_full_disk_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    scene = write_tiny_scene(tmp_path / "s", n_train=2, n_test=1, size=8)

    def full(self: Path, data: bytes) -> int:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Path, "write_bytes", full)
    line = one_line_error(capsys, main(["inspect", str(scene), "--out", str(tmp_path / "out")]), "inspect")
    assert "cannot write (No space left on device)" in line
    assert not (tmp_path / "out" / "inspect.json").exists()


@pytest.mark.parametrize("inside", ["", "sub"])
def test_inspect_out_is_never_the_scene_or_inside_it(tmp_path: Path, capsys: pytest.CaptureFixture[str], inside: str) -> None:
    scene = write_tiny_scene(tmp_path / "s", n_train=2, n_test=1, size=8)
    before = sorted(p.relative_to(scene) for p in scene.rglob("*"))
    line = one_line_error(capsys, main(["inspect", str(scene), "--out", str(scene / inside)]), "inspect")
    assert "is the input" in line and "write elsewhere" in line
    assert sorted(p.relative_to(scene) for p in scene.rglob("*")) == before


def test_views_that_would_not_fit_in_memory_are_refused_before_decoding(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A small transforms.json can list one image thousands of times: the stack is estimated from the headers first."""
    scene = edited_tiny_scene(tmp_path / "s", lambda d: d.update(frames=d["frames"][:1] * 2000))
    monkeypatch.setattr(common, "memory_limit_bytes", lambda: 1 << 20)
    line = one_line_error(capsys, main(["inspect", str(scene)]), "inspect")
    assert "4000 views of 8x8 need 4 MiB loaded, more than this machine's 1 MiB" in line
    path = write_npz(tmp_path / "s.npz", tiny_npz_members((2, 16, 16, 3)))
    monkeypatch.setattr(common, "memory_limit_bytes", lambda: 1000)
    line = one_line_error(capsys, main(["inspect", str(path)]), "inspect")
    assert "s.npz: images: 2 views of 16x16 need" in line


# --- seeded fuzzing: hostile scene files the tests above did not think of -----------------------------------


@pytest.mark.parametrize("kind", FUZZ_KINDS)
def test_fuzzed_scenes_load_or_are_refused_in_one_line(tmp_path: Path, kind: str) -> None:
    broken = [o for o in fuzz(kind, 12, tmp_path) if o.broken]
    assert not broken, broken[:3]
