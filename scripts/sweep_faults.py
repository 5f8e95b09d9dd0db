#!/usr/bin/env python
"""Kill -9 a sweep at random moments, rerun it, and check every configuration ran exactly as planned.

Makes a tiny scene and a tiny grid SPEC in a temporary folder, starts ``nerfmeta sweep`` and
SIGKILLs its coordinator ``--kills`` times at random moments while fits run (each kill waits for the
1st to 3rd new fit, at random, to start, then a random 0-3 s more; its workers and fits die with it: they hold
PR_SET_PDEATHSIG), checks no process of the sweep outlives a kill, then runs the same
command to the end and checks the study: each planned configuration COMPLETE exactly once, with
exactly ``repeats`` finished fit run folders, and nothing else completed.

Usage: python scripts/sweep_faults.py [--kills 3] [--seed 0] [--workers 2]
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from nerfmeta.data.synthetic import write_tiny_scene
from nerfmeta.sweep.spec import load_spec
from nerfmeta.sweep.study import completed, open_storage, open_study, slot_of

SPEC = {
    "scenes": ["scene"], "backbone": "grid",
    "fixed": {"iters": 300, "eval_every": 0, "checkpoint_every": 0, "coarse_iters": 10, "growth_steps": [],
              "coarse_num_voxels": 1000, "renders": 0},
    "search": {"batch_rays": {"values": [64, 128, 256, 512, 1024], "default": 256}, "num_voxels": {"values": [4000, 16000]}},
    "objectives": {"test_psnr": "max", "time_s": "min", "peak_rss_mb": "min"}, "repeats": 2,
}


def group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kills", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--keep", default=None, help="work in this folder and keep it (default: a temporary one)")
    args = parser.parse_args()
    rng = random.Random(args.seed)
    root = Path(args.keep or tempfile.mkdtemp(prefix="sweep_faults_"))
    write_tiny_scene(root / "scene")
    (root / "spec.json").write_text(json.dumps(SPEC))
    out = root / "out"
    cmd = [sys.executable, "-m", "nerfmeta", "sweep", str(root / "spec.json"), "--out", str(out), "--workers", str(args.workers)]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    rows = []
    for k in range(args.kills):
        started = len(list((out / "logs").glob("*.log"))) if (out / "logs").is_dir() else 0
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env, start_new_session=True)
        t0 = time.time()
        target = started + rng.randint(1, 3)  # kill during the 1st to 3rd fit this run starts
        while proc.poll() is None and (len(list((out / "logs").glob("*.log"))) if (out / "logs").is_dir() else 0) < target:
            time.sleep(0.1)
        time.sleep(rng.uniform(0.0, 3.0))
        wait = time.time() - t0
        finished = proc.poll() is not None
        proc.send_signal(signal.SIGKILL) if not finished else None
        proc.wait()
        deadline = time.time() + 10
        while group_alive(proc.pid) and time.time() < deadline:
            time.sleep(0.2)
        orphans = group_alive(proc.pid)
        if orphans:
            os.killpg(proc.pid, signal.SIGKILL)
        done = len(list((out / "trials").glob("*/sweep.json"))) if (out / "trials").is_dir() else 0
        rows.append({"kill": k + 1, "after_s": round(wait, 1), "finished_before": finished, "orphans_left": orphans,
                     "fits_done_so_far": done})
        print(f"kill {k + 1}: SIGKILL after {wait:.1f} s; {done} fits finished so far; orphan processes: {orphans}")
    t0 = time.time()
    final = subprocess.run(cmd, env=env, capture_output=True, text=True)
    print(f"final run: exit {final.returncode} in {time.time() - t0:.1f} s")
    if final.returncode != 0:
        print(final.stderr[-2000:])
        return 1
    spec = load_spec(root / "spec.json")
    study = open_study(spec, open_storage(out, None), create=False)
    trials = study.get_trials(deepcopy=False)
    plan = spec.grid_plan()
    complete = completed(study)
    per_slot = {f"p{i}": [t for t in complete if slot_of(t) == f"p{i}"] for i in range(len(plan))}
    failed = [t for t in trials if t.state.name == "FAIL"]
    ok = all(len(v) == 1 for v in per_slot.values()) and len(complete) == len(plan)
    for slot, ts in per_slot.items():
        runs = ts[0].user_attrs.get("runs", []) if ts else []
        finished = [r for r in runs if (out / r / "summary.json").is_file() and (out / r / "sweep.json").is_file()]
        ok &= len(runs) == spec.repeats == len(finished)
        ok &= all(ts[0].params[k] == (json.dumps(list(v)) if isinstance(v, tuple) else v)
                  for k, v in plan[int(slot[1:])].items()) if ts else False
    no_orphans = not any(r["orphans_left"] for r in rows)
    print(f"planned {len(plan)} configurations x {spec.repeats} repeats; COMPLETE trials {len(complete)}; "
          f"per configuration {sorted(len(v) for v in per_slot.values())}; failed (killed, retried) trials {len(failed)}; "
          f"fit run folders {len(list((out / 'trials').glob('*/sweep.json')))}; orphans after kills: {not no_orphans}")
    print(json.dumps({"ok": bool(ok and no_orphans), "kills": rows, "planned": len(plan), "complete": len(complete),
                      "failed_retried": len(failed)}))
    return 0 if ok and no_orphans else 1


if __name__ == "__main__":
    raise SystemExit(main())
