"""The README's main job: classify-and-fit two new scenes against the best scratch fit.

It generates two objects the zoo was never trained on (seeds the zoo build does not use): one of
a category the zoo knows (a chair) and one of a category it has never seen (a vase). Each goes
through ``nerfmeta fit SCENE --init auto --backbone ZOO_BACKBONE --compare scratch,scratch-nerf``
(the zoo's backbone is named so that its priors are used; a plain ``nerfmeta fit`` with the
shipped NeRF-MLP zoo fits the grid, from scratch at the demo's 32 px and from the learned occupancy start on object
views of 96-192 px, :func:`nerfmeta.route.occupancy_route`): the zoo's classifier names its category or says
"unknown", the fit starts from that category's model or from the meta-learned initialisation
where it applies, and beside it run the *fair* baseline ``scratch``, the voxel grid from scratch
with its tuned defaults given the routed fit's whole wall-clock time, and the second baseline
``scratch-nerf``, the same MLP from scratch with the routed fit's settings. The headline compares
the routed fit with the scratch grid on the wall-clock axis (classification and loading
included), and says so when the routed fit is behind. Each object is also fitted as a plain ``nerfmeta fit SCENE
--compare scratch`` fits it (``NAME_grid``): the voxel grid on the full-size views (96 px by default), by its default
route, the learned occupancy start (:func:`nerfmeta.route.occupancy_route`), against the scratch grid. Then
``nerfmeta report`` gathers every run into one report. Everything is made by the project itself, so it needs no data
from outside.

Without a zoo (``--zoo none``) the routed fits are scratch grid fits and there is nothing to compare.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

from nerfmeta.collection.generate import CollectionConfig, generate_collection, load_collection
from nerfmeta.config import bounded
from nerfmeta.fit.loop import Callback, FitConfig
from nerfmeta.fit.run import RunConfig
from nerfmeta.report.aggregate import write_report
from nerfmeta.report.snapshots import SNAPSHOT_ITERS
from nerfmeta.route import Route, classify_and_fit
from nerfmeta.runfolder import relocated, run_folder
from nerfmeta.zoo import Zoo


@dataclass(frozen=True)
class DemoConfig:
    """Settings of the demo."""

    known_category: str = "chair"
    """Category of the first object (one the shipped zoo has a model for)."""
    unseen_category: str = "vase"
    """Category of the second object (one the shipped zoo has never seen)."""
    resolution: int = 96
    """Image size of the generated views (what the classifier reads, and what the plain grid fits read)."""
    downscale: float = bounded(3.0, low=1)
    """The fits of the zoo's backbone read the views reduced by this factor (32 x 32 by default, as the zoo's models
    were trained)."""
    views: int = bounded(16, low=1)
    """Training views per object."""
    test_views: int = bounded(8, low=1)
    """Test views per object (other directions than the training views)."""
    iters: int | None = bounded(None, low=1)
    """Iterations of each fit (None: the zoo's)."""
    eval_every: int | None = bounded(50, low=0)
    """Test PSNR every this many iterations (None: the zoo's)."""
    eval_views: int = bounded(2, low=0)
    """Test views scored at the intermediate evaluations (the final one scores all; 0: all): evaluations are not
    counted in the fits' time, but they are in the demo's."""
    seed: int = 1000
    """Seed of the objects (the zoo is built from seed 0) and of the fits."""
    compare: tuple[str, ...] = ("scratch", "scratch-nerf")
    """Baselines fitted beside each routed fit (``scratch``: the tuned voxel grid, the headline's; ``scratch-nerf``:
    the MLP from scratch with the routed fit's settings)."""
    grid_iters: int = bounded(1000, low=0)
    """Iterations of each object's plain grid fit (what ``nerfmeta fit SCENE --compare scratch`` does: the voxel grid
    on the full-size views, by its default route, beside the scratch grid); 0: none."""
    grid_eval_every: int = bounded(25, low=1)
    """Test PSNR every this many iterations of the plain grid fits."""


@dataclass(frozen=True)
class DemoResult:
    scenes: dict[str, Path]
    runs: dict[str, Path]
    summaries: dict[str, dict[str, Any]]
    report: Path | None
    out: Path


def demo_collection(config: DemoConfig) -> CollectionConfig:
    return CollectionConfig(
        categories=(config.known_category, config.unseen_category), scenes_per_category=1, views=config.views,
        test_views=config.test_views, resolution=config.resolution, seed=config.seed, val_fraction=0.0, test_fraction=0.0,
    )


def run_demo(
    config: DemoConfig,
    out: str | Path,
    *,
    zoo: Zoo | None,
    overwrite: bool = False,
    callbacks_for: Callable[[str, str, FitConfig], Sequence[Callback]] = lambda run, fit, config: (),
    on_route: Callable[[str, Route], None] | None = None,
) -> DemoResult:
    """Generate the two scenes into ``out/scenes``, classify-and-fit each into ``out/NAME`` (the zoo's backbone) and
    (``config.grid_iters``) ``out/NAME_grid`` (a plain grid fit), report into ``out/report``.

    ``callbacks_for(run, fit, fit_config)`` gives the callbacks of the fit ``fit`` (``routed`` or a baseline's name)
    of the run ``run`` (a key of :attr:`DemoResult.runs`).

    The demo folder follows :mod:`nerfmeta.runfolder`'s rules: it is built aside and swapped in when
    complete, and ``overwrite`` replaces only a demo folder of ours.
    """
    out = Path(out)
    with run_folder(out, "demo", overwrite=overwrite, aside=True) as run:
        built = run.dir
        result = _demo_into(built, config, zoo=zoo, callbacks_for=callbacks_for, on_route=on_route)
    return _moved(result, built, run.path)


def _moved(result: DemoResult, built: Path, out: Path) -> DemoResult:
    """``result`` with the paths under the folder it was built in (``built``) moved to ``out``."""
    def move(p: Path) -> Path:
        return out / p.relative_to(built)

    return DemoResult({k: move(v) for k, v in result.scenes.items()}, {k: move(v) for k, v in result.runs.items()},
                      relocated(result.summaries, str(built), str(out)),
                      None if result.report is None else move(result.report), out)


def _demo_into(out: Path, config: DemoConfig, *, zoo: Zoo | None,
               callbacks_for: Callable[[str, str, FitConfig], Sequence[Callback]],
               on_route: Callable[[str, Route], None] | None) -> DemoResult:
    """:func:`run_demo` in the open folder ``out``."""
    coll = load_collection(generate_collection(demo_collection(config), out / "scenes"))
    zoo_fit = zoo.fit if zoo is not None else {}
    defaults = FitConfig()
    fit = FitConfig(iters=config.iters or zoo_fit.get("iters", 300), batch_rays=zoo_fit.get("batch_rays", defaults.batch_rays),
                    eval_every=config.eval_every or zoo_fit.get("eval_every", 25), checkpoint_every=0, seed=config.seed,
                    eval_views=config.eval_views)
    backbone = zoo.backbone if zoo is not None else "grid"
    model = dict(zoo_fit.get("model", {})) if zoo is not None else {}
    grid_fit = FitConfig(iters=config.grid_iters, eval_every=config.grid_eval_every, checkpoint_every=0, seed=config.seed,
                         eval_views=config.eval_views)
    scenes, runs, summaries = {}, {}, {}
    for record in coll.scenes:
        name = record.name
        scene_path = coll.scene_path(record)
        scenes[name] = scene_path
        run = RunConfig(scene=str(scene_path), backbone=backbone, model=model, fit=fit, downscale=config.downscale)
        run = dataclasses.replace(run, snapshot_iters=tuple(i for i in SNAPSHOT_ITERS if i <= fit.iters) if zoo else ())
        jobs = [(name, run, config.compare if zoo is not None else ())]
        if config.grid_iters and zoo is not None and backbone != "grid":  # the plain fit: the grid, full size, its route
            jobs.append((f"{name}_grid", RunConfig(scene=str(scene_path), backbone="grid", fit=grid_fit), ("scratch",)))
        for key, run_config, compare in jobs:
            summaries[key] = classify_and_fit(
                run_config, out / key, zoo=zoo, compare=compare,
                callbacks_for=lambda fit_name, k=key, c=run_config.fit: callbacks_for(k, fit_name, c),
                on_route=None if on_route is None else (lambda route, k=key: on_route(k, route)),
            )
            runs[key] = out / key
    report = None
    if zoo is not None:
        write_report(list(runs.values()), out / "report")
        report = out / "report" / "report.md"
    return DemoResult(scenes, runs, summaries, report, out)

