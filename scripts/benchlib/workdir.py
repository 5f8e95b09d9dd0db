"""The scratch folder a benchmark script writes into: absent or empty, never cleared.

A script that cleared its ``--work`` folder before starting (``rmtree``) would delete whatever a user kept there,
so the scripts refuse a folder that holds anything and delete nothing (``scripts/bench_poses.py``,
``scripts/bench_map_draws.py``).
"""

from __future__ import annotations

from pathlib import Path

from nerfmeta.runfolder import has_content


def work_folder_error(work: Path, flag: str = "--work") -> str | None:
    """The one-line error for a scratch folder that exists and is not empty (or is not a folder), else None."""
    if has_content(work) or (work.exists() and not work.is_dir()):
        return f"error: {flag} {work}: exists and is not an empty folder; give a new one (nothing is deleted)"
    return None
