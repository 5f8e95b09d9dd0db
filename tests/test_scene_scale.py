"""Forward-facing and unbounded captures in other units (poses in millimetres or kilometres) fit as in metres.

Object scenes have their rows in the stress table (BENCHMARKS.md, *Stress cases*); these two kinds of scene go
through other spaces (NDC rays, a contracted space round an inner box from the cameras), so they are checked here.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from nerfmeta.collection.forward import ForwardSceneConfig, make_forward_scene
from nerfmeta.collection.unbounded import UnboundedSceneConfig, make_unbounded_scene
from nerfmeta.fit.loop import FitConfig
from nerfmeta.fit.run import RunConfig, run_fit

MAKERS = {
    "forward": lambda folder: make_forward_scene(folder, ForwardSceneConfig(width=24, height=18, grid=(3, 3), supersample=1)),
    "unbounded": lambda folder: make_unbounded_scene(folder, UnboundedSceneConfig(width=24, height=18, views=9, supersample=1)),
}


def scaled_copy(scene, out, factor: float):
    """The LLFF scene ``scene`` with its camera centres and near/far bounds multiplied by ``factor``."""
    out.mkdir()
    shutil.copytree(scene / "images", out / "images")
    rows = np.load(scene / "poses_bounds.npy")
    matrices = rows[:, :15].reshape(-1, 3, 5).copy()
    matrices[:, :, 3] *= factor
    scaled = np.concatenate([matrices.reshape(-1, 15), rows[:, 15:] * factor], axis=1)
    np.save(out / "poses_bounds.npy", scaled)
    return out


def fit_psnr(scene, out) -> tuple[float, str]:
    config = RunConfig(scene=str(scene), renders=0, model={"coarse_iters": 10, "growth_steps": [10]},
                       fit=FitConfig(iters=30, batch_rays=256, eval_every=0, checkpoint_every=0, final_ssim=False,
                                     final_lpips=False))
    summary = run_fit(config, out)
    return summary["test_psnr"], summary["scene_type"]["kind"]


@pytest.mark.parametrize("kind", sorted(MAKERS))
def test_a_capture_in_other_units_fits_as_in_its_own(kind, tmp_path):
    scene = MAKERS[kind](tmp_path / "scene")
    reference, detected = fit_psnr(scene, tmp_path / "run")
    assert detected == kind
    for factor in (1e-3, 1e3):
        copy = scaled_copy(scene, tmp_path / f"x{factor:g}", factor)
        psnr, detected = fit_psnr(copy, tmp_path / f"run_x{factor:g}")
        assert detected == kind
        assert psnr == pytest.approx(reference, abs=0.05), f"poses x {factor:g}"
