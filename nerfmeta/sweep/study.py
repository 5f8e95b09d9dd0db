"""``nerfmeta sweep``: an Optuna study whose trials are ordinary fit run folders.

Layout of ``DIR/``::

    spec.json          the checked SPEC (a rerun must name the same one)
    study.journal      Optuna's journal storage (unless ``--storage URL`` names an RDB)
    trials/SLOT-rR/    one fit run folder per configuration and repeat (``nerfmeta fit``'s layout,
                       plus sweep.json: the process's peak RSS and wall time)
    logs/              each fit process's stderr
    report.md, *.png   the report (:mod:`nerfmeta.sweep.report`)

**One trial = one configuration.** Its repeats (seeds 0..R-1 as the fit seed) run inside it,
each fit in its own forked process (:mod:`nerfmeta.sweep.trial`), so that peak memory is that
process's own (``wait4``'s ``ru_maxrss``) and a crash or a kill takes one fit, not the sweep. The trial's values are the
means over repeats (and scenes); spreads, per-repeat figures and flags are user attributes.

**Slots and resuming.** Every planned configuration has a *slot*: ``pN`` for the grid design and the
default configuration (enqueued when the study is created), ``tN`` for a sampled one. A trial left
RUNNING by a killed worker is marked FAIL when the sweep starts again and its configuration is
enqueued once more under the same slot; its finished repeats are run folders with a summary and are
reused, the unfinished one is run again from scratch. A slot is counted once however often it was
retried, so each configuration is completed exactly once, with exactly ``repeats`` fits.

**Workers.** ``--workers N`` starts N worker processes on this machine; each asks the study for the
next trial (under a file lock in DIR, so the count of trials is exact) until the plan is used up.
Several machines join one study through ``--storage postgresql://...`` (Optuna's own distributed
mode), each with its own DIR for its run folders.
"""

from __future__ import annotations

import ctypes
import fcntl
import json
import logging
import os
import signal
import socket
import statistics
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from nerfmeta.errors import ConfigError, NerfmetaError
from nerfmeta.io import to_jsonable, write_json
from nerfmeta.runfolder import _pid_alive as pid_alive
from nerfmeta.sweep.spec import Knob, SweepSpec
from nerfmeta.sweep.trial import fork_fit

log = logging.getLogger(__name__)

SPEC_FILE = "spec.json"
JOURNAL = "study.journal"
TRIALS = "trials"
LOGS = "logs"
ASK_LOCK = "ask.lock"
MEASURE_FILE = "sweep.json"
"""What the sweep adds to a fit run folder: the fit process's peak RSS and wall time."""
MAX_RETRIES = 2
"""A configuration whose fit fails is tried this many more times, then given up (counted, not retried)."""
MAD_LIMIT = 3.0
"""A repeat's figure further than this many MADs from its repeats' median is flagged and re-run once."""
FLAGGED_FIGURES = ("time_s", "peak_rss_mb")
"""Figures checked for outliers besides the objectives (the study re-measured memory by hand)."""
POLL_S = 1.0
PLAN_WAIT_S = 60.0
"""How long a process that finds the study already created waits for its creator to enqueue the plan (after
that it enqueues what is missing itself: the creator was killed)."""


class TrialFailed(NerfmetaError):
    """A fit process of a trial exited with an error (one line: its last message)."""


# ---------------------------------------------------------------------------------------------------
# Optuna plumbing


def _optuna():
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    return optuna


def open_storage(out: Path, url: str | None):
    """The study's storage: the journal file in ``out`` by default, else Optuna's storage at ``url``."""
    optuna = _optuna()
    if url is None:
        backend = optuna.storages.journal.JournalFileBackend(str(out / JOURNAL))
        return optuna.storages.JournalStorage(backend)
    return optuna.storages.RDBStorage(url)


def make_sampler(spec: SweepSpec, worker: int = 0):
    """The SPEC's sampler for worker number ``worker``: each worker draws from its own seed (the same seed in
    two workers would propose the same configurations)."""
    optuna = _optuna()
    seed = spec.seed + 1_000_003 * worker
    if spec.sampler == "tpe":
        return optuna.samplers.TPESampler(seed=seed)
    if spec.sampler == "nsga2":
        return optuna.samplers.NSGAIISampler(seed=seed)
    return optuna.samplers.RandomSampler(seed=seed)  # grid: every trial is enqueued, nothing is sampled  # grid: every trial is enqueued, nothing is sampled


def _encode(value: Any) -> Any:
    """A knob value as Optuna stores it (its categorical choices must be scalars: lists become JSON text)."""
    return json.dumps(list(value)) if isinstance(value, (list, tuple)) else value


def _decode(knob: Knob, value: Any) -> Any:
    if knob.kind == "categorical" and isinstance(value, str) and any(isinstance(v, tuple) for v in knob.values):
        return tuple(json.loads(value))
    return value


def distributions(spec: SweepSpec) -> dict[str, Any]:
    optuna = _optuna()
    out = {}
    for k in spec.knobs:
        if k.kind == "categorical":
            out[k.name] = optuna.distributions.CategoricalDistribution([_encode(v) for v in k.values])
        elif k.kind == "int":
            out[k.name] = optuna.distributions.IntDistribution(int(k.low), int(k.high), log=k.log)
        else:
            out[k.name] = optuna.distributions.FloatDistribution(k.low, k.high, log=k.log)
    return out


def params_of(spec: SweepSpec, trial) -> dict[str, Any]:
    """A trial's configuration, knob name -> value (decoded)."""
    return {k.name: _decode(k, trial.params[k.name]) for k in spec.knobs if k.name in trial.params}


def open_study(spec: SweepSpec, storage, *, create: bool = True, worker: int = 0):
    """Create the study (and enqueue its plan) or load it; creating is atomic in the storage, so of several
    workers starting together exactly one enqueues the plan."""
    optuna = _optuna()
    name = spec.study_name()
    if create:
        try:
            study = optuna.create_study(storage=storage, study_name=name, directions=spec.directions,
                                        sampler=make_sampler(spec, worker))
        except optuna.exceptions.DuplicatedStudyError:
            study = optuna.load_study(study_name=name, storage=storage, sampler=make_sampler(spec, worker))
            deadline = time.monotonic() + PLAN_WAIT_S  # another process created it and may still be enqueuing
            while study.user_attrs.get("planned") is None and time.monotonic() < deadline:
                time.sleep(POLL_S)
    else:
        try:
            study = optuna.load_study(study_name=name, storage=storage, sampler=make_sampler(spec, worker))
        except KeyError:
            raise ConfigError(f"no study {name} in the storage; run the sweep first") from None
    if create and study.user_attrs.get("planned") is None:
        enqueue_plan(spec, study)
    return study


def enqueue_plan(spec: SweepSpec, study) -> None:
    """Enqueue the planned configurations not yet in the study (the grid design, or the default one)."""
    plan = spec.grid_plan() if spec.sampler == "grid" else [spec.default_params()]
    have = {t.user_attrs.get("slot") for t in study.get_trials(deepcopy=False)}
    for i, params in enumerate(plan):
        if f"p{i}" not in have:
            study.enqueue_trial({k: _encode(v) for k, v in params.items()}, user_attrs={"slot": f"p{i}", "retry": 0})
    study.set_user_attr("planned", len(plan))
    study.set_user_attr("spec_sha256", spec.digest())


def _state(name: str):
    return getattr(_optuna().trial.TrialState, name)


def slot_of(trial) -> str:
    return trial.user_attrs.get("slot") or f"t{trial.number}"


def used_slots(trials) -> set[str]:
    """Slots taken: every trial's but a surplus one's (a FAIL whose retry is enqueued shares its slot with the retry)."""
    return {slot_of(t) for t in trials if not t.user_attrs.get("surplus")}


def fail_trial(study, trial, reason: str) -> None:
    """Mark ``trial`` FAIL, saying why (its slot is enqueued again by :func:`enqueue_retries`)."""
    study._storage.set_trial_user_attr(trial._trial_id, "failed", reason)
    study._storage.set_trial_state_values(trial._trial_id, _state("FAIL"))


def enqueue_retries(study) -> list[str]:
    """Enqueue once more every slot that has no WAITING, RUNNING or COMPLETE trial, unless it failed
    :data:`MAX_RETRIES` + 1 times already (then it is given up). Idempotent, so a kill at any point of
    failing a trial leaves nothing lost and nothing doubled: the next start repairs it."""
    by_slot: dict[str, list] = {}
    for t in study.get_trials(deepcopy=False):
        if not t.user_attrs.get("surplus"):
            by_slot.setdefault(slot_of(t), []).append(t)
    retried = []
    for slot, trials in sorted(by_slot.items()):
        if any(t.state != _state("FAIL") for t in trials):
            continue
        if len(trials) > MAX_RETRIES:
            continue  # given up: counted as used, never run again
        last = max(trials, key=lambda t: t.number)
        study.enqueue_trial(dict(last.params), user_attrs={"slot": slot, "retry": len(trials)})
        retried.append(slot)
    return retried


def reconcile(study, *, exclusive: bool) -> list[int]:
    """Fail and re-enqueue the RUNNING trials whose worker is gone; return their numbers.

    ``exclusive``: this process owns the storage (the journal in DIR, whose lock it holds), so every
    RUNNING trial is a leftover. Otherwise (a shared RDB) only trials of this host whose process is gone.
    """
    host = socket.gethostname()
    found = []
    for t in study.get_trials(deepcopy=False, states=(_state("RUNNING"),)):
        worker = t.user_attrs.get("worker", "")
        whost, _, pid = worker.rpartition(":")
        dead = exclusive or (whost == host and pid.isdigit() and not pid_alive(int(pid)))
        if dead:
            fail_trial(study, t, f"its worker {worker or '?'} was gone (killed or crashed)")
            found.append(t.number)
    enqueue_retries(study)
    if found:
        log.info("trials %s were left running by a killed sweep: retried", found)
    return found


# ---------------------------------------------------------------------------------------------------
# One fit in its own process


def _die_with_parent() -> None:  # pragma: no cover - runs in the child
    """Linux: the child is killed when its parent dies, so a killed sweep leaves no orphan fit behind."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except OSError:
        pass


@dataclass(frozen=True)
class RepeatResult:
    """One fit of a trial: its run folder and figures (the summary's, with the process's peak RSS and wall time)."""

    folder: str
    seed: int
    figures: dict[str, float | None]


def _figures(summary: dict[str, Any], measure: dict[str, Any]) -> dict[str, float | None]:
    keys = ("test_psnr", "test_ssim", "test_lpips", "time_s", "eval_time_s", "samples_per_ray",
            "train_samples_per_ray", "n_parameters", "iters")
    out = {k: summary.get(k) for k in keys}
    out["peak_rss_mb"] = measure["peak_rss_mb"]
    out["wall_s"] = measure["wall_s"]
    return out


def run_repeat(spec: SweepSpec, out: Path, name: str, scene: str, params: dict[str, Any], seed: int) -> RepeatResult:
    """Fit ``scene`` with ``params`` and ``seed`` into ``out/trials/name`` in a child process (or read the
    finished run there)."""
    from nerfmeta.fit.loop import FitConfig
    from nerfmeta.fit.run import RunConfig

    folder = out / TRIALS / name
    if (folder / "summary.json").is_file() and (folder / MEASURE_FILE).is_file():
        summary = json.loads((folder / "summary.json").read_text())
        return RepeatResult(str(folder), seed, _figures(summary, json.loads((folder / MEASURE_FILE).read_text())))
    values = spec.run_values(params)
    run = {k: list(v) if isinstance(v, tuple) else v for k, v in values.get("run", {}).items()}
    config = RunConfig(scene=scene, backbone=spec.backbone, model=dict(values.get("model", {})),
                       fit=FitConfig(**{**values.get("fit", {}), "seed": seed}), init="scratch", **run)
    (out / LOGS).mkdir(parents=True, exist_ok=True)
    log_path = out / LOGS / f"{name}.log"
    child = fork_fit(to_jsonable(config), folder, log_path, before=_die_with_parent)
    if child.code != 0:
        lines = [line for line in log_path.read_text().splitlines() if line.strip()]
        raise TrialFailed(f"{name}: the fit exited with {child.code}: {lines[-1] if lines else 'no message'}")
    measure = {"peak_rss_mb": child.peak_rss_mb, "wall_s": round(child.wall_s, 3), "seed": seed,
               "cuda_peak_mb": child.result.get("cuda_peak_mb"),
               "note": "peak_rss_mb: ru_maxrss of the fit's own (forked) process, read by wait4"}
    write_json(folder / MEASURE_FILE, measure)
    summary = json.loads((folder / "summary.json").read_text())
    return RepeatResult(str(folder), seed, _figures(summary, measure))


# ---------------------------------------------------------------------------------------------------
# One trial: its repeats, outliers, aggregation


def mad_outliers(values: list[float], limit: float = MAD_LIMIT) -> list[int]:
    """Indices of ``values`` further than ``limit`` median absolute deviations from their median (needs 3+
    values and a MAD above 0: with two values each is exactly one MAD from their median)."""
    if len(values) < 3:
        return []
    med = statistics.median(values)
    mad = statistics.median(abs(v - med) for v in values)
    if mad <= 0:
        return []
    return [i for i, v in enumerate(values) if abs(v - med) > limit * mad]


def _spread(values: list[float]) -> dict[str, Any]:
    return {"mean": statistics.fmean(values), "std": statistics.pstdev(values) if len(values) > 1 else 0.0,
            "values": values}


def run_trial(spec: SweepSpec, out: Path, slot: str, params: dict[str, Any]) -> dict[str, Any]:
    """Run every scene and repeat of one configuration; return its figures (mean, spread, per repeat) and flags."""
    checked = tuple(dict.fromkeys([f for f, _ in spec.objectives] + list(FLAGGED_FIGURES)))
    per_scene: list[list[RepeatResult]] = []
    flags = []
    for si, scene in enumerate(spec.scenes):
        tag = f"{slot}-" + (f"s{si}-" if len(spec.scenes) > 1 else "")
        repeats = [run_repeat(spec, out, f"{tag}r{r}", scene, params, r) for r in range(spec.repeats)]
        for figure in checked:
            values = [r.figures.get(figure) for r in repeats]
            if any(v is None for v in values):
                continue
            for i in mad_outliers([float(v) for v in values]):
                again = run_repeat(spec, out, f"{tag}r{i}.rerun", scene, params, i)
                flags.append({"scene": scene, "repeat": i, "figure": figure, "value": values[i],
                              "median": statistics.median(values), "rerun": again.figures.get(figure)})
                repeats[i] = again
        per_scene.append(repeats)
    figures: dict[str, Any] = {}
    for figure in {*checked, "test_psnr", "test_ssim", "test_lpips", "time_s", "peak_rss_mb", "wall_s", "eval_time_s"}:
        rows = [[r.figures.get(figure) for r in reps] for reps in per_scene]
        if any(v is None for row in rows for v in row):
            figures[figure] = None
            continue
        means = [statistics.fmean(row) for row in rows]
        spread = _spread([v for row in rows for v in row])
        figures[figure] = {**spread, "mean": statistics.fmean(means)}
    return {"figures": figures, "flags": flags,
            "runs": [r.folder for reps in per_scene for r in reps]}


def objective_values(spec: SweepSpec, result: dict[str, Any]) -> list[float]:
    values = []
    for figure, _ in spec.objectives:
        entry = result["figures"].get(figure)
        if entry is None:
            raise TrialFailed(f"objective {figure}: the fits did not report it (see their summary.json notes)")
        values.append(float(entry["mean"]))
    return values


# ---------------------------------------------------------------------------------------------------
# Workers


@contextmanager
def file_lock(path: Path) -> Iterator[None]:
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)


def completed(study) -> list:
    return study.get_trials(deepcopy=False, states=(_state("COMPLETE"),))


def work_left(spec: SweepSpec, study) -> bool:
    """Whether a worker would find a trial to run (an enqueued one, or a slot of the plan not yet taken)."""
    trials = study.get_trials(deepcopy=False)
    if any(t.state == _state("WAITING") for t in trials):
        return True
    return spec.sampler != "grid" and len(used_slots(trials)) < spec.planned_trials()


def next_trial(spec: SweepSpec, study, out: Path):
    """Ask the study for the next planned trial, or None when the plan is used up (under DIR's ask lock)."""
    with file_lock(out / ASK_LOCK):
        if not work_left(spec, study):
            return None
        trial = study.ask(distributions(spec))
        if not trial.user_attrs.get("slot") and spec.sampler == "grid":
            # another machine took the last enqueued trial between our look and our ask
            trial.set_user_attr("surplus", True)
            study.tell(trial, state=_state("FAIL"))
            return None
        trial.set_user_attr("slot", slot_of(trial))
        trial.set_user_attr("worker", f"{socket.gethostname()}:{os.getpid()}")
        return trial


def work(spec: SweepSpec, out: Path, storage_url: str | None, worker: int = 0) -> int:
    """A worker's loop: ask, run, tell, until the plan is used up; returns the trials it completed."""
    study = open_study(spec, open_storage(out, storage_url), create=False, worker=worker)
    done = 0
    while True:
        t_ask = time.perf_counter()
        trial = next_trial(spec, study, out)
        if trial is None:
            return done
        slot = trial.user_attrs["slot"]
        params = params_of(spec, trial)
        overhead = time.perf_counter() - t_ask
        t0 = time.perf_counter()
        try:
            result = run_trial(spec, out, slot, params)
            values = objective_values(spec, result)
        except TrialFailed as err:
            log.warning("trial %d (%s): %s", trial.number, slot, err)
            with file_lock(out / ASK_LOCK):
                fail_trial(study, trial, str(err))
                enqueue_retries(study)
            continue
        trial_s = time.perf_counter() - t0
        t_tell = time.perf_counter()
        trial.set_user_attr("figures", result["figures"])
        trial.set_user_attr("flags", result["flags"])
        trial.set_user_attr("runs", [os.path.relpath(r, out) for r in result["runs"]])
        trial.set_user_attr("trial_s", round(trial_s, 3))
        study.tell(trial, values)
        overhead += time.perf_counter() - t_tell
        write_json(out / LOGS / f"overhead-{trial.number}.json",
                   {"trial": trial.number, "slot": slot, "bookkeeping_s": round(overhead, 4), "trial_s": round(trial_s, 3)})
        done += 1
