"""The coordinator of ``nerfmeta sweep``: open DIR, create or continue the study, start the workers,
print a line per finished trial, write the report (see :mod:`nerfmeta.sweep.study` for the layout)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from nerfmeta.errors import ConfigError, NerfmetaError
from nerfmeta.io import write_json
from nerfmeta.runfolder import is_run_of, run_folder
from nerfmeta.sweep.report import write_report
from nerfmeta.sweep.spec import SweepSpec
from nerfmeta.sweep.study import (LOGS, POLL_S, SPEC_FILE, _die_with_parent, completed, open_storage, open_study,
                                  params_of, reconcile, slot_of, work_left)


@dataclass(frozen=True)
class TrialDone:
    """A trial that completed while the sweep ran (for the progress line)."""

    number: int
    slot: str
    params: dict[str, Any]
    figures: dict[str, Any]
    done: int
    total: int
    eta_s: float | None


def check_spec_matches(out: Path, spec: SweepSpec) -> None:
    saved = out / SPEC_FILE
    if saved.is_file():
        old = SweepSpec.from_json(json.loads(saved.read_text()))
        if old.digest() != spec.digest():
            raise ConfigError(f"{out}: holds a sweep of another SPEC ({saved}); choose another --out, or rerun that SPEC")


def _spawn_worker(out: Path, storage: str | None, index: int) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "nerfmeta.sweep.worker", str(out), "--index", str(index)] + (["--storage", storage] if storage else [])
    return subprocess.Popen(cmd, preexec_fn=_die_with_parent)


def run_sweep(spec: SweepSpec, out: str | Path, *, storage: str | None = None, workers: int = 1,
              on_trial: Callable[[TrialDone], None] | None = None) -> Path:
    """Run (or continue) the sweep of ``spec`` in ``out``; write the report; return ``out``."""
    if workers < 1:
        raise ConfigError(f"--workers {workers}: must be 1 or more")
    out = Path(os.path.abspath(out))
    resume = is_run_of(out, "sweep")
    if resume:
        check_spec_matches(out, spec)
    with run_folder(out, "sweep", resume=resume, protect=spec.scenes) as run:
        if not (out / SPEC_FILE).is_file():
            write_json(out / SPEC_FILE, spec.as_json())
        study = open_study(spec, open_storage(out, storage))
        reconcile(study, exclusive=storage is None)
        total = spec.planned_trials()
        seen = {t.number for t in completed(study)}
        start, done_here = time.perf_counter(), 0
        procs = [_spawn_worker(out, storage, i) for i in range(workers)] if work_left(spec, study) else []
        try:
            while True:
                running = [p for p in procs if p.poll() is None]
                for t in sorted(completed(study), key=lambda t: t.number):
                    if t.number in seen:
                        continue
                    seen.add(t.number)
                    done_here += 1
                    left = max(0, total - len({slot_of(x) for x in completed(study)}))
                    rate = (time.perf_counter() - start) / done_here
                    if on_trial:
                        on_trial(TrialDone(t.number, slot_of(t), params_of(spec, t), t.user_attrs.get("figures", {}),
                                           len({slot_of(x) for x in completed(study)}), total, rate * left / workers))
                if not running:
                    break
                time.sleep(POLL_S)
        finally:
            for p in procs:
                if p.poll() is None:
                    p.terminate()
                    p.wait()
        write_json(out / LOGS / f"session-{os.getpid()}-{int(time.time())}.json",
                   {"wall_s": round(time.perf_counter() - start, 3), "workers": len(procs), "trials_completed": done_here})
        bad = [p.returncode for p in procs if p.returncode]
        if bad:
            raise NerfmetaError(f"{out}: {len(bad)} worker(s) failed (exit {bad[0]}); see {out / LOGS}; rerun to continue")
        write_report(spec, study, run.dir)
    return out


def redraw_report(out: str | Path, storage: str | None = None) -> Path:
    """``nerfmeta sweep DIR --report``: the report of the study in DIR, from storage, running nothing."""
    out = Path(os.path.abspath(out))
    if not is_run_of(out, "sweep") or not (out / SPEC_FILE).is_file():
        raise ConfigError(f"{out}: not a sweep folder (no {SPEC_FILE}); give the --out folder of a sweep")
    spec = SweepSpec.from_json(json.loads((out / SPEC_FILE).read_text()))
    with run_folder(out, "sweep", resume=True) as run:
        study = open_study(spec, open_storage(out, storage), create=False)
        write_report(spec, study, run.dir)
    return out
