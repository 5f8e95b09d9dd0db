"""A pytest plugin that records each test's CPU and wall time (for ``scripts/bench_suite.py``).

Load it with ``PYTHONPATH=scripts python -m pytest -p benchlib.testtime``; the times go to the JSON
file named by ``$NERFMETA_TESTTIME_OUT`` as ``{"cpu": {nodeid: s}, "wall": {nodeid: s}}``. CPU time is
this process's (``time.process_time``): it counts set-up, call and tear-down of the test and is far
less disturbed than wall time by other work on the machine; CLI tests that spawn processes show
their children's time only in the wall figure.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import pytest

_CPU: dict[str, float] = {}
_WALL: dict[str, float] = {}


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None):
    cpu, wall = time.process_time(), time.perf_counter()
    yield
    _CPU[item.nodeid] = time.process_time() - cpu
    _WALL[item.nodeid] = time.perf_counter() - wall


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    out = os.environ.get("NERFMETA_TESTTIME_OUT")
    if out:
        Path(out).write_text(json.dumps({"cpu": _CPU, "wall": _WALL}, indent=1))
