"""The example backbone of docs/new_field.md: the page shows the file as it is, and the file fits."""

import re
from pathlib import Path

import torch

from nerfmeta.data import load_scene
from nerfmeta.fields.base import check_partition
from nerfmeta.fields.dense_grid import DenseGrid, DenseGridConfig
from nerfmeta.fields.registry import BACKBONES, build_model, model_class
from nerfmeta.fit.evaluate import evaluate_views
from nerfmeta.fit.loop import FitConfig, fit

ROOT = Path(__file__).resolve().parents[1]


def test_docs_show_the_example_field_and_its_registry_line_verbatim():
    page = (ROOT / "docs" / "new_field.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", page, flags=re.S)
    source = (ROOT / "nerfmeta" / "fields" / "dense_grid.py").read_text()
    assert blocks[0] == source
    registry = (ROOT / "nerfmeta" / "fields" / "registry.py").read_text()
    assert blocks[1].strip() in registry and model_class("dense") is DenseGrid
    assert len(source.splitlines()) <= 60  # small enough to read as an example


def test_the_example_field_fits_the_tiny_scene(tiny_scene):
    scene = load_scene(tiny_scene)
    model = build_model("dense", DenseGridConfig(side=20), scene.bounds, seed=0)
    check_partition(model)
    white = torch.ones(3)
    before = evaluate_views(model, scene, list(scene.splits["test"]), white, with_ssim=False).psnr
    result = fit(model, scene, FitConfig(iters=150, batch_rays=512, eval_every=0, final_ssim=False), background=white)
    assert result.final.psnr > before + 6.0, (before, result.final.psnr)
    assert set(BACKBONES) >= {"grid", "nerf", "dense"}
