"""Fault injection: kill -9, two writers and a full disk against every command that writes a run folder.

Each case runs the real ``nerfmeta`` command line in subprocesses on tiny inputs (the analytic
spheres scene, and a tiny model zoo built with the recipe of ``tests/conftest.py``), with user
files planted beside the run folder, inside it (after a kill) and around the scene, then checks:

- **kill**: ``fit``, a routed ``fit --init auto --backbone nerf --compare scratch-nerf``, ``pretrain category`` and
  ``meta-train`` are killed with SIGKILL at a random moment, then continued with ``--resume``
  (and, when that is refused because nothing could be kept, started again). Half of the fit
  trials kill an ``--overwrite`` of a finished run: the finished run must still be there, whole.
- **two writers**: a second ``fit`` on the folder of a running one (with ``--overwrite``, then
  with ``--resume``) must be refused in one line while the first finishes untouched.
- **full disk**: the run folder sits on a small tmpfs (``mount -t tmpfs``; without the right to
  mount, a file size limit, ``RLIMIT_FSIZE``, which gives EFBIG instead of ENOSPC) that fills up
  during a new fit and during an ``--overwrite`` of a finished run: one line and exit 2, the
  previous run whole; with space again, the run completes.

A trial **survives** when every command it ran either succeeded or was refused in one line with
exit code 2 (no traceback), and the run folder ends complete (``summary.json`` or ``init.json``,
one metrics record per step, a readable checkpoint) or cleanly refused. **Lost** counts planted
user files (and scene files) that were changed or removed, over all trials: it must be 0.

Usage::

    .venv/bin/python scripts/faults.py [--trials 2] [--seed 0] [--work DIR] [--write]

The default run takes a few minutes on 2 loaded cores (most of it building the tiny zoo).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

SECTION = "## Fault injection"
PY = sys.executable
FIT_FAST = ["--init", "scratch", "--eval-every", "0", "--renders", "0", "--batch-rays", "256", "--checkpoint-every", "3",
            "--set", "coarse_iters=0", "--set", "growth_steps=[]", "--set", "num_voxels=4096"]
USER_TEXT = "a user's file: must survive every fault\n"


@dataclass
class Tally:
    """The outcome of one case's trials."""

    case: str
    trials: int = 0
    survived: int = 0
    lost: int = 0
    resumed: int = 0
    """Trials that continued from a checkpoint (the others were refused cleanly, or started again)."""
    notes: list[str] = field(default_factory=list)

    def add(self, ok: bool, lost: int, note: str, *, resumed: bool = False) -> None:
        self.trials += 1
        self.survived += int(ok and lost == 0)
        self.lost += lost
        self.resumed += int(resumed)
        if note and note not in self.notes:
            self.notes.append(note)


# --- running the command line -----------------------------------------------------------------------


def _env() -> dict[str, str]:
    env = dict(os.environ, NERFMETA_ZOO="none", OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    return env


def nerfmeta(args: Sequence[str], *, limit_bytes: int | None = None, timeout: float = 600) -> tuple[int, str]:
    """Run ``nerfmeta ARGS``; return (exit code, last stderr line that is not a progress bar)."""
    def limit() -> None:
        if limit_bytes is not None:
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of a kill
            resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))

    proc = subprocess.run([PY, "-m", "nerfmeta", *args], capture_output=True, text=True, env=_env(), timeout=timeout,
                          preexec_fn=limit)
    return proc.returncode, _verdict(proc.returncode, proc.stderr)


def _verdict(code: int, stderr: str) -> str:
    """``ok``, ``refused: LINE`` (exit 2, one error line, no traceback) or ``broken: ...``."""
    if "Traceback" in stderr:
        return "broken: " + stderr.strip().splitlines()[-1][:160]
    errors = [line for line in stderr.replace("\r", "\n").splitlines() if ": error: " in line]
    if code == 0:
        return "ok"
    if code == 2 and len(errors) == 1:
        return "refused: " + errors[0][:160]
    return f"broken: exit {code}: " + (stderr.strip().splitlines() or [""])[-1][:160]


def start(args: Sequence[str]) -> subprocess.Popen:
    """Start ``nerfmeta ARGS`` in the background (its output discarded: a full pipe would stall it)."""
    return subprocess.Popen([PY, "-m", "nerfmeta", *args], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=_env())


def kill_after(proc: subprocess.Popen, seconds: float) -> bool:
    """SIGKILL ``proc`` after ``seconds`` unless it ended; True when it was killed."""
    try:
        proc.wait(timeout=seconds)
        return False
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        return True


def timed(args: Sequence[str]) -> float:
    t0 = time.perf_counter()
    code, verdict = nerfmeta(args)
    if code != 0:
        raise SystemExit(f"reference run failed: nerfmeta {' '.join(args)}: {verdict}")
    return time.perf_counter() - t0


# --- what must survive --------------------------------------------------------------------------------


def plant(folder: Path, name: str = "thesis.tex") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    path.write_text(USER_TEXT)
    return path


def tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def lost_files(planted: Sequence[Path], scene: Path | None, scene_before: dict[str, bytes] | None) -> int:
    lost = sum(1 for p in planted if not p.is_file() or p.read_text() != USER_TEXT)
    if scene is not None and scene_before is not None:
        now = tree(scene)
        lost += sum(1 for k, v in scene_before.items() if now.get(k) != v)
    return lost


def complete(run: Path, *, steps_key: str, final: str, steps: int | None) -> bool:
    """A finished run: its final file, one metrics record per step (1..steps; None: the summary's
    ``iters``), a readable checkpoint."""
    from nerfmeta.runfolder import CHECKPOINT

    if not (run / final).is_file():
        return False
    try:
        records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
        steps = steps if steps is not None else int(json.loads((run / final).read_text())["iters"])
    except (OSError, ValueError, KeyError):
        return False
    if [r[steps_key] for r in records] != list(range(1, steps + 1)):
        return False
    from safetensors import safe_open

    try:
        with safe_open(str(run / CHECKPOINT), framework="pt") as f:
            json.loads(f.metadata()["nerfmeta"])
    except Exception:  # noqa: BLE001 - any unreadable checkpoint is a failed trial
        return False
    return True


# --- kill -9 and resume -------------------------------------------------------------------------------


@dataclass(frozen=True)
class KillCase:
    """A command to kill and resume."""

    name: str
    args: Callable[[Path], list[str]]
    """The command's arguments for the run folder ``out`` (without --resume / --overwrite)."""
    done: Callable[[Path], bool]
    """True for a finished run folder."""
    scene: Path | None = None
    """A folder the command reads, which must stay unchanged."""


def _short(verdict: str) -> str:
    """A refusal's reason without the folder it names (the same reason reads the same in every trial)."""
    reason = verdict.split(": error: ", 1)[-1]
    return reason.split(": ", 1)[-1][:70] if reason.startswith("/") else reason[:70]


def kill_trial(case: KillCase, work: Path, rng: random.Random, duration: float, *,
               overwrite_finished: bool) -> tuple[bool, int, str, bool]:
    """One kill -9 trial; returns (survived, lost, note, resumed from a checkpoint)."""
    out = work / "run"
    planted = [plant(work)]
    scene_before = tree(case.scene) if case.scene is not None else None
    if overwrite_finished:
        code, verdict = nerfmeta(case.args(out))
        if verdict != "ok":
            return False, 0, f"first run: {verdict}"
        before = {k: v for k, v in tree(out).items() if not k.startswith(".nerfmeta")}
    t0 = time.perf_counter()
    proc = start(case.args(out) + (["--overwrite"] if overwrite_finished else []))
    if not overwrite_finished:  # kill while the run writes, not while python starts
        while not (out / "config.json").is_file() and proc.poll() is None and time.perf_counter() - t0 < duration:
            time.sleep(0.05)
    left = max(0.2, duration - (time.perf_counter() - t0))
    killed = kill_after(proc, rng.uniform(0.0, 1.0) * left)
    if not killed and proc.returncode != 0:
        return False, 0, f"unkilled run exited {proc.returncode}", False
    if overwrite_finished:
        now = {k: v for k, v in tree(out).items() if not k.startswith(".nerfmeta")}
        if now != before and not case.done(out):
            return False, lost_files(planted, case.scene, scene_before), "the finished run was damaged by a killed --overwrite", False
        return True, lost_files(planted, case.scene, scene_before), "", False
    if out.is_dir():
        planted.append(plant(out, "notes.txt"))  # a user's file dropped into the run folder after the kill
    code, verdict = nerfmeta(case.args(out) + ["--resume"])
    note, resumed = "", verdict == "ok"
    if verdict.startswith("refused"):  # nothing to resume: a plain start must then work, or be refused cleanly
        note = "resume refused: " + _short(verdict)
        code, verdict = nerfmeta(case.args(out))
        if verdict.startswith("refused"):
            note += "; start refused: " + _short(verdict)
    ok = not verdict.startswith("broken") and (verdict != "ok" or case.done(out))
    if verdict.startswith("broken"):
        note = verdict
    return ok, lost_files(planted, case.scene, scene_before), note, resumed


def run_kill_case(case: KillCase, work: Path, trials: int, rng: random.Random, *, with_overwrite: bool = False) -> Tally:
    tally = Tally(f"kill -9 during {case.name}, then --resume")
    ref = work / "reference"
    duration = timed(case.args(ref / "run"))
    if not case.done(ref / "run"):
        raise SystemExit(f"{case.name}: the reference run is not complete")
    for i in range(trials):
        trial = work / f"trial{i}"
        survived, lost, note, resumed = kill_trial(case, trial, rng, duration, overwrite_finished=with_overwrite and i % 2 == 1)
        tally.add(survived, lost, note, resumed=resumed)
        shutil.rmtree(trial, ignore_errors=True)
    return tally


# --- two writers ----------------------------------------------------------------------------------------


def two_writers(scene: Path, work: Path, trials: int) -> Tally:
    tally = Tally("two writers on one folder")
    for i in range(trials):
        out = work / f"two{i}" / "run"
        planted = [plant(out.parent)]
        first = start([*("fit", str(scene), "--out", str(out)), *FIT_FAST, "--iters", "100000", "--time-budget", "10",
                       "--checkpoint-every", "50"])
        deadline = time.time() + 120
        while not (out / "config.json").is_file() and first.poll() is None and time.time() < deadline:
            time.sleep(0.2)
        second = [nerfmeta([*("fit", str(scene), "--out", str(out)), *FIT_FAST, "--iters", "6", flag])[1]
                  for flag in ("--overwrite", "--resume")]
        first.wait()
        ok = first.returncode == 0 and all(v.startswith("refused") and "in use" in v for v in second) \
            and complete(out, steps_key="iter", final="summary.json", steps=None)
        tally.add(ok, lost_files(planted, None, None), "" if ok else f"first exit {first.returncode}; second: {second}")
    return tally


# --- a full disk ----------------------------------------------------------------------------------------


def _mount_tmpfs(path: Path, size_kib: int) -> bool:
    path.mkdir(parents=True, exist_ok=True)
    try:
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_kib}k", "tmpfs", str(path)], capture_output=True)
    except OSError:
        return False
    return done.returncode == 0


def _umount(path: Path) -> None:
    subprocess.run(["umount", str(path)], capture_output=True)


def full_disk(scene: Path, work: Path, trials: int) -> Tally:
    """A new fit and an --overwrite of a finished fit, each on a disk that fills up; then with space again."""
    ref = work / "reference"
    args = lambda out, iters=9: ["fit", str(scene), "--out", str(out), *FIT_FAST, "--iters", str(iters)]  # noqa: E731
    nerfmeta(args(ref))
    ckpt = (ref / "checkpoint.safetensors").stat().st_size
    disk = work / "disk"
    tmpfs = _mount_tmpfs(disk, 4096)
    tally = Tally("full disk (" + ("tmpfs, ENOSPC" if tmpfs else "RLIMIT_FSIZE, EFBIG") + ")")
    try:
        for i in range(trials):
            overwrite = i % 2 == 1
            out = disk / f"run{i}"
            planted = [plant(disk, f"thesis{i}.tex")]
            before = None
            if overwrite:
                nerfmeta(args(out))
                before = {k: v for k, v in tree(out).items() if not k.startswith(".nerfmeta")}
            ballast = None
            limit = None
            if tmpfs:  # leave less room than a second checkpoint needs
                free = shutil.disk_usage(disk).free
                ballast = disk / f"ballast{i}.bin"
                ballast.write_bytes(b"\0" * max(0, free - ckpt // 2 - 64 * 1024))
                planted.append(ballast)
                ballast_bytes = ballast.read_bytes()
            else:
                limit = ckpt // 2
            code, verdict = nerfmeta(args(out, 12) + (["--overwrite"] if overwrite else []), limit_bytes=limit)
            refused = verdict.startswith("refused")
            intact = before is None or {k: v for k, v in tree(out).items() if not k.startswith(".nerfmeta")} == before
            if ballast is not None:
                kept = ballast.read_bytes() == ballast_bytes
                ballast.unlink()
                planted.remove(ballast)
            else:
                kept = True
            # with space again: resume (or start again when nothing could be kept)
            again, verdict2 = nerfmeta(args(out, 12) + ["--resume"])
            resumed = verdict2 == "ok"
            if verdict2.startswith("refused"):
                again, verdict2 = nerfmeta(args(out, 12) + ["--overwrite"])
            ok = refused and intact and kept and verdict2 == "ok" and complete(out, steps_key="iter", final="summary.json", steps=None)
            tally.add(ok, lost_files(planted, None, None) + (0 if kept else 1),
                      "" if ok else f"full: {verdict}; intact={intact}; again: {verdict2}", resumed=resumed)
            shutil.rmtree(out, ignore_errors=True)
    finally:
        if tmpfs:
            _umount(disk)
    return tally


# --- the tiny zoo -------------------------------------------------------------------------------------


def tiny_zoo(work: Path) -> tuple[Path, Path, Path]:
    """(zoo, collection, a new scene of a known category) built with the recipe of tests/conftest.py."""
    sys.path.insert(0, str(ROOT / "tests"))
    import torch

    from conftest import TINY_ZOO  # the tests' tiny recipe: the same zoo the routing tests use
    from nerfmeta.collection.generate import load_collection
    from pretrain.zoo import build_zoo

    torch.set_num_threads(1)
    zoo, scratch = work / "zoo", work / "zoo_work"
    if not (zoo / "manifest.json").is_file():
        shutil.rmtree(zoo, ignore_errors=True)
        build_zoo(TINY_ZOO, zoo, scratch, threads=1)
    coll = load_collection(scratch / "collection")
    scene = next(coll.scene_path(r) for r in coll.scenes if r.split == "test" and r.category == "chair")
    return zoo, scratch / "collection", scene


# --- main -----------------------------------------------------------------------------------------------


def table(tallies: Sequence[Tally]) -> str:
    lines = ["| case | trials | survived | lost | resumed from a checkpoint | notes |", "|---|---:|---:|---:|---:|---|"]
    for t in tallies:
        lines.append(f"| {t.case} | {t.trials} | {t.survived} | {t.lost} | {t.resumed} | {'; '.join(t.notes[:3]) or ''} |")
    return "\n".join(lines)


def section_text(tallies: Sequence[Tally], seconds: float, args: argparse.Namespace) -> str:
    total = sum(t.trials for t in tallies)
    survived = sum(t.survived for t in tallies)
    lost = sum(t.lost for t in tallies)
    return "\n".join([
        SECTION, "",
        f"`scripts/faults.py --trials {args.trials} --seed {args.seed}` ({time.strftime('%Y-%m-%d')}, 2-core CPU shared with "
        f"other jobs, {seconds:.0f} s{', the tiny zoo built beforehand' if args.keep_zoo else ''}): {survived} of {total} trials survived, {lost} user files lost. Each trial runs the real "
        "command line on tiny inputs with user files planted beside the run folder, inside it (after a kill) and in the "
        "scene; a trial survives when every command either succeeded or was refused in one line (exit 2), and the run "
        "folder ends complete or cleanly refused. A kill comes at a uniform moment between the run folder's first file "
        "and the end of an uninterrupted run (an --overwrite: of the whole run); *resumed* counts the trials that "
        "continued from a checkpoint rather than being refused (nothing kept yet) and started again.", "",
        table(tallies), "",
    ])


def write_benchmarks(text: str) -> None:
    from benchlib.sections import write_section  # beside this script (scripts/benchlib)

    write_section(ROOT / "BENCHMARKS.md", SECTION, text)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=2, help="trials per case (default 2)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the kill moments (default 0)")
    parser.add_argument("--work", type=Path, default=None, help="work folder (default: a temporary one, removed)")
    parser.add_argument("--keep-zoo", type=Path, default=None, help="build (or reuse) the tiny zoo here")
    parser.add_argument("--write", action="store_true", help="put the table into BENCHMARKS.md")
    args = parser.parse_args(argv)
    rng = random.Random(args.seed)
    t0 = time.perf_counter()
    work = args.work or Path(tempfile.mkdtemp(prefix="nerfmeta-faults-"))
    try:
        from nerfmeta.data.synthetic import write_tiny_scene

        scene = write_tiny_scene(work / "scene" / "spheres")
        zoo, collection, new_scene = tiny_zoo(args.keep_zoo or work)
        fit_args = lambda out: ["fit", str(scene), "--out", str(out), *FIT_FAST, "--iters", "12"]  # noqa: E731
        fit_done = lambda out: complete(out, steps_key="iter", final="summary.json", steps=12)  # noqa: E731
        routed_args = lambda out: ["fit", str(new_scene), "--out", str(out), "--init", "auto", "--zoo", str(zoo),  # noqa: E731
                                   "--backbone", "nerf", "--compare", "scratch-nerf", "--iters", "8", "--eval-every", "4", "--checkpoint-every", "2"]
        routed_done = lambda out: (complete(out, steps_key="iter", final="summary.json", steps=8)  # noqa: E731
                                   and "comparison" in json.loads((out / "summary.json").read_text())
                                   and complete(out / "compare" / "scratch-nerf", steps_key="iter", final="summary.json", steps=8))
        category_args = lambda out: ["pretrain", "category", str(collection), "--category", "chair", "--out", str(out),  # noqa: E731
                                     "--backbone", "nerf", "--iters", "12", "--batch-rays", "64", "--checkpoint-every", "3",
                                     *[a for k, v in (("depth", 2), ("width", 16), ("skips", "[]"), ("n_samples", 8))
                                       for a in ("--set", f"{k}={v}")]]
        category_done = lambda out: complete(out, steps_key="iter", final="init.json", steps=12)  # noqa: E731
        meta_args = lambda out: ["meta-train", str(collection), "--out", str(out), "--backbone", "nerf", "--meta-steps", "8",  # noqa: E731
                                 "--checkpoint-every", "2", "--meta-batch", "2", "--support-rays", "32", "--query-rays", "32",
                                 "--inner-steps", "1", "--eval-tasks", "1",
                                 *[a for k, v in (("depth", 2), ("width", 16), ("skips", "[]"), ("n_samples", 8))
                                   for a in ("--set", f"{k}={v}")]]
        meta_done = lambda out: complete(out, steps_key="step", final="summary.json", steps=8)  # noqa: E731
        cases = [
            (KillCase("fit (half of them an --overwrite of a finished run)", fit_args, fit_done, scene), True),
            (KillCase("fit --init auto --backbone nerf --compare scratch-nerf", routed_args, routed_done, new_scene), False),
            (KillCase("pretrain category", category_args, category_done, collection), False),
            (KillCase("meta-train", meta_args, meta_done, collection), False),
        ]
        tallies = []
        for i, (case, with_overwrite) in enumerate(cases):
            tally = run_kill_case(case, work / f"case{i}", args.trials * (2 if with_overwrite else 1), rng,
                                  with_overwrite=with_overwrite)
            print(f"{tally.case}: {tally.survived}/{tally.trials} survived, {tally.lost} lost", flush=True)
            tallies.append(tally)
        for tally in (two_writers(scene, work / "two", max(1, args.trials // 2)), full_disk(scene, work / "full", args.trials)):
            print(f"{tally.case}: {tally.survived}/{tally.trials} survived, {tally.lost} lost", flush=True)
            tallies.append(tally)
    finally:
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)
    text = section_text(tallies, time.perf_counter() - t0, args)
    print(text)
    if args.write:
        write_benchmarks(text)
    return 0 if all(t.lost == 0 and t.survived == t.trials for t in tallies) else 1


if __name__ == "__main__":
    raise SystemExit(main())
