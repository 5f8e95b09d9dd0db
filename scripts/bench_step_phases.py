"""Where a fit step's time goes: the same fit as a finished run, timed by phase over a window of steps.

Refits the scene of ``RUN`` with its saved ``config.json`` (optionally changed by ``--set KEY=VALUE``, parsed and checked as
``nerfmeta fit --set``) into the new folder ``--out``, without its time budget: ``--warm`` steps untimed, then
``--steps`` steps timed. Each phase is the wall time spent in one function, summed over the window and divided by its
steps; phases nest (``forward`` holds ``sample`` and, for an SDF, ``evaluate`` and ``colour``), so they do not add up to
the step. Prints JSON: ms per step of the whole step and of each phase that ran, with the torch threads.

Phases: ``begin_step`` (the model's schedules, occupancy refreshes), ``rays`` (drawing the batch), ``forward`` (the
model's forward and losses), inside it ``sample`` (the march) and, for ``--backbone sdf``, ``evaluate`` (the SDF network
and its gradient) and ``colour`` (the colour branch); ``backward``; ``optimizer`` (Adam's step). BENCHMARKS.md,
*Surfaces: carving concavities*, section 15, has what it measured.

Usage::

    .venv/bin/python scripts/bench_step_phases.py RUN --out NEW_DIR [--warm 1500] [--steps 300] [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import functools
import json
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import nerfmeta  # noqa: E402,F401 - before torch, which then spins its OpenMP workers briefly (nerfmeta/__init__.py)
import torch  # noqa: E402

from nerfmeta.commands.fit import parse_overrides  # noqa: E402
from nerfmeta.errors import NerfmetaError  # noqa: E402
from nerfmeta.fields.registry import model_class  # noqa: E402
from nerfmeta.fit.run import RunConfig, run_fit  # noqa: E402
from nerfmeta.fit.sampler import RaySampler  # noqa: E402

MODEL_PHASES = {"begin_step": "begin_step", "forward": "forward", "sample": "forward.sample",
                "evaluate": "forward.evaluate", "get_outputs": "forward.colour"}
"""Methods of the backbone's class that are timed (when it has them), and their phase names."""


class PhaseTimer:
    """Sums the wall time of wrapped functions while :attr:`on`."""

    def __init__(self) -> None:
        self.on = False
        self.seconds: collections.Counter[str] = collections.Counter()

    def wrap(self, owner: Any, name: str, phase: str) -> None:
        """Replace ``owner.name`` by a timed call of itself (for the rest of the process)."""
        inner = getattr(owner, name)

        @functools.wraps(inner)
        def timed(*args: Any, **kwargs: Any) -> Any:
            if not self.on:
                return inner(*args, **kwargs)
            t = time.perf_counter()
            try:
                return inner(*args, **kwargs)
            finally:
                self.seconds[phase] += time.perf_counter() - t

        setattr(owner, name, timed)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", help="a finished fit run (its config.json is refitted)")
    ap.add_argument("--out", required=True, help="new folder for the timing fit (absent or empty)")
    ap.add_argument("--warm", type=int, default=1500, help="untimed steps first, at least 1 (default 1500)")
    ap.add_argument("--steps", type=int, default=300, help="timed steps (default 300)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="change a model setting")
    args = ap.parse_args()
    if args.warm < 1 or args.steps < 1:
        print(f"error: --warm {args.warm} --steps {args.steps}: need at least one step of each", file=sys.stderr)
        return 2
    config_path = Path(args.run) / "config.json"
    try:
        config = RunConfig.from_json(json.loads(config_path.read_text()))
    except (OSError, ValueError, TypeError, NerfmetaError) as exc:
        print(f"error: {config_path}: not a fit run's config ({exc})", file=sys.stderr)
        return 2
    try:
        changes = parse_overrides(args.set, config.backbone)
    except NerfmetaError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    fit = dataclasses.replace(config.fit, time_budget_s=None, iters=args.warm + args.steps + 1, eval_views=1,
                              eval_every=0, checkpoint_every=0)
    config = dataclasses.replace(config, model={**config.model, **changes}, fit=fit, renders=0, snapshot_iters=())

    timer = PhaseTimer()
    backbone_class = model_class(config.backbone)
    for method, phase in MODEL_PHASES.items():
        if hasattr(backbone_class, method):
            timer.wrap(backbone_class, method, phase)
    timer.wrap(torch.Tensor, "backward", "backward")
    timer.wrap(torch.optim.Adam, "step", "optimizer")
    timer.wrap(RaySampler, "sample", "rays")
    window: dict[str, float] = {}

    def on_step(record, model, state) -> None:  # noqa: ANN001 (the fit loop's Callback)
        if record.iter == args.warm:
            timer.on, window["start"] = True, time.perf_counter()
        elif record.iter == args.warm + args.steps:
            timer.on, window["seconds"] = False, time.perf_counter() - window["start"]

    try:
        run_fit(config, args.out, callbacks=[on_step])
    except NerfmetaError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if "seconds" not in window:
        print(f"error: the fit in {args.out} stopped before step {args.warm + args.steps} (see its summary.json)", file=sys.stderr)
        return 2
    per_step = {phase: round(1000.0 * s / args.steps, 2) for phase, s in sorted(timer.seconds.items())}
    print(json.dumps({"run": args.run, "backbone": config.backbone, "threads": torch.get_num_threads(),
                      "warm": args.warm, "steps": args.steps, "step_ms": round(1000.0 * window["seconds"] / args.steps, 2),
                      "phase_ms": per_step, "set": changes}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
