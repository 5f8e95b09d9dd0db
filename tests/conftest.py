"""Shared pytest fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from nerfmeta.collection.generate import load_collection
from nerfmeta.collection.render import RenderConfig
from nerfmeta.data.synthetic import write_tiny_scene
from pretrain.zoo import ZooRecipe, build_zoo


@pytest.fixture(autouse=True, scope="session")
def one_torch_thread():
    """Every test runs torch on one thread: the tensors are small, and on a shared 2-core machine intra-op
    threads only contend (as the CLI's collection and benchmark workers do)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(autouse=True)
def no_default_zoo(monkeypatch: pytest.MonkeyPatch) -> None:
    """Tests see no model zoo unless they pass one (--zoo DIR): `nerfmeta fit` without --init then fits
    from scratch, whatever model_zoo/ holds. Routing tests build their own tiny zoo."""
    monkeypatch.setenv("NERFMETA_ZOO", "none")


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A Blender-format folder with the tiny analytic spheres scene: 8 train + 4 test views, 32x32 RGBA."""
    return write_tiny_scene(tmp_path_factory.mktemp("tiny_scene") / "spheres")


# --- a real tiny model zoo (classifier, category models, meta-init), built once per session ---------

TINY_MODEL = {"depth": 2, "width": 16, "skips": [], "n_samples": 8, "pos_freqs": 2, "alpha_init": 1e-3, "lr": 1e-2}
TINY_ZOO = ZooRecipe(
    known=("chair", "mug"), unseen=("vase",), scenes_per_category=4, views=4, test_views=2, resolution=16, val_fraction=0.25,
    test_fraction=0.25, render=RenderConfig(supersample=1, max_steps=48), classifier_budget_s=60.0,
    classifier={"input_size": 16, "batch_size": 8, "epochs": 2, "stats_views": 4}, model=TINY_MODEL, downscale=1.0, batch_rays=64,
    category_iters=10, meta_steps=2, meta={"meta_batch": 2, "support_rays": 32, "query_rays": 32, "inner_steps": 1, "eval_tasks": 1},
    fit_iters=6, fit_eval_every=3, freeze=1,
    occupancy_resolutions=(16,), occupancy_scenes_per_category=1, occupancy_views=4, occupancy={"steps": 4, "width": 2},
)


@pytest.fixture(scope="session")
def zoo_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("zoo")
    build_zoo(TINY_ZOO, root / "zoo", root / "work", threads=1)
    return root / "zoo"


@pytest.fixture(scope="session")
def new_scenes(zoo_dir: Path) -> dict[str, Path]:
    """The zoo collection's test scenes (never used to build the zoo): one known (chair), one unseen (vase)."""
    coll = load_collection(zoo_dir.parent / "work" / "collection")
    tests = {r.category: coll.scene_path(r) for r in coll.scenes if r.split == "test"}
    return {"known": tests["chair"], "unseen": tests["vase"]}
