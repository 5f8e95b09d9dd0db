"""Classify-and-fit: route a scene to a prior that applies to it, or to the scratch fit.

``nerfmeta fit SCENE --init auto`` (the default when a model zoo is present) makes a route that
is allowed to try only what applies to the scene:

1. the backbone is the one asked for (``--backbone``, else :data:`DEFAULT_BACKBONE`, the voxel
   grid: the fastest scratch fit); only the zoo's priors *of that backbone* are candidates
   (a zoo holds one backbone; today the shipped zoo holds NeRF-MLP weight priors only);
2. the zoo's classifier looks at the scene's *training* views (the test views are the fit's
   evaluation and are never shown to any method) and names a category or answers "unknown":
   the candidates are that category's model, then the meta-learned initialisation (a scene to
   which no prior of the zoo applies by step 3, e.g. a photograph, is not classified at all);
3. a candidate is used only where it applies (:func:`prior_checks`, pure): its box holds the
   scene's object box (both in the loaded scene's frame, which is the frame a saved model's box
   is in: a saved model keeps its box, so the mapping is the identity and a scene outside it
   cannot be fitted), the scene's resolution is within :data:`RESOLUTION_FACTOR` of the one the
   zoo was trained at, and the scene's images were composited on the prior's background (an
   opaque photograph has none: not an object scene of the zoo's kind);
4. with no candidate left the route is scratch on the asked backbone, with the reason printed
   and kept in ``summary.json["route"]`` beside every check (name, prior, pass/fail, figures);
5. a scratch route on the voxel grid becomes the zoo's learned occupancy start (:func:`occupancy_route`: the grid's
   coarse stage started from the scene's own training views) for an object scene with alpha whose views are within
   :data:`OCCUPANCY_PX`, where on held-out seen-category scenes it was never more than 0.1 dB behind the scratch grid
   (it is not a guarantee: :data:`OCCUPANCY_ROUTE` says where it ended below); it needs no classifier, and where the
   views give no silhouettes it declines and the grid starts from scratch.

The routed fit runs into ``RUN/`` (a normal fit run folder). ``--compare`` fits baselines into
``RUN/compare/NAME/`` (:data:`BASELINES`): ``scratch`` is the *best* scratch fit, the voxel grid
with its tuned defaults (what ``nerfmeta fit SCENE --init scratch --backbone grid`` does), given
the routed fit's time budget, or without one the routed fit's whole wall-clock time; ``scratch-nerf``
is the NeRF MLP from scratch with the routed fit's settings (the source work's vanilla NeRF; the
same everything as a routed MLP fit but its start). Reports put them on a wall-clock axis that
includes the routed fit's classification (``route.classify_s``) and loading of its start
(``summary.json["init_load_s"]``); ``time_s`` stays the fit loop's own optimisation time.

``RUN/summary.json`` gets ``route`` (:meth:`Route.as_json`) and, with a comparison, the numbers
of the comparison report; it is assembled here and written once, when everything is done. With
``--overwrite`` the whole run (baselines included) is built aside and swapped in at the end
(:mod:`nerfmeta.runfolder`).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from nerfmeta.errors import ConfigError
from nerfmeta.fit.loop import Callback, FitConfig
from nerfmeta.fit.run import RunConfig, fit_in_folder, load_run_scene, run_fit, write_run_summary
from nerfmeta.io import write_json
from nerfmeta.runfolder import CHECKPOINT, run_folder
from nerfmeta.zoo import Zoo, ZooEntry

log = logging.getLogger(__name__)

ROUTES = ("category", "meta", "occupancy", "carve", "scratch")
CARVE_ROUTE = False
"""Whether a scratch route on the voxel grid becomes the carved start (``--init carve``, :mod:`nerfmeta.priors`).
Off: on held-out generated scenes it is far ahead early but not within 0.1 dB of scratch at every time: a concave
object (an open lamp shade, seed 11) or one the hull's margin cuts into (a table on thin legs, seed 13) ends below
scratch even at equal iterations, and the faster carved fit reaches the late fall of test PSNR sooner (BENCHMARKS.md,
*Grid priors (#17)*, *Carved start: never behind*, *Carved start: concave objects and the early check*)."""
OCCUPANCY_ROUTE = True
"""Whether a scratch route on the voxel grid becomes the zoo's learned occupancy start (``--init occupancy``,
:mod:`nerfmeta.priors.occupancy`) where it applies (:func:`occupancy_route`). On 44 held-out generated object scenes at
128 px (four collection seeds) it ends above the scratch grid on 42 with the shipped threshold
(:data:`~nerfmeta.priors.occupancy.THRESHOLD`); an airplane 0.03 dB and an unseen sofa 0.52 dB below (0.33 dB over
three fit seeds: it is not a guarantee on categories the network never saw). With the start's 200 coarse steps
(:data:`~nerfmeta.priors.occupancy.COARSE_ITERS`, session 34) that sofa ends 0.52 dB above, and a fresh seed's 11
scenes on the clock all end above and are never more than 0.1 dB behind (four seeds, 44 scenes: all above at the
end, two of seed 73's dip 0.13 and 0.59 dB behind after a grid growth); at 96 px it ended above on 22 of 22 (two
seeds, with the first threshold, 0.1; the five of them fitted again with 0.02 too), at 160 px on 8 of 8 (0.1); at
64 px it is behind by more than 0.1 dB on 4 of 11, hence :data:`OCCUPANCY_PX` (BENCHMARKS.md, *Grid priors*, sessions
32 and 33)."""
OCCUPANCY_PX = (96, 192)
"""The longer side (pixels, as the fit loads the views) of the object scenes routed to the learned start: from 96 px
(a coarse grid of 42 voxels a side; at 64 px, 28 a side, the scratch grid's own coarse stage finds the shape about
as fast and the start fell behind) to 1.5x the largest size its network was trained at, 128 px (the zoo's
:data:`RESOLUTION_FACTOR`; measured at 96, 100 (lego), 128 and 160 px)."""
COMPARE_DIR = "compare"
DEFAULT_BACKBONE = "grid"
"""The backbone of a fit that names none: the voxel grid, the fastest scratch fit."""
BASELINES = {
    "scratch": "the voxel grid from scratch with its tuned defaults (the best scratch fit)",
    "scratch-nerf": "the NeRF MLP from scratch with the routed fit's settings (the source work's vanilla NeRF)",
}
"""Baselines ``--compare`` can fit beside a routed fit, with what each is."""
RESOLUTION_FACTOR = 1.5
"""A prior trained at R pixels (longer side) applies to scenes of R / 1.5 .. 1.5 R pixels: its
positional encoding and sampling were tuned to that detail; farther off, scratch is the safe start."""
BOX_TOLERANCE = 1e-3
"""How far (scene units) the scene's box may stick out of a prior's box and still count as inside."""
BACKGROUND_TOLERANCE = 1e-3
"""Largest difference per channel between two backgrounds that still count as the same."""


@dataclass(frozen=True)
class SceneFacts:
    """What routing needs to know of a scene, as the fit will load it.

    Attributes:
        box: ``[min_xyz, max_xyz]`` box holding the content, in the loaded scene's frame.
        resolution: ``(height, width)`` of its views after the fit's downscale.
        background: RGB its RGBA views were composited on; None for opaque images (photographs).
    """

    box: tuple[tuple[float, float, float], tuple[float, float, float]]
    resolution: tuple[int, int]
    background: tuple[float, float, float] | None


@dataclass(frozen=True)
class PriorFacts:
    """What a zoo prior applies to.

    Attributes:
        name: its zoo entry name (``category/chair``, ``meta``).
        backbone: its backbone.
        box: ``[min_xyz, max_xyz]`` box its field lives in; None if the zoo does not say.
        resolution: the resolution (longer side, pixels) the zoo's models were trained at; None if not recorded.
        background: RGB its training views were composited on; None if not recorded.
    """

    name: str
    backbone: str
    box: tuple[tuple[float, float, float], tuple[float, float, float]] | None
    resolution: int | None
    background: tuple[float, float, float] | None


@dataclass(frozen=True)
class Check:
    """One applicability check of one prior.

    Attributes:
        name: ``backbone``, ``box``, ``resolution`` or ``background``.
        prior: the prior's zoo entry name, or ``zoo`` for a check of the whole zoo.
        passed: whether the prior applies on this count.
        figures: the numbers compared (JSON-able).
        note: one sentence saying what was compared.
    """

    name: str
    prior: str
    passed: bool
    figures: dict[str, Any]
    note: str

    def as_json(self) -> dict[str, Any]:
        return {"name": self.name, "prior": self.prior, "passed": self.passed, "figures": dict(self.figures), "note": self.note}


@dataclass(frozen=True)
class Route:
    """Where a scene's fit starts, and why.

    Attributes:
        route: one of :data:`ROUTES`.
        init: the ``--init`` spec it resolves to (``category:DIR``, ``meta:DIR``, ``occupancy:NET``, ``carve`` or
            ``scratch``).
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
        backbone: the backbone of the fit (the one asked for).
        checks: the applicability checks made, in order (:class:`Check`).
        classify_s: wall seconds spent routing (reading the scene's facts, classifying) before the fit.
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
    backbone: str = DEFAULT_BACKBONE
    checks: tuple[Check, ...] = ()
    classify_s: float = 0.0

    def as_json(self) -> dict[str, Any]:
        return {
            "route": self.route, "init": self.init, "freeze": self.freeze, "reason": self.reason, "category": self.category,
            "confidence": self.confidence, "unknown": self.unknown, "probabilities": dict(self.probabilities),
            "score": self.score, "known_categories": list(self.known_categories), "views": self.views, "zoo": self.zoo,
            "backbone": self.backbone, "checks": [c.as_json() for c in self.checks], "classify_s": self.classify_s,
        }

    @staticmethod
    def from_json(doc: Mapping[str, Any]) -> "Route":
        """A route back from :meth:`as_json` (as ``config.json`` records it; older runs lack the newer keys)."""
        names = {f.name for f in dataclasses.fields(Route)}
        values = {k: v for k, v in doc.items() if k in names}
        values["known_categories"] = tuple(values.get("known_categories", ()))
        values["checks"] = tuple(Check(**c) for c in values.get("checks", ()))
        return Route(**values)


def _box_inside(inner, outer, tolerance: float) -> bool:
    return all(inner[0][k] >= outer[0][k] - tolerance and inner[1][k] <= outer[1][k] + tolerance for k in range(3))


def _rounded_box(box) -> list[list[float]]:
    return [[round(float(v), 4) for v in row] for row in box]


def prior_checks(prior: PriorFacts, scene: SceneFacts) -> tuple[Check, ...]:
    """Whether ``prior`` applies to ``scene``: its box, resolution and background (pure; every check made, in order)."""
    name = prior.name
    if prior.box is None:
        box = Check("box", name, False, {"scene_box": _rounded_box(scene.box), "prior_box": None},
                    "the zoo does not record the prior's box")
    else:
        inside = _box_inside(scene.box, prior.box, BOX_TOLERANCE)
        box = Check("box", name, inside, {"scene_box": _rounded_box(scene.box), "prior_box": _rounded_box(prior.box)},
                    "the scene's object box " + ("lies inside" if inside else "is not inside") + " the prior's box")
    side = max(scene.resolution)
    if prior.resolution is None:
        res = Check("resolution", name, False, {"scene_px": side, "trained_px": None}, "the zoo does not record its trained resolution")
    else:
        lo, hi = prior.resolution / RESOLUTION_FACTOR, prior.resolution * RESOLUTION_FACTOR
        ok = lo <= side <= hi
        res = Check("resolution", name, ok, {"scene_px": side, "trained_px": prior.resolution, "allowed_px": [round(lo, 2), round(hi, 2)]},
                    f"the scene's {side} px views are " + ("within" if ok else "outside")
                    + f" {RESOLUTION_FACTOR:g}x of the {prior.resolution} px the zoo was trained at")
    figures = {"scene": None if scene.background is None else list(scene.background),
               "prior": None if prior.background is None else list(prior.background)}
    if scene.background is None:
        bg = Check("background", name, False, figures, "the scene's images are opaque (no alpha): not an object scene like the zoo's")
    elif prior.background is None:
        bg = Check("background", name, False, figures, "the zoo does not record the prior's background")
    else:
        same = all(abs(a - b) <= BACKGROUND_TOLERANCE for a, b in zip(scene.background, prior.background))
        bg = Check("background", name, same, figures, "the scene is composited on " + ("the" if same else "another")
                   + " background than the prior was trained on")
    return box, res, bg


def any_prior_applies(priors: Mapping[str, PriorFacts], scene: SceneFacts) -> bool:
    """Whether some prior passes every :func:`prior_checks` for ``scene`` (pure): if none does, classifying the scene
    cannot change its route, so it is not classified (a photograph, a scene far from the zoo's resolution)."""
    return any(all(c.passed for c in prior_checks(p, scene)) for p in priors.values())


def _failed_by_note(checks: Sequence[Check]) -> str:
    """The failed checks' notes, each once, with the priors it holds for ("every prior" when all of them)."""
    priors = list(dict.fromkeys(c.prior for c in checks))
    by_note: dict[str, list[str]] = {}
    for c in checks:
        if not c.passed:
            by_note.setdefault(c.note, []).append(c.prior)
    return "; ".join(f"{note} ({'every prior' if len(who) == len(priors) else ', '.join(who)})" for note, who in by_note.items())


def _failed_text(checks: Sequence[Check]) -> str:
    return "; ".join(f"{c.prior}: {c.note}" for c in checks if not c.passed)


def decide_route(
    prediction: Mapping[str, Any] | None,
    zoo: Zoo | None,
    freeze: int,
    *,
    backbone: str,
    scene: SceneFacts | None,
    priors: Mapping[str, PriorFacts],
    unclassified: bool = False,
) -> Route:
    """The starting point for a classifier answer (pure).

    Args:
        prediction: ``nerfmeta classify``'s document (``category``, ``confidence``, ``unknown``,
            ``probabilities``, ``views``, ``score``), None when there is no classifier (or it was not asked).
        zoo: the zoo, None when there is none.
        freeze: layers to freeze on the category route.
        backbone: the backbone of the fit; only the zoo's priors of this backbone are candidates.
        scene: the scene's facts; None only when there is no zoo or no prior of ``backbone``.
        priors: zoo entry name -> the facts of that prior (:func:`prior_facts`).
        unclassified: the scene was not shown to the classifier because no prior applies to it
            (:func:`any_prior_applies`): the route is scratch, with every prior's checks.

    Returns:
        the route: the first candidate (the classified category's model, then the meta-learned
        initialisation) whose every :func:`prior_checks` passes, else scratch; ``checks`` lists
        every check made and ``reason`` says why.
    """
    if zoo is None:
        return Route("scratch", "scratch", 0, "no model zoo found (pass --zoo DIR or build one with scripts/build_model_zoo): "
                     f"fitting the {backbone} from scratch", backbone=backbone)
    where = str(zoo.root)
    if zoo.backbone != backbone:
        check = Check("backbone", "zoo", False, {"asked": backbone, "zoo": zoo.backbone},
                      f"the zoo holds {zoo.backbone} priors only; this fit is a {backbone} fit")
        return Route("scratch", "scratch", 0, f"the model zoo holds no {backbone} prior (only {zoo.backbone} ones): fitting the "
                     f"{backbone} from scratch (--backbone {zoo.backbone} starts from the zoo's priors)", zoo=where,
                     backbone=backbone, checks=(check,))
    if unclassified:
        if scene is None:
            raise ValueError("decide_route: the scene's facts are needed to check the zoo's priors (see scene_facts)")
        checks = tuple(c for name in sorted(priors) for c in prior_checks(priors[name], scene))
        return Route("scratch", "scratch", 0, f"no prior of the zoo applies to this scene ({_failed_by_note(checks)}): fitting the "
                     f"{backbone} from scratch, without classifying it", zoo=where, backbone=backbone, checks=checks)
    facts: dict[str, Any] = {"zoo": where, "backbone": backbone}
    candidates: list[tuple[str, ZooEntry, int, str]] = []
    if prediction is None:
        why = "the zoo has no classifier"
    else:
        facts.update(category=prediction["category"], confidence=float(prediction["confidence"]), unknown=bool(prediction["unknown"]),
                     probabilities={k: float(v) for k, v in prediction.get("probabilities", {}).items()},
                     score=prediction.get("score"), known_categories=tuple(prediction.get("probabilities", {})),
                     views=int(prediction.get("views", 0)))
        category = prediction["category"]
        p = facts["confidence"]
        model = zoo.categories.get(category)
        if not prediction["unknown"] and model is not None:
            candidates.append(("category", model, freeze, f"classified as {category} (p = {p:.2f}): fine-tuning the {category} model"
                               + (f" with its first {freeze} layers frozen" if freeze else "")))
            why = f"classified as {category} (p = {p:.2f})"
        elif prediction["unknown"]:
            why = f"unknown category (score {_score_text(prediction.get('score'))}; most like {category}, p = {p:.2f})"
        else:
            why = f"classified as {category}, which has no category model in the zoo"
    if zoo.meta is not None:
        candidates.append(("meta", zoo.meta, 0, f"{why}: starting from the meta-learned initialisation"))
    if not candidates:
        return Route("scratch", "scratch", 0, f"{why}, and the zoo has no meta-learned initialisation: fitting the {backbone} from scratch",
                     **facts)
    if scene is None:
        raise ValueError("decide_route: the scene's facts are needed to check the zoo's priors (see scene_facts)")
    checks: list[Check] = []
    for kind, entry, k, reason in candidates:
        made = prior_checks(priors[entry.name], scene)
        checks += made
        if all(c.passed for c in made):
            if checks[:-len(made)]:
                reason += f" ({_failed_text(checks[:-len(made)])})"
            return Route(kind, f"{kind}:{entry.path}", k, reason, checks=tuple(checks), **facts)
    return Route("scratch", "scratch", 0, f"{why}, but no prior applies to this scene ({_failed_text(checks)}): fitting the "
                 f"{backbone} from scratch", checks=tuple(checks), **facts)


def carve_route(route: Route) -> Route:
    """``route`` with a scratch grid start replaced by the carved start (pure); any other route unchanged.

    The carving checks its own applicability when the fit builds its start (alpha, or a uniform border background;
    enough views): where it does not apply the grid starts from scratch and ``summary.json["init_source"]`` says why.
    """
    if route.route != "scratch" or route.backbone != "grid":
        return route
    reason = (f"{route.reason}; the grid starts from the visual hull of the scene's own training views where they can "
              "be carved (a bounded object scene with alpha or a uniform background), else from scratch "
              "(summary.json[\"init_source\"] says which and why)")
    return dataclasses.replace(route, route="carve", init="carve", reason=reason)


def occupancy_route(route: Route, net: Path | None, views: tuple[int, bool] | None) -> Route:
    """``route`` with a scratch grid start replaced by the learned occupancy start of the network ``net`` where it
    applies (pure): ``views`` = (the longer side of the scene's views as the fit reads them, whether they have alpha);
    it applies to an object scene (alpha) whose side is within :data:`OCCUPANCY_PX`. Any other route, or unknown
    ``views``, is returned unchanged; a scratch grid route it does not apply to keeps scratch, with the checks made
    added. The start needs no classifier: it reads the scene's own training views (and declines, the grid then
    starting from scratch, where they give no silhouettes: ``summary.json["init_source"]`` says so).
    """
    if route.route != "scratch" or route.backbone != "grid" or net is None or views is None:
        return route
    (side, alpha), (lo, hi) = views, OCCUPANCY_PX
    sized = lo <= side <= hi
    checks = (Check("resolution", "occupancy", sized, {"scene_px": side, "allowed_px": [lo, hi]},
                    f"the scene's {side} px views are " + ("within" if sized else "outside")
                    + f" the {lo}-{hi} px the learned start is routed at"),
              Check("background", "occupancy", alpha, {"alpha": alpha},
                    "the scene's views have alpha (an object scene)" if alpha
                    else "the scene's images are opaque (no alpha): not an object scene like the network's"))
    if not all(c.passed for c in checks):
        return dataclasses.replace(route, checks=route.checks + checks,
                                   reason=f"{route.reason} (no learned occupancy start: {_failed_text(checks)})")
    reason = (f"the grid's coarse stage starts from the learned occupancy of the scene's own {side} px training views "
              f"(the zoo's network, {net}); no classifier is needed for it")
    return dataclasses.replace(route, route="occupancy", init=f"occupancy:{net}", reason=reason, checks=route.checks + checks)


def view_facts(config: RunConfig, scene: SceneFacts | None = None) -> tuple[int, bool] | None:
    """(the longer side of ``config.scene``'s views as the fit reads them, whether they have alpha): from ``scene``
    when its facts are loaded already, else from the header of its first image in name order (the downscale and
    ``max_side`` rule of the loader, :func:`~nerfmeta.data.common.side_factor`), so that routing does not load a
    scene the fit loads again (lego's 300 images: 1.7 s). None when there is no readable image (a video, a bad file:
    the loader then reports it with its own message)."""
    if scene is not None:
        return max(scene.resolution), scene.background is not None
    from classifier.inputs import _first_image
    from nerfmeta.data.common import side_factor
    from nerfmeta.data.images import image_has_alpha, image_shape
    from nerfmeta.errors import SceneError

    path = Path(config.scene)
    first = _first_image(path) if path.is_dir() else None
    if first is None:
        return None
    try:
        height, width = image_shape(first)
        alpha = image_has_alpha(first)
    except SceneError:
        return None
    factor = side_factor(height, width, config.downscale, config.max_side)
    return max(1, round(max(height, width) / factor)), alpha


def _score_text(score: Mapping[str, Any] | None) -> str:
    if not score:
        return "n/a"
    return f"{score.get('name')} {float(score.get('value')):.3g} < threshold {float(score.get('threshold')):.3g}"


def scene_facts(config: RunConfig) -> SceneFacts:
    """The facts of ``config.scene`` as the fit loads it (downscale, background, normalisation)."""
    scene = load_run_scene(config)
    box = scene.bounds.detach().cpu().tolist()
    return SceneFacts((tuple(box[0]), tuple(box[1])), (scene.height, scene.width),
                      None if scene.background is None else tuple(float(v) for v in scene.background))


def prior_facts(zoo: Zoo, entry: ZooEntry) -> PriorFacts:
    """What the zoo prior ``entry`` applies to: its box (``init.json``'s ``model_box``, else the weights' ``bounds``),
    the zoo's trained resolution and its background (``init.json``, else the entry's recipe)."""
    from nerfmeta.init import INDEX, WEIGHTS

    meta = json.loads((entry.path / INDEX).read_text()).get("meta", {})
    box = meta.get("model_box")
    if box is None:
        from safetensors import safe_open

        with safe_open(str(entry.path / WEIGHTS), framework="pt") as f:
            box = f.get_tensor("bounds").tolist() if "bounds" in f.keys() else None
    background = meta.get("background", entry.config.get("background"))
    trained = zoo.fit.get("trained_resolution")
    return PriorFacts(entry.name, str(meta.get("backbone", zoo.backbone)),
                      None if box is None else (tuple(map(float, box[0])), tuple(map(float, box[1]))),
                      None if trained is None else int(trained),
                      None if background is None else tuple(float(v) for v in background))


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


def route_scene(config: RunConfig, zoo: Zoo | None, freeze: int, *, carve: bool = CARVE_ROUTE,
                occupancy: bool = OCCUPANCY_ROUTE) -> Route:
    """Read the scene's facts and the zoo's priors, classify the scene, decide; ``classify_s`` is the wall time it took.

    Nothing is classified when there is no zoo or the zoo has no prior of ``config.backbone``, and the scene is
    not classified when none of the zoo's priors applies to it (:func:`any_prior_applies`). With ``occupancy`` and a
    zoo holding an occupancy network, a scratch grid route becomes the learned start where it applies
    (:func:`occupancy_route`); with ``carve``, a scratch grid route left becomes the carved start (:func:`carve_route`).
    """
    t0 = time.perf_counter()
    prediction, scene, priors, unclassified = None, None, {}, False
    if zoo is not None and zoo.backbone == config.backbone:
        scene = scene_facts(config)
        priors = {e.name: prior_facts(zoo, e) for e in zoo.entries if e.kind in ("category", "meta")}
        unclassified = not any_prior_applies(priors, scene)  # then whatever the classifier says, the route is scratch
        if not unclassified:
            prediction = classify_scene(config.scene, zoo, config.background)
    route = decide_route(prediction, zoo, freeze, backbone=config.backbone, scene=scene, priors=priors, unclassified=unclassified)
    if occupancy and zoo is not None and zoo.occupancy_net is not None and route.route == "scratch" and config.backbone == "grid":
        route = occupancy_route(route, zoo.occupancy_net, view_facts(config, scene))
    if carve:
        route = carve_route(route)
    return dataclasses.replace(route, classify_s=round(time.perf_counter() - t0, 3))


def routed_config(config: RunConfig, route: Route) -> RunConfig:
    """The routed fit's config: ``config`` (whose backbone the route keeps) with the route's init and freeze."""
    return dataclasses.replace(config, init=route.init, freeze=route.freeze)


def grid_baseline_config(routed: RunConfig, wall_s: float) -> RunConfig:
    """The ``scratch`` baseline: the voxel grid from scratch with its tuned defaults (backbone config and
    :class:`FitConfig`), on the routed fit's scene, seed, evaluation settings and snapshots, with the routed fit's
    time budget, or (without one) its whole wall-clock time ``wall_s`` as the budget."""
    fit = routed.fit
    budget = fit.time_budget_s if fit.time_budget_s else max(round(wall_s, 1), 0.1)
    grid_fit = dataclasses.replace(FitConfig(), time_budget_s=budget, seed=fit.seed, eval_every=fit.eval_every, eval_views=fit.eval_views,
                                   checkpoint_every=fit.checkpoint_every, chunk_rays=fit.chunk_rays, final_ssim=fit.final_ssim)
    return dataclasses.replace(routed, backbone="grid", model={}, fit=grid_fit, init="scratch", freeze=0)


def nerf_baseline_config(routed: RunConfig, saved_model: Mapping[str, Any] | None, zoo: Zoo | None) -> RunConfig:
    """The ``scratch-nerf`` baseline: the NeRF MLP from scratch. Beside a routed MLP fit: the same everything, fresh
    weights from the seed (``saved_model``, the routed init's backbone config, sized for the scene's own box); beside
    a fit of another backbone: the zoo's MLP settings when it holds MLPs, else the MLP's defaults, with the routed fit loop."""
    if routed.backbone == "nerf":
        model = dict(saved_model) if saved_model is not None else dict(routed.model)
        return dataclasses.replace(routed, init="scratch", freeze=0, model=model)
    model = dict(zoo.fit.get("model", {})) if zoo is not None and zoo.backbone == "nerf" else {}
    return dataclasses.replace(routed, backbone="nerf", init="scratch", freeze=0, model=model)


def baselines_to_fit(compare: Sequence[str], route: Route, backbone: str) -> list[str]:
    """The baselines of ``compare`` that differ from the routed fit (a scratch fit of that very kind is not repeated)."""
    same = {"grid": "scratch", "nerf": "scratch-nerf"}.get(backbone) if route.route == "scratch" else None
    return [name for name in compare if name != same]


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
        config: the fit settings (``config.backbone`` is the backbone asked for; ``init`` is ignored).
        out: the run folder (the routed fit; baselines in ``out/compare/NAME``).
        zoo: the verified zoo, None for none (the fit is then from scratch).
        freeze: layers to freeze on the category route (None: the zoo's recommended value).
        compare: baselines to fit too (keys of :data:`BASELINES`).
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


def _recorded_route(folder: Path) -> Route:
    """The routing decision ``config.json`` recorded before the routed fit's first step (for a resume)."""
    try:
        route_doc = json.loads((folder / "config.json").read_text()).get("route")
    except (OSError, ValueError):
        raise ConfigError(f"{folder}: nothing to resume (no readable config.json there)") from None
    if route_doc is None:
        raise ConfigError(f"{folder}/config.json: no routing decision recorded; this run was not made by "
                          "nerfmeta fit --init auto (resume it with the --init it was made with)")
    return Route.from_json(route_doc)


def _classify_and_fit_in(folder: Path, config: RunConfig, *, zoo: Zoo | None, freeze: int | None, compare: Sequence[str],
                         resume: bool, callbacks_for: Callable[[str], Sequence[Callback]],
                         on_route: Callable[[Route], None] | None) -> dict[str, Any]:
    """:func:`classify_and_fit` in an open run folder; ``summary.json`` is assembled here and written once."""
    if resume:
        route = _recorded_route(folder)
    else:
        k = int(zoo.fit.get("freeze", 0)) if freeze is None and zoo else int(freeze or 0)
        route = route_scene(config, zoo, k)
    if on_route is not None:
        on_route(route)
    routed = routed_config(config, route)
    planned = baselines_to_fit(compare, route, routed.backbone)
    if len(planned) < len(compare):
        log.info("the routed fit is that scratch fit already: not fitted twice")
    summary = fit_in_folder(folder, routed, resume=resume, callbacks=list(callbacks_for("routed")),
                            record={"route": route.as_json()}, route=route.as_json(), write_summary=not planned)
    write_json(folder / "route.json", route.as_json())
    if not planned:
        return summary.as_json()
    wall_s = route.classify_s + (summary.init_load_s or 0.0) + summary.time_s
    saved_model = json.loads((folder / "config.json").read_text()).get("model")
    baselines: dict[str, Path] = {}
    for name in planned:
        base_out = folder / COMPARE_DIR / name
        base_resume = resume and (base_out / "config.json").is_file() and (base_out / CHECKPOINT).is_file()  # else anew
        base = grid_baseline_config(routed, wall_s) if name == "scratch" else nerf_baseline_config(routed, saved_model, zoo)
        run_fit(base, base_out, resume=base_resume, overwrite=not base_resume, callbacks=list(callbacks_for(name)))
        baselines[name] = base_out
    from nerfmeta.report.compare import write_comparison

    main_baseline = next(name for name in BASELINES if name in baselines)
    comparison = write_comparison(folder, baselines, folder, baseline=main_baseline, name="routed", summary=summary.as_json(),
                                  update_summary=False)
    comparison["headline"] = headline(comparison)
    summary = dataclasses.replace(summary, comparison=comparison)
    write_run_summary(folder, summary)
    return summary.as_json()


def headline(comparison: Mapping[str, Any]) -> list[str]:
    """Lines for the terminal: the routed fit against the baseline on the wall-clock axis (classification and loading
    included), then whether it is ahead at every evaluation of that axis."""
    base = comparison.get("baseline", "scratch")
    what = BASELINES.get(base, base)
    methods = comparison.get("methods", {})
    routed, baseline = methods.get(comparison.get("method", "routed"), {}), methods.get(base, {})
    lines = [f"baseline {base}: {what}; time axis: wall-clock, the routed fit's classification and loading included"]
    if routed and baseline:
        lines.append(f"routed {_psnr(routed.get('final_test_psnr'))} in {_secs(routed.get('wall_s'))} "
                     f"(classify {_secs(routed.get('classify_s'))} + load {_secs(routed.get('init_load_s'))} + fit "
                     f"{_secs(routed.get('time_s'))}); {base} {_psnr(baseline.get('final_test_psnr'))} in {_secs(baseline.get('wall_s'))}")
    target, sw = comparison.get("target_psnr"), comparison.get("speedup_wall")
    lines.append(f"to {base}'s final test PSNR ({target:.2f} dB): {sw:.2f}x {'faster' if sw >= 1 else 'as fast (slower)'} in wall-clock"
                 if target is not None and sw else
                 f"{base}'s final test PSNR ({target:.2f} dB) not reached by the routed fit" if target is not None
                 else f"{base} has no final test PSNR")
    ahead = comparison.get("ahead_wall")
    lines.append(f"routed fit ahead of {base} at every evaluation on the wall-clock axis" if ahead else
                 f"routed fit behind {base} (by up to {comparison.get('behind_wall_db') or 0:.2f} dB) on the wall-clock axis"
                 if ahead is False else f"routed fit and {base} share no wall-clock range")
    return lines


def _psnr(value: float | None) -> str:
    return "no test PSNR" if value is None else f"{value:.2f} dB"


def _secs(value: float | None) -> str:
    return "?" if value is None else f"{value:.1f} s"
