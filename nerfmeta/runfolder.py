"""One run folder for every command that writes one: fits, category models, meta-training,
classifiers, collections, the demo and sweeps.

The rules, the same for every kind of run:

- **Ours.** A folder nerfmeta made holds a marker file :data:`MARKER` naming its kind
  (``fit``, ``category``, ``meta``, ``classifier``, ``collection``, ``poses``, ``demo``). A folder written
  before the marker existed is recognised by the files its kind always wrote (see
  :attr:`Layout.legacy`: e.g. a fit's ``config.json`` with a ``scene`` key beside a
  ``metrics.jsonl``); the marker is added when such a folder is resumed or replaced.
- **Never replace what is not ours.** ``--overwrite`` only replaces a folder that is ours, of the
  same kind, and holds nothing its kind does not write (:func:`foreign_entries`: a user's
  ``thesis.tex`` beside the run is a refusal, not a deletion). The folder of a protected path
  (the scene being fitted) and any of its parents are never a run folder.
- **Build aside.** With ``--overwrite`` (and always for kinds that have no resume: classifiers,
  collections, the demo) the new run is built in a hidden sibling ``.NAME.partial-PID`` and
  swapped in only when it is complete (:meth:`RunFolder.commit`); a failure or a kill before that
  leaves the previous run untouched. A kill leaves the sibling behind; the next run on the same
  folder removes it once its process is gone.
- **One writer.** A run holds an exclusive ``flock`` on :data:`LOCK` inside its folder while it
  writes; a second process on the same folder is refused in one line. The kernel drops the lock
  when a process dies, so the lock of a killed run is simply taken over.
- **No half files.** Every file is written to a temporary name and renamed (:mod:`nerfmeta.io`);
  the temporary files a kill leaves behind are removed when the folder is opened again.

Everything a user can cause raises :class:`RunFolderError`, a one-line
:class:`~nerfmeta.errors.NerfmetaError` that the CLI prints before exiting with code 2.
"""

from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import re
import shutil
from contextlib import contextmanager
from dataclasses import dataclass
from fnmatch import fnmatch
from pathlib import Path
from typing import Any, Iterator, Sequence

from nerfmeta.errors import ConfigError, NerfmetaError
from nerfmeta.io import write_json

log = logging.getLogger(__name__)

MARKER = ".nerfmeta-run"
"""Marker file of a folder nerfmeta made: JSON ``{"format": ..., "kind": ...}``."""
LOCK = ".nerfmeta-lock"
"""Lock file a writing process holds an exclusive ``flock`` on (it holds that process's pid)."""
MARKER_FORMAT = "nerfmeta-run-1"

_TMP_RE = re.compile(r"^\..+\.[A-Za-z0-9_]{8}\.tmp$")  # io.atomic_path's temporary names (mkstemp's 8 characters)
_ASIDE_RE = re.compile(r"^\.(?P<name>.+)\.(?:partial|old)-(?P<pid>\d+)$")


class RunFolderError(ConfigError):
    """A run folder (the ``--out`` value) cannot be created, replaced, resumed or locked (one line naming it)."""


@dataclass(frozen=True)
class Layout:
    """What one kind of run folder holds at its top level."""

    kind: str
    """The kind recorded in the marker."""
    command: str
    """The command that writes it (for messages)."""
    files: tuple[str, ...]
    """Glob patterns of the files a run of this kind writes."""
    folders: tuple[str, ...] = ()
    """Glob patterns of its sub-folders (their contents are its own)."""
    runs: tuple[str, ...] = ()
    """Kinds of run folders it may hold as sub-folders (a demo holds fits)."""
    legacy: tuple[str, ...] = ()
    """Files that together mark a folder of this kind written before the marker existed (empty: none recognised)."""
    legacy_key: str | None = None
    """A key the first legacy file (JSON) of such a folder holds, to tell kinds with the same files apart."""


LAYOUTS: dict[str, Layout] = {layout.kind: layout for layout in (
    Layout("fit", "fit", ("config.json", "metrics.jsonl", "checkpoint.safetensors", "summary.json", "route.json", "report.md",
                   "psnr_vs_iter.png", "psnr_vs_time.png", "comparison_renders_view_*.png",
                   "bench.json", "bench_zoo_sha256.txt",  # what scripts/bench_*.py add to their fits
                   "sweep.json"),  # and what nerfmeta sweep adds (the fit process's peak RSS)
           folders=("renders", "snapshots", "compare"), legacy=("config.json", "metrics.jsonl"), legacy_key="scene"),
    Layout("category", "pretrain category", ("config.json", "metrics.jsonl", "checkpoint.safetensors", "psnr_vs_iter.png", "model.safetensors",
                        "init.json"), legacy=("config.json", "metrics.jsonl"), legacy_key="category"),
    Layout("meta", "meta-train", ("config.json", "metrics.jsonl", "checkpoint.safetensors", "model.safetensors", "init.json",
                    "summary.json", "query_psnr_vs_step.png"), legacy=("config.json", "metrics.jsonl"), legacy_key="algo"),
    Layout("classifier", "classifier train", ("classifier.json", "model.safetensors", "history.json", "training_curve.png"),
           legacy=("classifier.json",)),
    Layout("collection", "make-collection", ("collection.json", "preview.png"), legacy=("collection.json",)),
    Layout("sweep", "sweep", ("spec.json", "study.journal", "study.journal.lock", "ask.lock", "report.md", "*.png"),
           folders=("trials", "logs", "plots")),
    Layout("demo", "demo", (), folders=("scenes", "report"), runs=("fit",), legacy=("scenes/collection.json",)),
    Layout("poses", "poses", ("transforms.json", "sfm.json"), folders=("images", "colmap")),
    Layout("frames", "fit VIDEO / poses VIDEO", ("frames.json", "frame_*.jpg")),  # a video's frames, in the cache
)}


def layout(kind: str) -> Layout:
    if kind not in LAYOUTS:
        raise ValueError(f"unknown run kind {kind!r}; known: {', '.join(LAYOUTS)}")
    return LAYOUTS[kind]


# ---------------------------------------------------------------------------------------------
# Recognising a folder


def marker_kind(path: Path) -> str | None:
    """The kind in ``path``'s marker, None without a readable one."""
    try:
        doc = json.loads((path / MARKER).read_text())
    except (OSError, ValueError):
        return None
    return doc.get("kind") if isinstance(doc, dict) and doc.get("format") == MARKER_FORMAT else None


def is_run_of(path: Path, kind: str) -> bool:
    """True when ``path`` is a folder nerfmeta made for a run of ``kind`` (marker, or the files of an older version)."""
    if not path.is_dir() or path.is_symlink():
        return False
    found = marker_kind(path)
    if found is not None:
        return found == kind
    spec = layout(kind)
    if not spec.legacy or not all((path / name).is_file() for name in spec.legacy):
        return False
    if spec.legacy_key is None:
        return True
    try:
        doc = json.loads((path / spec.legacy[0]).read_text())
    except (OSError, ValueError):
        return False
    return isinstance(doc, dict) and spec.legacy_key in doc


def _collection_folders(path: Path) -> tuple[str, ...]:
    """The top-level folders a collection's ``collection.json`` lists scenes in."""
    try:
        doc = json.loads((path / "collection.json").read_text())
        return tuple({Path(str(s["path"])).parts[0] for s in doc.get("scenes", ())})
    except (OSError, ValueError, KeyError, TypeError, IndexError, AttributeError):
        return ()


def _ours_by_name(name: str) -> bool:
    return name in (MARKER, LOCK) or bool(_TMP_RE.match(name)) or bool(_ASIDE_RE.match(name))


def foreign_entries(path: Path, kind: str) -> list[str]:
    """Names at the top of ``path`` that a run of ``kind`` does not write (what ``--overwrite`` must not delete)."""
    spec = layout(kind)
    folders = spec.folders + (_collection_folders(path) if kind == "collection" else ())
    foreign = []
    for entry in sorted(path.iterdir()):
        name = entry.name
        if _ours_by_name(name):
            continue
        if entry.is_symlink():
            foreign.append(name)
        elif entry.is_dir():
            if any(fnmatch(name, p) for p in folders):
                continue
            if any(is_run_of(entry, k) and not foreign_entries(entry, k) for k in spec.runs):
                continue
            foreign.append(name + "/")
        elif not any(fnmatch(name, p) for p in spec.files):
            foreign.append(name)
    return foreign


def has_content(path: Path) -> bool:
    """True when ``path`` is a folder holding anything besides the marker, the lock and orphan temporary files."""
    return path.is_dir() and any(not _ours_by_name(e.name) for e in path.iterdir())


def _check_protected(out: Path, protect: Sequence[str | os.PathLike]) -> None:
    target = Path(os.path.realpath(out))
    for p in protect:
        kept = Path(os.path.realpath(p))
        if target == kept:
            raise RunFolderError(f"{out}: is {p}, which this run reads; choose another --out folder")
        if target in kept.parents:
            raise RunFolderError(f"{out}: holds {p}, which this run reads; choose an --out folder outside it")


def check_target(out: str | os.PathLike, kind: str, *, resume: bool = False, overwrite: bool = False,
                 protect: Sequence[str | os.PathLike] = ()) -> None:
    """Raise :class:`RunFolderError` unless ``out`` may take a run of ``kind`` in this mode; writes nothing.

    Args:
        out: the run folder.
        kind: one of :data:`LAYOUTS`.
        resume: continue the run in ``out`` (it must be ours, of ``kind``).
        overwrite: replace the run in ``out`` (only if ours, of ``kind``, holding nothing else).
        protect: paths the run reads (the scene): ``out`` may be neither one nor a parent of one.
    """
    out = Path(out)
    if resume and overwrite:
        raise RunFolderError("--resume and --overwrite cannot be combined")
    _check_protected(out, protect)
    if out.is_symlink() and not out.exists():
        raise RunFolderError(f"{out}: is a dangling symbolic link; choose another --out")
    if out.exists() and not out.is_dir():
        raise RunFolderError(f"{out}: exists and is not a folder; choose another --out")
    if out.is_dir():
        _refuse_if_locked(out)
    spec = layout(kind)
    what = f"{spec.command} run"
    if resume:
        if not is_run_of(out, kind):
            raise RunFolderError(f"{out}: not a {what} folder; nothing to resume")
        return
    if not has_content(out):
        return
    if not overwrite:
        raise RunFolderError(f"{out}: folder exists and is not empty; pass --overwrite to replace it"
                             + (" or --resume to continue it" if kind in ("fit", "meta", "category") else ""))
    if not is_run_of(out, kind):
        found = marker_kind(out)
        why = (f"it holds a {layout(found).command} run" if found in LAYOUTS else
               f"it has no {MARKER} marker" + (f" and no {' + '.join(spec.legacy)}" if spec.legacy else ""))
        raise RunFolderError(f"{out}: not a {what} folder ({why}); --overwrite only replaces a folder nerfmeta made "
                             "for the same command; choose another --out")
    foreign = foreign_entries(out, kind)
    if foreign:
        shown = ", ".join(foreign[:3]) + (f" and {len(foreign) - 3} more" if len(foreign) > 3 else "")
        raise RunFolderError(f"{out}: holds {shown}, which a {what} does not write; --overwrite never deletes "
                             "other files: move them out or choose another --out")


# ---------------------------------------------------------------------------------------------
# Locks, markers, orphans


def _holder(path: Path) -> str:
    try:
        pid = (path / LOCK).read_text().strip()
    except OSError:
        pid = ""
    return f" (pid {pid})" if pid.isdigit() else ""


def _refuse_if_locked(path: Path) -> None:
    """Raise if another process holds the lock of ``path`` (creates nothing)."""
    try:
        fd = os.open(path / LOCK, os.O_RDONLY)
    except OSError:
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        raise RunFolderError(f"{path}: in use by another nerfmeta process{_holder(path)}; wait for it to finish "
                             "or choose another --out") from None
    finally:
        os.close(fd)  # closing drops a lock taken here


def _lock(path: Path) -> int:
    """Take the exclusive lock of the folder ``path`` (created if missing) and record this pid; return its fd."""
    fd = os.open(path / LOCK, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise RunFolderError(f"{path}: in use by another nerfmeta process{_holder(path)}; wait for it to finish "
                             "or choose another --out") from None
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    return fd


def _unlock(fd: int) -> None:
    try:
        fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)


def _write_marker(path: Path, kind: str) -> None:
    from nerfmeta import __version__

    write_json(path / MARKER, {"format": MARKER_FORMAT, "kind": kind, "nerfmeta": __version__})


def clean_orphans(path: Path) -> list[Path]:
    """Remove the temporary files a kill left in ``path`` and its sub-folders (call with the lock held)."""
    removed = []
    for root, dirs, files in os.walk(path):
        dirs[:] = [d for d in dirs if not _ASIDE_RE.match(d)]
        for name in files:
            if _TMP_RE.match(name):
                p = Path(root) / name
                p.unlink(missing_ok=True)
                removed.append(p)
    if removed:
        log.info("%s: removed %d temporary file(s) left by an interrupted run", path, len(removed))
    return removed


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def clean_stale_asides(out: Path) -> None:
    """Remove ``.NAME.partial-PID`` / ``.NAME.old-PID`` siblings of ``out`` whose process is gone (ours: they hold a marker)."""
    if not out.parent.is_dir():
        return
    for entry in out.parent.iterdir():
        m = _ASIDE_RE.match(entry.name)
        if not m or m["name"] != out.name or not entry.is_dir() or entry.is_symlink():
            continue
        if int(m["pid"]) != os.getpid() and _pid_alive(int(m["pid"])):
            continue
        if marker_kind(entry) is not None:
            shutil.rmtree(entry)
            log.info("removed %s, left by an interrupted run", entry)


# ---------------------------------------------------------------------------------------------
# An open run folder


def relocated(value: Any, old: str, new: str) -> Any:
    """``value`` (JSON) with every path string under ``old`` moved under ``new``."""
    if isinstance(value, str) and (value == old or value.startswith(old + os.sep)):
        return new + value[len(old):]
    if isinstance(value, list):
        return [relocated(v, old, new) for v in value]
    if isinstance(value, dict):
        return {k: relocated(v, old, new) for k, v in value.items()}
    return value


def relocate_paths(root: Path, old: Path, new: Path) -> None:
    """Rewrite the paths under ``old`` recorded in the JSON files under ``root`` to lie under ``new``
    (a run built aside records where it was built, e.g. the demo's generated scenes)."""
    for path in sorted(root.rglob("*.json")):
        try:
            doc = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        moved = relocated(doc, str(old), str(new))
        if moved != doc:
            write_json(path, moved)


class RunFolder:
    """An open, locked run folder. Files go to :attr:`dir`: the folder itself, or the sibling the run
    is built in (``aside``) until :meth:`commit` swaps it in.

    Attributes:
        path: the run folder (absolute).
        dir: where to write now.
        kind: the run's kind.
    """

    def __init__(self, path: Path, dir: Path, kind: str, locks: list[int], *, aside: bool, created: bool):
        self.path, self.dir, self.kind = path, dir, kind
        self._locks = locks
        self._aside, self._created = aside, created
        self._committed = False
        self._keep_work = False

    def commit(self) -> None:
        """Swap a run built aside into place (the previous run, if any, is removed); no-op in place."""
        if not self._aside or self._committed:
            return
        out, work = self.path, self.dir
        trash = out.parent / f".{out.name}.old-{os.getpid()}"
        if (out.exists() and not out.is_dir()) or (has_content(out) and (not is_run_of(out, self.kind)
                                                                         or foreign_entries(out, self.kind))):
            self._keep_work = True  # a finished run is never thrown away
            raise RunFolderError(f"{out}: changed during the run and is no longer a {layout(self.kind).command} run of "
                                 f"ours; the new run is left in {work}")
        if has_content(out):
            os.replace(out, trash)
        elif out.is_dir():
            shutil.rmtree(out)  # empty but for our marker, lock or temporary files
        try:
            os.replace(work, out)
        except OSError:
            if trash.exists() and not out.exists():
                os.replace(trash, out)
            raise
        self._committed = True
        self.dir = out
        relocate_paths(out, work, out)
        old_locks, self._locks = self._locks[:-1], self._locks[-1:]  # the last lock is the new folder's
        for fd in old_locks:
            _unlock(fd)
        shutil.rmtree(trash, ignore_errors=True)

    def close(self) -> None:
        """Release the locks; drop an uncommitted run built aside, or a new folder that received nothing."""
        for fd in self._locks:
            _unlock(fd)
        self._locks = []
        if self._aside and not self._committed and not self._keep_work:
            shutil.rmtree(self.dir, ignore_errors=True)
        elif not self._aside and not has_content(self.dir) and self.dir.is_dir():
            for name in (MARKER, LOCK):
                (self.dir / name).unlink(missing_ok=True)
            if self._created and not any(self.dir.iterdir()):
                self.dir.rmdir()


def open_run(out: str | os.PathLike, kind: str, *, resume: bool = False, overwrite: bool = False, aside: bool = False,
             protect: Sequence[str | os.PathLike] = ()) -> RunFolder:
    """Check, lock and open the run folder ``out`` for a run of ``kind`` (see the module rules).

    Args:
        out: the run folder.
        kind: one of :data:`LAYOUTS`.
        resume: continue the run there (in place).
        overwrite: replace a previous run there; the new one is built aside.
        aside: build aside even for a new folder (kinds without resume, so that ``out`` never holds half a run).
        protect: paths the run reads (see :func:`check_target`).

    Raises:
        RunFolderError: ``out`` cannot take the run, or another process holds it.
    """
    out = Path(os.path.abspath(out))
    check_target(out, kind, resume=resume, overwrite=overwrite, protect=protect)
    try:
        return _open(out, kind, resume=resume, replacing=overwrite and has_content(out), aside=aside)
    except OSError as err:
        full = disk_full_error(err, err.filename or out)
        raise full or RunFolderError(f"{err.filename or out}: cannot write there ({err.strerror}); "
                                     "choose another --out") from None


def _open(out: Path, kind: str, *, resume: bool, replacing: bool, aside: bool) -> RunFolder:
    if aside or replacing:
        out.parent.mkdir(parents=True, exist_ok=True)
        locks = [_lock(out)] if out.is_dir() else []
        clean_stale_asides(out)
        work = out.parent / f".{out.name}.partial-{os.getpid()}"
        if work.exists():
            shutil.rmtree(work)
        work.mkdir()
        _write_marker(work, kind)
        locks.append(_lock(work))
        return RunFolder(out, work, kind, locks, aside=True, created=True)
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    lock = _lock(out)
    clean_orphans(out)
    if marker_kind(out) is None:
        _write_marker(out, kind)
    return RunFolder(out, out, kind, [lock], aside=False, created=created)


@contextmanager
def run_folder(out: str | os.PathLike, kind: str, **options: Any) -> Iterator[RunFolder]:
    """:func:`open_run` as a context: commit when the block succeeds, always unlock (see :meth:`RunFolder.close`)."""
    run = open_run(out, kind, **options)
    try:
        yield run
        run.commit()
    except OSError as err:
        full = disk_full_error(err, getattr(err, "filename", None) or run.dir)
        if full is None:
            raise
        raise full from None
    finally:
        run.close()


def disk_full_error(err: OSError, path: str | os.PathLike) -> NerfmetaError | None:
    """A one-line error for a full disk or an exceeded file size limit while writing ``path``, else None."""
    if err.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
        return RunFolderError(f"{path}: cannot write ({os.strerror(err.errno)}); free space and rerun with --resume "
                              "(or --overwrite)")
    return None


# ---------------------------------------------------------------------------------------------
# The one checkpoint format


CHECKPOINT = "checkpoint.safetensors"
"""The checkpoint's name in every run folder that has one."""
CHECKPOINT_FORMAT = "nerfmeta-checkpoint-2"


@dataclass(frozen=True)
class CheckpointFile:
    """A checkpoint read back.

    Attributes:
        kind: what saved it (``fit`` for the fit loop, which category pretraining uses too, or ``meta``).
        tensors: every tensor by name (``model.*``, ``optim.*``, ...).
        state: the JSON state saved beside them (step, clock, structure, ...).
    """

    kind: str
    tensors: dict[str, Any]
    state: dict[str, Any]

    def prefixed(self, prefix: str) -> dict[str, Any]:
        """The tensors whose names start with ``prefix``, with it removed."""
        return {k[len(prefix):]: v for k, v in self.tensors.items() if k.startswith(prefix)}


def save_checkpoint(path: str | os.PathLike, kind: str, tensors: dict[str, Any], state: dict[str, Any]) -> None:
    """Write ``tensors`` (safetensors) with ``state`` (JSON, in the file's metadata) to ``path`` atomically.

    Raises:
        FloatingPointError: a floating-point tensor holds NaN or infinity (a NaN never reaches disk).
    """
    import torch

    from nerfmeta.io import save_tensors

    for name, value in tensors.items():
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise FloatingPointError(f"refusing to checkpoint non-finite values in {name}")
    meta = {"format": CHECKPOINT_FORMAT, "kind": kind, "state": state}
    save_tensors(path, tensors, metadata={"nerfmeta": json.dumps(meta)})


def load_checkpoint(path: str | os.PathLike, kind: str) -> CheckpointFile:
    """Read a checkpoint written by :func:`save_checkpoint` for ``kind``; one-line error if unreadable or another kind."""
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt") as f:
            meta = json.loads((f.metadata() or {}).get("nerfmeta", "{}"))
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as err:  # OSError, JSON errors, or safetensors' own SafetensorError
        raise RunFolderError(f"{path}: not a readable checkpoint ({type(err).__name__}: {err})") from None
    if meta.get("format") != CHECKPOINT_FORMAT:
        raise RunFolderError(f"{path}: not a nerfmeta checkpoint of this version (format {meta.get('format')!r}, "
                             f"expected {CHECKPOINT_FORMAT!r}); start a new run")
    if meta.get("kind") != kind:
        raise RunFolderError(f"{path}: a {meta.get('kind')} checkpoint, not a {kind} one")
    return CheckpointFile(kind, tensors, meta.get("state") or {})


def optimizer_tensors(optimizer_state: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """A torch optimiser ``state_dict()`` as tensors ``optim.{index}.{key}`` and JSON (param groups, keys)."""
    import torch

    tensors: dict[str, Any] = {}
    keys: dict[str, list[str]] = {}
    for idx, st in optimizer_state["state"].items():
        keys[str(idx)] = sorted(st)
        for key, value in st.items():
            tensors[f"optim.{idx}.{key}"] = torch.as_tensor(value)
    groups = [{k: (list(v) if isinstance(v, tuple) else v) for k, v in g.items()} for g in optimizer_state["param_groups"]]
    return tensors, {"param_groups": groups, "state_keys": keys}


def optimizer_state(checkpoint: CheckpointFile, meta: dict[str, Any] | None) -> dict[str, Any] | None:
    """The optimiser ``state_dict()`` :func:`optimizer_tensors` saved (``meta`` its JSON part), None without one."""
    if not meta:
        return None
    state = {int(idx): {k: checkpoint.tensors[f"optim.{idx}.{k}"] for k in keys} for idx, keys in meta["state_keys"].items()}
    return {"state": state, "param_groups": meta["param_groups"]}


SUMMARY = "summary.json"
"""The final figures of a run, written once when it ends."""


def write_summary(folder: str | os.PathLike, summary: Any) -> None:
    """Write a run's summary (a dataclass with ``as_json()``) to ``folder/summary.json``, atomically."""
    write_json(Path(folder) / SUMMARY, summary.as_json())
