"""One fit of a sweep, in a process of its own, so that its peak RSS is that fit's alone.

A worker has imported torch and nerfmeta once; :func:`fork_fit` forks a child per fit (no second
import: on this machine that is 4-7 s per fit) and reads the child's ``ru_maxrss`` when it exits
(``wait4``). The child starts with the worker's resident pages (the imported libraries), as a fresh
``python -m`` process would after its imports. A run folder left half-done by a killed sweep is
replaced (``--overwrite`` rules of :mod:`nerfmeta.runfolder`: only a fit run of ours). A user error
is one line on the child's stderr (the log file) and exit code 2.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable


@dataclass(frozen=True)
class ChildExit:
    """How a forked fit ended: exit code, peak RSS (MB), wall time, and what it printed on its result pipe."""

    code: int
    peak_rss_mb: float
    wall_s: float
    result: dict[str, Any]


def warm_imports() -> None:
    """Import in the worker what every fit imports (torch, the fit, plots, LPIPS), so forked fits start warm."""
    import importlib.util

    import nerfmeta.fit.run  # noqa: F401
    import nerfmeta.report.plots  # noqa: F401

    if importlib.util.find_spec("lpips") is not None:
        from nerfmeta.compat import import_torchvision

        import_torchvision()
        import lpips  # noqa: F401


def fit_one(config_json: dict[str, Any], folder: Path) -> dict[str, Any]:
    """Run the fit of ``config_json`` (a ``config.json`` form) into ``folder``; return what the sweep adds (CUDA peak)."""
    import torch

    from nerfmeta.fit.run import RunConfig, run_fit
    from nerfmeta.runfolder import has_content

    config = RunConfig.from_json(dict(config_json))
    run_fit(config, folder, overwrite=has_content(folder))
    cuda = torch.cuda.max_memory_allocated() / 2**20 if config.device.startswith("cuda") else None
    return {"cuda_peak_mb": None if cuda is None else round(cuda, 1)}


def fork_fit(config_json: dict[str, Any], folder: Path, log_path: Path, *, before: Callable[[], None] = lambda: None) -> ChildExit:
    """Run :func:`fit_one` in a forked child (stderr to ``log_path``); ``before`` runs first in the child."""
    from nerfmeta.errors import NerfmetaError

    read_end, write_end = os.pipe()
    t0 = time.perf_counter()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        code = 1
        try:
            os.close(read_end)
            fd = os.open(log_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            os.dup2(fd, 2)
            sys.stderr = os.fdopen(2, "w", buffering=1)
            logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s", force=True,
                                stream=sys.stderr)
            before()
            result = fit_one(config_json, folder)
            os.write(write_end, json.dumps(result).encode())
            code = 0
        except NerfmetaError as err:
            print(f"nerfmeta sweep: error: {err}", file=sys.stderr)
            code = 2
        except BaseException:  # noqa: BLE001 - reported in the log; the exit code tells the sweep
            traceback.print_exc()
        finally:
            sys.stderr.flush()
            os._exit(code)
    os.close(write_end)
    chunks = []
    while True:
        chunk = os.read(read_end, 65536)
        if not chunk:
            break
        chunks.append(chunk)
    os.close(read_end)
    _, status, usage = os.wait4(pid, 0)
    wall = time.perf_counter() - t0
    text = b"".join(chunks).decode()
    return ChildExit(os.waitstatus_to_exitcode(status), round(usage.ru_maxrss / 1024, 1), wall,
                     json.loads(text) if text else {})
