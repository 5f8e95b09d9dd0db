"""Classify-and-fit: route a scene to its category's model, the meta-learned initialisation, or scratch.

``nerfmeta fit SCENE --init auto`` (the default when a model zoo is present):

1. the zoo's classifier looks at the scene's *training* views (the test views are the fit's
   evaluation and are never shown to any method) and names a category or answers "unknown";
2. :func:`decide_route` turns that into a starting point: a known category with a category model
   -> ``category:DIR`` with the first ``freeze`` layers frozen; unknown (or a category without a
   model) -> ``meta:DIR``; no zoo -> ``scratch``, saying so;
3. the routed fit runs into ``RUN/`` (a normal fit run folder), and with ``--compare scratch`` the
   from-scratch baseline runs into ``RUN/compare/scratch/`` with the identical backbone config,
   optimiser, learning rates, ray batch, budget and seed: only the starting point differs.

``RUN/summary.json`` gets ``route`` (:meth:`Route.as_json`) and, with a comparison, the numbers
of the comparison report; it is assembled here and written once, when everything is done. With
``--overwrite`` the whole run (baselines included) is built aside and swapped in at the end
(:mod:`nerfmeta.runfolder`).
"""

from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from nerfmeta.errors import ConfigError
from nerfmeta.fit.loop import Callback
from nerfmeta.fit.run import RunConfig, fit_in_folder, run_fit, write_run_summary
from nerfmeta.io import write_json
from nerfmeta.runfolder import CHECKPOINT, run_folder
from nerfmeta.zoo import Zoo

log = logging.getLogger(__name__)

ROUTES = ("category", "meta", "scratch")
COMPARE_DIR = "compare"
BASELINES = ("scratch",)


@dataclass(frozen=True)
class Route:
    """Where a scene's fit starts, and why.

    Attributes:
        route: ``category``, ``meta`` or ``scratch``.
        init: the ``--init`` spec it resolves to (``category:DIR``, ``meta:DIR`` or ``scratch``).
        freeze: layers kept frozen (category route only).
        reason: one sentence for the user.
        category: the classifier's most probable known category (None without a classifier).
        confidence: its view-averaged probability.
        unknown: the classifier's unknown decision.
        probabilities: category -> view-averaged probability.
        score: the unknown score: name, value, threshold.
        known_categories: the categories the classifier knows.
        views: views the classifier averaged over.
        zoo: the zoo folder used, None without one.
    """

    route: str
    init: str
    freeze: int
    reason: str
    category: str | None = None
    confidence: float | None = None
    unknown: bool | None = None
    probabilities: dict[str, float] = field(default_factory=dict)
    score: dict[str, Any] | None = None
    known_categories: tuple[str, ...] = ()
    views: int = 0
    zoo: str | None = None

    def as_json(self) -> dict[str, Any]:
        return {
            "route": self.route, "init": self.init, "freeze": self.freeze, "reason": self.reason, "category": self.category,
            "confidence": self.confidence, "unknown": self.unknown, "probabilities": dict(self.probabilities),
            "score": self.score, "known_categories": list(self.known_categories), "views": self.views, "zoo": self.zoo,
        }


def decide_route(prediction: Mapping[str, Any] | None, zoo: Zoo | None, freeze: int) -> Route:
    """The starting point for a classifier answer (pure).

    Args:
        prediction: ``nerfmeta classify``'s document (``category``, ``confidence``, ``unknown``,
            ``probabilities``, ``views``, ``score``), None when there is no classifier.
        zoo: the zoo, None when there is none.
        freeze: layers to freeze on the category route.
    """
    if zoo is None:
        return Route("scratch", "scratch", 0, "no model zoo found (pass --zoo DIR or build one with scripts/build_model_zoo): "
                     "fitting from scratch")
    where = str(zoo.root)
    if prediction is None:
        if zoo.meta is not None:
            return Route("meta", f"meta:{zoo.meta.path}", 0, "the zoo has no classifier: starting from its meta-learned initialisation",
                         zoo=where)
        return Route("scratch", "scratch", 0, "the zoo has neither a classifier nor a meta-learned initialisation", zoo=where)
    known = tuple(prediction.get("probabilities", {}))
    facts = dict(category=prediction["category"], confidence=float(prediction["confidence"]), unknown=bool(prediction["unknown"]),
                 probabilities={k: float(v) for k, v in prediction.get("probabilities", {}).items()},
                 score=prediction.get("score"), known_categories=known, views=int(prediction.get("views", 0)), zoo=where)
    models = zoo.categories
    category = prediction["category"]
    if not prediction["unknown"] and category in models:
        return Route("category", f"category:{models[category].path}", freeze,
                     f"classified as {category} (p = {facts['confidence']:.2f}): fine-tuning the {category} model"
                     + (f" with its first {freeze} layers frozen" if freeze else ""), **facts)
    why = (f"unknown category (score {_score_text(prediction.get('score'))}; most like {category}, p = {facts['confidence']:.2f})"
           if prediction["unknown"] else f"classified as {category}, which has no category model in the zoo")
    if zoo.meta is not None:
        return Route("meta", f"meta:{zoo.meta.path}", 0, f"{why}: starting from the meta-learned initialisation", **facts)
    return Route("scratch", "scratch", 0, f"{why}, and the zoo has no meta-learned initialisation: fitting from scratch", **facts)


def _score_text(score: Mapping[str, Any] | None) -> str:
    if not score:
        return "n/a"
    return f"{score.get('name')} {float(score.get('value')):.3g} < threshold {float(score.get('threshold')):.3g}"


def classify_scene(scene_path: str | Path, zoo: Zoo, background: tuple[float, float, float]) -> dict[str, Any] | None:
    """The zoo classifier's answer for a scene, from its training views only (None if the zoo has no classifier)."""
    from classifier.data import scene_premultiplied, to_input_size
    from classifier.inputs import _downscale_for, _first_image
    from classifier.store import classify_views, load_classifier
    from nerfmeta.data import load_scene

    entry = zoo.classifier
    if entry is None:
        return None
    classifier = load_classifier(entry.path)
    size = classifier.meta.input_size
    path = Path(scene_path)
    factor = _downscale_for(_first_image(path) if path.is_dir() else None, size)
    scene = load_scene(path, downscale=factor, background=classifier.meta.background)
    train = scene.subset("train")
    views = to_input_size(scene_premultiplied(train), size)
    return classify_views(classifier, views).to_json()


def routed_config(config: RunConfig, route: Route, zoo: Zoo | None) -> RunConfig:
    """The routed fit's config: ``config`` with the route's init and freeze (and the zoo's backbone)."""
    if route.route == "scratch":
        return dataclasses.replace(config, init="scratch", freeze=0)
    return dataclasses.replace(config, init=route.init, freeze=route.freeze, backbone=zoo.backbone if zoo else config.backbone)


def baseline_config(routed: RunConfig, saved_model: Mapping[str, Any] | None) -> RunConfig:
    """The scratch baseline of a routed fit: the same everything, fresh weights from the seed.

    ``saved_model`` is the routed init's backbone config (JSON form): the baseline builds the
    same architecture, sized for the scene's own box.
    """
    model = dict(saved_model) if saved_model is not None else dict(routed.model)
    return dataclasses.replace(routed, init="scratch", freeze=0, model=model)


def classify_and_fit(
    config: RunConfig,
    out: str | Path,
    *,
    zoo: Zoo | None,
    freeze: int | None = None,
    compare: Sequence[str] = (),
    resume: bool = False,
    overwrite: bool = False,
    callbacks_for: Callable[[str], Sequence[Callback]] = lambda name: (),
    on_route: Callable[[Route], None] | None = None,
) -> dict[str, Any]:
    """Classify ``config.scene``, route it, fit it into ``out`` and (``compare``) fit the baselines beside it.

    Args:
        config: the fit settings shared by the routed fit and its baselines (``init`` is ignored).
        out: the run folder (the routed fit; baselines in ``out/compare/NAME``).
        zoo: the verified zoo, None for none (the fit is then from scratch).
        freeze: layers to freeze on the category route (None: the zoo's recommended value).
        compare: baselines to fit too (``scratch``).
        callbacks_for: fit callbacks (progress bars) per fit name: ``routed`` or a baseline name.
        on_route: called with the decision before any fitting (the CLI prints it).

    Returns:
        the routed fit's summary with ``route`` and (with a comparison) ``comparison`` added.
    """
    unknown = sorted(set(compare) - set(BASELINES))
    if unknown:
        raise ConfigError(f"--compare {','.join(unknown)}: supported baselines are {', '.join(BASELINES)}")
    with run_folder(out, "fit", resume=resume, overwrite=overwrite, protect=(config.scene,)) as run:
        return _classify_and_fit_in(run.dir, config, zoo=zoo, freeze=freeze, compare=compare, resume=resume,
                                    callbacks_for=callbacks_for, on_route=on_route)


def _classify_and_fit_in(folder: Path, config: RunConfig, *, zoo: Zoo | None, freeze: int | None, compare: Sequence[str],
                         resume: bool, callbacks_for: Callable[[str], Sequence[Callback]],
                         on_route: Callable[[Route], None] | None) -> dict[str, Any]:
    """:func:`classify_and_fit` in an open run folder; ``summary.json`` is assembled here and written once."""
    if resume:  # the decision was recorded in config.json before the routed fit's first step
        try:
            route_doc = json.loads((folder / "config.json").read_text()).get("route")
        except (OSError, ValueError):
            raise ConfigError(f"{folder}: nothing to resume (no readable config.json there)") from None
        if route_doc is None:
            raise ConfigError(f"{folder}/config.json: no routing decision recorded; this run was not made by "
                              "nerfmeta fit --init auto (resume it with the --init it was made with)")
        route = Route(**{**route_doc, "known_categories": tuple(route_doc.get("known_categories", ()))})
    else:
        prediction = classify_scene(config.scene, zoo, config.background) if zoo is not None else None
        route = decide_route(prediction, zoo, freeze=int(zoo.fit.get("freeze", 0)) if freeze is None and zoo else int(freeze or 0))
    if on_route is not None:
        on_route(route)
    routed = routed_config(config, route, zoo)
    planned = [name for name in compare if not (name == "scratch" and route.route == "scratch")]
    if len(planned) < len(compare):
        log.info("the routed fit is from scratch already: no separate scratch baseline")
    summary = fit_in_folder(folder, routed, resume=resume, callbacks=list(callbacks_for("routed")),
                            record={"route": route.as_json()}, route=route.as_json(), write_summary=not planned)
    write_json(folder / "route.json", route.as_json())
    if not planned:
        return summary.as_json()
    baselines: dict[str, Path] = {}
    saved_model = json.loads((folder / "config.json").read_text()).get("model")
    for name in planned:
        base_out = folder / COMPARE_DIR / name
        base_resume = resume and (base_out / "config.json").is_file() and (base_out / CHECKPOINT).is_file()  # else anew
        run_fit(baseline_config(routed, saved_model), base_out, resume=base_resume, overwrite=not base_resume,
                callbacks=list(callbacks_for(name)))
        baselines[name] = base_out
    from nerfmeta.report.compare import write_comparison

    comparison = write_comparison(folder, baselines, folder, baseline="scratch", name="routed", summary=summary.as_json(),
                                  update_summary=False)
    comparison["headline"] = headline(comparison)
    summary = dataclasses.replace(summary, comparison=comparison)
    write_run_summary(folder, summary)
    return summary.as_json()


def headline(comparison: Mapping[str, Any]) -> list[str]:
    """Two lines for the terminal: PSNR against scratch and the speed-up to scratch's final PSNR."""
    target = comparison.get("target_psnr")
    si, st = comparison.get("speedup_iters"), comparison.get("speedup_time")
    ahead = comparison.get("ahead_at_every_eval")
    lines = [f"to scratch's final test PSNR ({target:.2f} dB): speed-up {si:.1f}x in iterations, {st:.1f}x in time"
             if target is not None and si and st else
             f"scratch's final test PSNR ({target:.2f} dB) not reached by the routed fit" if target is not None
             else "scratch has no final test PSNR"]
    not_ahead = comparison.get("not_ahead_at") or []
    lines.append("routed fit ahead of scratch at every evaluation" if ahead else
                 f"routed fit not ahead of scratch at iterations {', '.join(str(i) for i in not_ahead[:8])}")
    return lines
