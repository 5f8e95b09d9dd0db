"""The one fit loop, for every backbone and every initialisation.

Differences between scratch, transfer and meta-initialised fits are data: the model passed in
(its parameters and frozen layers) and the :class:`FitConfig`. Logging, progress bars and
checkpoints are callbacks, never forks of the loop. Time is measured on the optimisation only:
evaluation and checkpoint writing are excluded from ``time_s`` and reported separately.

When a model ends a stage (:meth:`~nerfmeta.fields.base.RadianceModel.stage_ending`), the loop
evaluates it if there is a target PSNR (a stage that meets the target ends the fit) and lets it make
its per-scene decisions from training rays (:meth:`~nerfmeta.fields.base.RadianceModel.decide`).
Decisions are logged, noted in the next ``StepRecord.event`` and kept in ``FitState.decisions``.

A fit of few views (``FitConfig.holdout_max_views``) of an object (``FitConfig.holdout_scene_types``) holds a square
tile of its training views out of training (:mod:`nerfmeta.fit.holdout`); their PSNR every ``holdout_every`` steps
(counted in ``time_s``) picks the parameters the fit ends with and stops it when they have stopped improving
(``patience``).

A divergence guard (:mod:`nerfmeta.fit.guard`, ``FitConfig.guard``) checks every step's loss and
gradients; a bad step is rolled back to the last good snapshot, the learning rates are lowered for
the rest of the fit (``FitState.lr_guard_scale``, kept in checkpoints) and the step is tried again
with fresh rays, so ``iters`` counts good steps (the time of bad ones still counts in ``time_s``).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Callable, Literal, Protocol, Sequence, runtime_checkable

import torch

from nerfmeta.config import bounded, check_fields
from nerfmeta.data.scene import Scene
from nerfmeta.data.scene_type import SCENE_TYPES
from nerfmeta.fields.base import Decision, RadianceModel, total_loss
from nerfmeta.fit.evaluate import MSE_FLOOR, EvalResult, evaluate_views, pixel_stride, render_rays, strided_rays
from nerfmeta.fit.guard import DivergenceGuard, GuardConfig, GuardEvent
from nerfmeta.fit.holdout import BestSnapshot, place_tiles
from nerfmeta.fit.sampler import RaySampler
from nerfmeta.fit.views import ViewErrors
from nerfmeta.metrics import LpipsUnavailable, load_lpips, lpips_skip_reason, mse_to_psnr, ssim_skip_reason

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FitConfig:
    """Optimisation settings shared by every backbone and initialisation."""

    iters: int = bounded(3000, low=1)
    """Maximum number of iterations."""
    time_budget_s: float | None = bounded(None, low=0, low_open=True)
    """Stop once this much optimisation time (seconds, evaluation excluded) has passed."""
    target_psnr: float | None = None
    """Stop at the first evaluation whose test PSNR reaches this (dB): an intermediate evaluation's, on the first ``eval_views`` test views (views larger than ``eval_max_rays`` allows scored on every s-th pixel), so the final figure over every test view and pixel can differ a little."""
    batch_rays: int = bounded(4096, low=1)
    """Rays per iteration."""
    seed: int = 0
    """Seed of the ray sampler and of sample jitter."""
    lr_decay: float = bounded(0.1, low=0, high=1, low_open=True)
    """Learning rates decay exponentially to this fraction at the end (of iters or of the time budget)."""
    adam_eps: float = bounded(1e-8, low=0, low_open=True)
    """Adam's epsilon, for the parameter groups that declare none of their own (``ParamGroup.adam_eps``)."""
    eval_every: int = bounded(500, low=0)
    """Evaluate test PSNR every this many iterations (0: only at the end)."""
    eval_views: int = bounded(4, low=0)
    """Test views rendered at intermediate evaluations (0: all); the final evaluation uses all."""
    eval_max_rays: int = bounded(262144, low=0)
    """Most rays an intermediate evaluation renders: larger views are scored on every s-th pixel row and column, s as small as fits (0: every pixel); the final evaluation renders every pixel."""
    checkpoint_every: int = bounded(500, low=0)
    """Write a checkpoint every this many iterations (0: only at the end)."""
    chunk_rays: int = bounded(16384, low=1)
    """Most rays rendered at once during evaluation (on a CPU also at most ``nerfmeta.fit.evaluate.CPU_CHUNK_RAYS``, in worker threads)."""
    stage_end_eval: bool = True
    """With a target PSNR, evaluate (like ``eval_every``) when the model ends a stage, so a stage that already meets the target ends the fit and the next is never built (False: scheduled evaluations only)."""
    final_ssim: bool = True
    """Compute SSIM at the final evaluation (``test_ssim``; False saves its time)."""
    final_lpips: bool = True
    """Compute LPIPS (AlexNet) at the final evaluation (``test_lpips``; needs the weights installed at set-up, else noted as unavailable)."""
    holdout_tile: float = bounded(0.17, low=0, high=0.5)
    """Side of the square tile held out of training views (as many as ``holdout_rays`` asks), as a fraction of a view's
    shorter side (0: none, and no early stop; a 16-view fit at 96 px holds out 2.8 % of its pixels): the fit never trains
    on the tiles; their PSNR every ``holdout_every`` steps picks the parameters the fit ends with (the best so far,
    unless the last score is within ``patience_db`` of it) and stops it after ``patience`` steps without a better one
    (see nerfmeta.fit.holdout). Only for fits of at most ``holdout_max_views`` training views."""
    holdout_max_views: int = bounded(20, low=0)
    """Hold tiles out only of a fit with at most this many training views (0: any number). Few views are where a grid
    fit overfits and the tiles' score follows the test views' (16 views: 0.06-0.93 dB higher in 0.5-0.7x the time);
    with 24 and 40 the tiles' score flattened or fell while the test views' still rose, and stopping there cost up to
    0.5 dB (BENCHMARKS.md, *Stopping where the held-out pixels stop improving*)."""
    holdout_scene_types: tuple[Literal["object", "forward", "unbounded"], ...] = ("object",)
    """Kinds of scene whose fits hold tiles out (the kind detected, or given by ``--scene-type``). Objects only: on two
    generated forward-facing scenes (14 and 17 training views, 120-s budgets) the tiles' score levelled off while the
    test views' still rose, so the early stop ended 0.1-0.6 dB lower in 5 fits of 6 (in 0.2-0.5x the time); on a real
    unbounded capture cut to 20 views (beer) it ended 0.25 dB higher but 0.04 worse in LPIPS, a smoother picture
    (BENCHMARKS.md, *Stopping where the held-out pixels stop improving*)."""
    holdout_every: int = bounded(50, low=1)
    """Steps between two scores of the held-out tiles (their render counts in the fit's time)."""
    holdout_rays: int = bounded(4096, low=0)
    """Held-out pixels: tiles go into as many training views as hold this many pixels (at least 8 views, at most all),
    and at most this many are scored (every s-th row and column of each tile where there are more; 0: every view
    tiled, every pixel scored)."""
    patience: int = bounded(200, low=0)
    """Stop once this many steps pass without a better held-out PSNR than the best so far, and the last score is
    ``patience_db`` below the best (0: never stop early; the fit still ends with the best parameters). Scores start
    again after the model changes its structure (a grid's growth), whose dip passes."""
    holdout_release: float = bounded(0.75, low=0, high=1)
    """At this fraction of the fit (its iterations or time budget), a fit whose held-out score is still at its best
    (within ``patience_db``) gives the tiles back to training for the rest: it has not overfitted, so the pixels are worth
    more as data than as a check (1: never; nothing is stopped or put back after it)."""
    patience_db: float = bounded(0.1, low=0)
    """How far below the best the last held-out score must be to stop early, or for the fit to end with the best
    parameters rather than its last: a plateau within it is noise, not a fall."""
    random_background: tuple[Literal["object", "forward", "unbounded"], ...] = ()
    """Kinds of scene whose training rays are composited on a random colour, drawn per ray (as DirectVoxGO's
    ``rand_bkgd`` does for its forward-facing and unbounded scenes), rather than on ``background``; test renders keep
    ``background``. Where every ray ends on something, a fixed white lets a surface as light as it turn half
    transparent and show the white through, which holds in the training views and not between them; a random colour
    behind matches no photo, so the fit is pushed to make every ray opaque. None by default (measured in session 47,
    BENCHMARKS.md #16): on four generated forward-facing layouts at 160 x 120 it gained +0.9 to +2.5 dB at 1500 steps
    and +0.2 to +0.8 in 60-s fits, every seed, but at LLFF's 504 x 378 in the 120 s that #16 asks for it lost 4.5-4.9
    dB with the grid then 126 voxels across (the training error fell far more slowly, the far wall came out streaked)
    and 0.6 dB with it 64 across (its steps slower: 1602 in 120 s against 3000 in 87 s); on unbounded captures a
    generated room gained 0.9 dB and beer lost 6.6 (its far railings and walls, which the white had stood in for,
    smeared over the contracted shell's coarse far voxels). Never for scenes with alpha (their targets were composited
    on ``background``). Those figures were measured on the fixed white, before the grid learned a background colour on
    forward-facing and unbounded scenes (``VoxelGridConfig.background_map``, session 48): with that table, as by
    default there now, it is added to each training ray's random colour as it is to ``background`` (the sum clamped
    to [0, 1]); the two together have not been measured."""
    guard: GuardConfig = GuardConfig()
    """Divergence guard: on a NaN/inf or exploding step, roll back, lower the learning rates and retry (see nerfmeta.fit.guard)."""

    def __post_init__(self) -> None:
        # config.json holds the guard as a dict and tuples as lists: accept them so a saved config loads back equal.
        object.__setattr__(self, "guard", GuardConfig.coerce(self.guard))
        for name in ("holdout_scene_types", "random_background"):
            if isinstance(getattr(self, name), list):
                object.__setattr__(self, name, tuple(getattr(self, name)))
        check_fields(self, "fit config")

    @classmethod
    def from_json(cls, data: dict) -> "FitConfig":
        """The config saved in a ``config.json``; keys of older versions that no longer mean anything are dropped, a
        config saved before held-out tiles existed resumes training on every pixel, as it started, and one saved before
        their scene kinds were chosen resumes with tiles in any kind of scene, as it started; one saved before random
        backgrounds resumes on its fixed background."""
        if "holdout_tile" in data:
            data = {"holdout_scene_types": SCENE_TYPES, **data}
        data = {"holdout_tile": 0.0, "random_background": (), **data}
        return cls(**{k: v for k, v in data.items() if k not in RETIRED_FIT_KEYS})


RETIRED_FIT_KEYS = ("adam_eps_density",)
"""FitConfig fields of older versions: the density groups' Adam epsilon is now declared by the field
(``ParamGroup.adam_eps``), so a run folder written before that still loads and resumes."""


@dataclass
class StepRecord:
    """One logged iteration; ``test_psnr`` only where evaluated, ``event`` where the model changed or the
    divergence guard rolled back before the step succeeded; ``lr_scale`` includes the guard's factor."""

    iter: int
    time_s: float
    train_psnr: float
    samples_per_ray: float
    lr_scale: float
    test_psnr: float | None = None
    holdout_psnr: float | None = None
    event: str | None = None

    def as_json(self) -> dict:
        out = {"iter": self.iter, "time_s": round(self.time_s, 4), "train_psnr": round(self.train_psnr, 4),
               "samples_per_ray": round(self.samples_per_ray, 2), "lr_scale": round(self.lr_scale, 5)}
        if self.test_psnr is not None:
            out["test_psnr"] = round(self.test_psnr, 4)
        if self.holdout_psnr is not None:
            out["holdout_psnr"] = round(self.holdout_psnr, 4)
        if self.event:
            out["event"] = self.event
        return out


@dataclass
class FitState:
    """Everything needed to continue a fit exactly: iteration, clock, RNG, optimiser and the guard's lr factor."""

    step: int = 0
    time_s: float = 0.0
    eval_time_s: float = 0.0
    rng_state: torch.Tensor | None = None
    optimizer_state: dict | None = None
    last_test_psnr: float | None = None
    stop_reason: str = ""
    decisions: dict[str, dict] = field(default_factory=dict)
    """Per-scene choices made so far, by name (:meth:`~nerfmeta.fields.base.Decision.as_json`)."""
    lr_guard_scale: float = 1.0
    """Learning-rate factor left by the divergence guard's rollbacks (1: none); kept across resumes."""
    guard_events: list[GuardEvent] = field(default_factory=list)
    """The divergence guard's rollbacks so far, oldest first."""
    holdout_psnr: float = -math.inf
    """The held-out tiles' PSNR at their last score (``FitConfig.holdout_tile``)."""
    best: BestSnapshot | None = None
    """The parameters with the best held-out PSNR so far (``FitConfig.holdout_tile``; None: none scored yet)."""


class Callback(Protocol):
    def __call__(self, record: StepRecord, model: RadianceModel, state: FitState) -> None: ...


@runtime_checkable
class EvalProgress(Protocol):
    """A callback that also hears how the final evaluation advances (it can take longer than the fit on large views)."""

    def evaluating(self, done: int, total: int) -> None: ...


@dataclass
class FitResult:
    state: FitState
    final: EvalResult | None
    history: list[StepRecord] = field(default_factory=list)
    view_psnr: torch.Tensor | None = None
    """(V,) each training view's PSNR over the fit's last steps (:class:`~nerfmeta.fit.views.ViewErrors`; NaN:
    too few rays to tell), in the order of the scene's ``train`` split."""


def build_optimizer(model: RadianceModel, config: FitConfig) -> torch.optim.Adam:
    """Adam with one parameter group per model LR group; frozen parameters are left out.

    The fused implementation (one kernel per step instead of a dozen tensor ops per parameter;
    the same update) is used when every parameter is a floating-point CPU or CUDA tensor: on a
    2-core CPU it steps a 7-million-value voxel grid about four times faster.

    A group's epsilon is the one it declares (``ParamGroup.adam_eps``, e.g. the voxel grid's density
    groups, see ``nerfmeta.fields.voxel_grid.DENSITY_ADAM_EPS``), else ``config.adam_eps``.
    """
    params = dict(model.named_parameters())
    groups = []
    for g in model.param_groups():
        ps = [params[n] for n in g.param_names if params[n].requires_grad]
        if ps:
            eps = config.adam_eps if g.adam_eps is None else g.adam_eps
            groups.append({"params": ps, "lr": g.lr, "base_lr": g.lr, "name": g.name, "eps": eps})
    if not groups:
        raise ValueError("every parameter is frozen: nothing to optimise")
    tensors = [p for g in groups for p in g["params"]]
    fused = all(p.is_floating_point() and p.device.type in ("cpu", "cuda") for p in tensors)
    return torch.optim.Adam(groups, eps=config.adam_eps, fused=fused)


_DIVERGED_HINT = ("lower the learning rates (e.g. --set lr_density=..., --set lr=...) or check the scene "
                  "(a NaN pixel or pose makes every step fail)")


def fit_progress(config: FitConfig, step: int, time_s: float) -> float:
    """How far a fit is towards its end, in [0, 1]: by iterations, or by the time budget where that is further along.

    The learning-rate decay (:func:`lr_scale`) and a model's schedules that are set in fractions of the fit
    (:meth:`~nerfmeta.fields.base.RadianceModel.begin_step`) follow it, so they land in the same place on a
    fast or a slow machine.
    """
    progress = step / max(1, config.iters)
    if config.time_budget_s:
        progress = max(progress, time_s / config.time_budget_s)
    return min(1.0, progress)


def joined_events(*messages: str | None) -> str | None:
    """A record's ``event``: the non-empty messages joined with "; " (None if there are none)."""
    return "; ".join(m for m in messages if m) or None


def lr_scale(config: FitConfig, step: int, time_s: float) -> float:
    """Exponential decay factor at the current progress (:func:`fit_progress`)."""
    return config.lr_decay ** fit_progress(config, step, time_s)


def fit(
    model: RadianceModel,
    scene: Scene,
    config: FitConfig,
    *,
    background: torch.Tensor,
    callbacks: Sequence[Callback] = (),
    state: FitState | None = None,
    should_checkpoint: Callable[[FitState], None] | None = None,
) -> FitResult:
    """Fit ``model`` to the training views of ``scene``.

    Args:
        model: any backbone, on the device to train on (its frozen layers already frozen).
        scene: the scene; its ``train`` split is fitted and its ``test`` split evaluated.
        config: optimisation settings.
        background: (3,) RGB the scene was composited on, on the model's device.
        callbacks: called after every iteration with the :class:`StepRecord`.
        state: a state to resume from (from a checkpoint), else a fresh start.
        should_checkpoint: called with the state at checkpoint iterations and at the end
            (after the optimiser state has been captured).

    Returns:
        The final state, the final evaluation on all test views, and the per-iteration history.
    """
    device = background.device
    n_train = len(scene.splits.get("train", ()))
    few = config.holdout_max_views == 0 or n_train <= config.holdout_max_views
    kind = scene.scene_type.kind
    tiled_kind = kind in config.holdout_scene_types
    if state is not None and "holdout_released" in state.decisions:  # resumed after the tiles were given back
        few = False
    tiled = few and tiled_kind
    random_background = kind in config.random_background and scene.alphas is None
    tiles = (place_tiles(n_train, scene.height, scene.width, config.holdout_tile, config.seed, config.holdout_rays)
             if tiled else None)
    sampler = RaySampler(scene, "train", device, tiles)
    held = None if tiles is None else sampler.held_out(config.holdout_rays)
    test_views = scene.splits.get("test", ())
    state = state or FitState()
    gen = torch.Generator().manual_seed(config.seed)
    if state.rng_state is not None:
        gen.set_state(state.rng_state)
    model.train()
    optimizer = build_optimizer(model, config)
    if state.optimizer_state is not None:
        optimizer.load_state_dict(state.optimizer_state)
    history: list[StepRecord] = []
    is_cuda = device.type == "cuda"
    view_errors = ViewErrors.empty(sampler.n_views)

    final: EvalResult | None = None

    def final_eval() -> EvalResult:
        t_eval = time.perf_counter()
        lpips_model = None
        if config.final_lpips and not lpips_skip:
            try:
                lpips_model = load_lpips(device=device)
            except LpipsUnavailable as err:  # e.g. a tampered weights file: the fit's result still stands
                log.warning("%s", err)
                note_decisions([Decision("final_lpips", False, str(err), {})])
        watchers = [cb for cb in callbacks if isinstance(cb, EvalProgress)]

        def on_view(done: int, total: int) -> None:
            for watcher in watchers:
                watcher.evaluating(done, total)

        result = evaluate_views(model, scene, list(test_views), background, with_ssim=config.final_ssim and not ssim_skip,
                                chunk=config.chunk_rays, lpips_model=lpips_model, on_view=on_view)
        state.eval_time_s += time.perf_counter() - t_eval
        state.last_test_psnr = result.psnr
        return result

    def capture() -> None:
        state.rng_state = gen.get_state()
        state.optimizer_state = optimizer.state_dict()

    evaluated_at = -1  # the step of the last intermediate evaluation
    eval_notes: list[str] = []  # decisions an intermediate evaluation made, for the next record's event

    def partial_eval() -> float:
        """Test PSNR on the first ``eval_views`` test views (an intermediate evaluation)."""
        nonlocal evaluated_at
        views = list(test_views) if config.eval_views <= 0 else list(test_views)[: config.eval_views]
        stride = pixel_stride(len(views), scene.height, scene.width, config.eval_max_rays)
        if stride > 1 and "eval_stride" not in state.decisions:  # said once, at the first
            rays = strided_rays(len(views), scene.height, scene.width, stride)
            eval_notes.extend(note_decisions([Decision("eval_stride", stride, (
                f"intermediate evaluations score one pixel in {stride} along each row and column of their {len(views)} views "
                f"({rays} rays, at most eval_max_rays={config.eval_max_rays}, instead of "
                f"{len(views) * scene.height * scene.width}); the final evaluation renders every pixel"),
                {"views": len(views), "rays": rays, "max_rays": config.eval_max_rays})]))
        t_eval = time.perf_counter()
        ev = evaluate_views(model, scene, views, background, with_ssim=False, chunk=config.chunk_rays, stride=stride)
        state.eval_time_s += time.perf_counter() - t_eval
        state.last_test_psnr, evaluated_at = ev.psnr, state.step
        return ev.psnr

    scored_at = -1  # the step of the last score of the held-out tiles
    ended = False  # the fit's parameters are final (the best held-out ones put back)

    def score_held_out() -> float:
        """The held-out tiles' PSNR now (kept with a copy of the parameters when the best so far); the fit's own work,
        so its time counts."""
        nonlocal scored_at
        t_score = time.perf_counter()
        model.eval()
        try:
            with torch.no_grad():
                rgb, _ = render_rays(model, held, background, chunk=config.chunk_rays)
        finally:
            model.train()
        psnr = float(mse_to_psnr(((rgb.clamp(0, 1) - held.target) ** 2).mean().clamp(min=MSE_FLOOR)))
        if state.best is None or psnr > state.best.psnr:
            state.best = BestSnapshot.of(model, state.step, psnr)
        state.time_s += time.perf_counter() - t_score
        scored_at, state.holdout_psnr = state.step, psnr
        return psnr

    def out_of_patience() -> bool:
        return (held is not None and config.patience > 0 and state.best is not None
                and state.step - state.best.step >= config.patience and state.holdout_psnr <= state.best.psnr - config.patience_db)

    def end_with_best() -> list[str]:
        """Before the final evaluation: put back the parameters of the best held-out PSNR, if not the current ones."""
        nonlocal ended, optimizer
        if held is None or ended:
            return []
        ended = True
        if scored_at != state.step:
            score_held_out()
        best = state.best
        if best is None or best.step == state.step or state.holdout_psnr > best.psnr - config.patience_db:
            return []  # the last parameters score best, or within the noise of the best: they have trained longer
        t_restore = time.perf_counter()
        best.restore(model)
        optimizer = build_optimizer(model, config)  # the restored parameters' own (fresh) state, for the checkpoint
        state.time_s += time.perf_counter() - t_restore
        return note_decisions([Decision("holdout_best", best.step, (
            f"the fit ends with the parameters of step {best.step}, the best held-out PSNR ({best.psnr:.2f} dB), "
            f"not those of step {state.step}"), {"step": best.step, "holdout_psnr": round(best.psnr, 4),
                                                 "last_step": state.step})])

    def note_decisions(decisions: Sequence[Decision]) -> list[str]:
        for d in decisions:
            state.decisions[d.name] = d.as_json()
            log.info("iter %d: %s", state.step, d.reason)
        return [d.reason for d in decisions]

    def end_of_stage(stage: str) -> tuple[bool, list[str]]:
        """The model is about to leave ``stage``: does the fit stop here (target met), and what did the model decide?"""
        if config.target_psnr is not None and config.stage_end_eval and test_views:
            psnr = state.last_test_psnr if evaluated_at == state.step else partial_eval()
            met = psnr >= config.target_psnr
            reason = (f"end of the {stage} stage: test PSNR {psnr:.2f} dB {'>=' if met else '<'} target "
                      f"{config.target_psnr:g} dB{', the fit ends here' if met else ''}")
            evidence = {"test_psnr": round(psnr, 4), "target_psnr": config.target_psnr, "step": state.step}
            note_decisions([Decision(f"stop_after_{stage}", met, reason, evidence)])
            if met:
                return True, []
        # The evidence comes from its own seeded ray stream: deciding leaves the fit's rays unchanged.
        probe = torch.Generator().manual_seed(config.seed + 1_000_003 * (state.step + 1))
        t_decide = time.perf_counter()
        notes = note_decisions(model.decide(lambda n: sampler.sample(n, probe), background=background))
        state.time_s += time.perf_counter() - t_decide  # part of the fit's work, like the steps
        return False, notes

    ssim_skip = ssim_skip_reason(scene.height, scene.width) if config.final_ssim and test_views else None
    if ssim_skip:  # decided before training, recorded in summary.json: the final evaluation must not fail
        note_decisions([Decision("final_ssim", False, ssim_skip, {"height": scene.height, "width": scene.width})])

    lpips_skip = lpips_skip_reason(scene.height, scene.width) if config.final_lpips and test_views else None
    if lpips_skip:  # one line, decided before training; summary.json says why test_lpips is missing
        (log.warning if lpips_skip.startswith("LPIPS unavailable") else log.info)("%s", lpips_skip)
        note_decisions([Decision("final_lpips", False, lpips_skip, {"height": scene.height, "width": scene.width})])

    if tiles is None and not tiled and config.holdout_tile > 0 and "holdout_tiles" not in state.decisions:
        kinds = ",".join(config.holdout_scene_types) or "()"
        why = (f"{'an' if kind[0] in 'aeiou' else 'a'} {kind} scene, not one of holdout_scene_types={kinds}" if not tiled_kind
               else f"{n_train} training views > holdout_max_views={config.holdout_max_views}")
        note_decisions([Decision("holdout_tiles", False, f"{why}: no held-out tiles, every pixel trained on and every "
                                 "step run", {"views": n_train, "max_views": config.holdout_max_views, "kind": kind})])
    if tiles is not None and "holdout_tiles" not in state.decisions:
        share = tiles.held_fraction(scene.height, scene.width)
        note_decisions([Decision("holdout_tiles", tiles.side, (
            f"a {tiles.side} x {tiles.side} px tile of {len(tiles.views)} of the {n_train} training views is held out ({share:.1%} of "
            f"the pixels, {len(held)} scored every {config.holdout_every} steps): the fit ends with the parameters that "
            f"score best on them" + (f" and stops {config.patience} steps after the last improvement" if config.patience else "")),
            {"side": tiles.side, "fraction": round(share, 5), "scored_rays": len(held)})])

    if config.random_background and "random_background" not in state.decisions:  # asked for: say whether it applies
        kinds = ",".join(config.random_background)
        why = ("training rays are composited on a random colour each, test renders on the fixed background: every ray "
               "has to end on something" if random_background
               else "its photos have alpha, composited on the fixed background" if kind in config.random_background
               else f"{'an' if kind[0] in 'aeiou' else 'a'} {kind} scene, not one of random_background={kinds}")
        note_decisions([Decision("random_background", random_background,
                                 f"random background {'on' if random_background else 'off'}: {why}",
                                 {"kind": kind, "alpha": scene.alphas is not None})])

    guard = DivergenceGuard(config.guard, lr_scale=state.lr_guard_scale, events=state.guard_events)
    guard.retake(state.step, model, optimizer)

    def trainable() -> list[torch.Tensor]:
        return [p for g in optimizer.param_groups for p in g["params"]]

    while True:
        if state.step >= config.iters:
            state.stop_reason = f"reached {config.iters} iterations"
            break
        if config.time_budget_s is not None and state.time_s >= config.time_budget_s:
            state.stop_reason = f"time budget of {config.time_budget_s:g} s used"
            break
        if out_of_patience():
            state.stop_reason = (f"held-out PSNR no better than step {state.best.step}'s ({state.best.psnr:.2f} dB) "
                                 f"for {config.patience} steps, {state.best.psnr - state.holdout_psnr:.2f} dB below it now")
            break
        notes: list[str] = []
        stage = model.stage_ending(state.step)
        if stage is not None:
            stop, notes = end_of_stage(stage)
            if stop:
                state.stop_reason = f"target PSNR {config.target_psnr:g} dB reached at the end of the {stage} stage"
                break
        if config.target_psnr is not None and state.last_test_psnr is not None and state.last_test_psnr >= config.target_psnr:
            state.stop_reason = f"target PSNR {config.target_psnr:g} dB reached"
            break
        t0 = time.perf_counter()
        event = model.begin_step(state.step, fit_progress(config, state.step, state.time_s))
        note_decisions(event.decisions)
        if event.params_changed:
            # A grown grid (or a new stage) first dips, then passes the old: held-out scores start again from it.
            state.best = None
            optimizer = build_optimizer(model, config)
            guard.retake(state.step, model, optimizer, shape_changed=True)  # never roll back across a shape change
        if event.message:
            log.info("iter %d: %s", state.step, event.message)
        rollbacks: list[str] = []
        while True:  # a bad step is rolled back to the snapshot and tried again with fresh rays
            scale = lr_scale(config, state.step, state.time_s) * guard.lr_scale
            for g in optimizer.param_groups:
                g["lr"] = g["base_lr"] * scale
            batch, views = sampler.draw(config.batch_rays, gen)
            behind = (torch.rand(len(batch), 3, generator=gen).to(device) if random_background else background)
            out = model(batch, background=behind, train=True, generator=gen, target=batch.target)
            mse, loss = out.losses["mse"], total_loss(out.losses)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            loss_value, bad = guard.check_step(loss, trainable(), state.step + 1, _DIVERGED_HINT)
            if bad is None:
                break
            rollbacks.append(guard.rollback(state.step + 1, bad, model, optimizer, _DIVERGED_HINT).message())
            state.lr_guard_scale, state.guard_events = guard.lr_scale, list(guard.events)
        guard.accept(loss_value, state.step, model, optimizer)  # before the update: the snapshot holds checked values
        view_errors.add(views, out.rgb, batch.target)
        optimizer.step()
        if is_cuda:
            torch.cuda.synchronize(device)
        state.time_s += time.perf_counter() - t0
        state.step += 1
        record = StepRecord(
            iter=state.step,
            time_s=state.time_s,
            train_psnr=float(mse_to_psnr(mse.detach().clamp(min=MSE_FLOOR))),  # 100 dB, not inf, for a perfect batch
            samples_per_ray=out.samples_evaluated / len(batch),
            lr_scale=scale,
            event=joined_events(*notes, event.message, *rollbacks, *eval_notes),
        )
        eval_notes.clear()
        if held is not None and state.step % config.holdout_every == 0:
            record.holdout_psnr = score_held_out()
            if (config.holdout_release < 1 and fit_progress(config, state.step, state.time_s) >= config.holdout_release
                    and state.holdout_psnr > state.best.psnr - config.patience_db):
                notes_release = note_decisions([Decision("holdout_released", state.step, (
                    f"step {state.step}: the held-out score is still at its best ({state.holdout_psnr:.2f} dB) at "
                    f"{config.holdout_release:g} of the fit: the tiles are trained on from here, nothing is stopped or put back"),
                    {"step": state.step, "holdout_psnr": round(state.holdout_psnr, 4)})])
                record.event = joined_events(record.event, *notes_release)
                sampler.tiles, held, state.best = None, None, None
        last = (state.step >= config.iters or (config.time_budget_s is not None and state.time_s >= config.time_budget_s)
                or out_of_patience())
        if last:
            record.event = joined_events(record.event, *end_with_best())
        if test_views and last:
            final = final_eval()
            record.test_psnr = final.psnr
        elif test_views and config.eval_every > 0 and state.step % config.eval_every == 0:
            record.test_psnr = partial_eval()
        history.append(record)
        for cb in callbacks:
            cb(record, model, state)
        if should_checkpoint and config.checkpoint_every > 0 and state.step % config.checkpoint_every == 0:
            capture()
            should_checkpoint(state)
    end_with_best()
    if test_views and final is None:
        final = final_eval()
    capture()
    if should_checkpoint:
        should_checkpoint(state)
    return FitResult(state, final, history, view_errors.psnr())
