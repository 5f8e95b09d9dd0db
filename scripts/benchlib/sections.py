"""BENCHMARKS.md sections: each benchmark script owns one ``## `` section and replaces it in place."""

from __future__ import annotations

import os
import re

from nerfmeta.io import write_bytes_atomic


def write_section(path: str | os.PathLike, heading: str, text: str) -> None:
    """Replace the section of ``path`` that starts with the line ``heading`` (up to the next ``## ``
    heading or the end) by ``text``, or append ``text`` when there is no such section; atomically.

    Args:
        path: the markdown file (created with a ``# Benchmarks`` title when missing).
        heading: the section's heading line, e.g. ``"## Stress cases"``.
        text: the whole new section, heading included.
    """
    path = os.fspath(path)
    doc = open(path, encoding="utf-8").read() if os.path.exists(path) else "# Benchmarks\n"
    block = text.rstrip("\n") + "\n\n"
    pattern = re.compile(rf"^{re.escape(heading)}\n.*?(?=^## |\Z)", re.S | re.M)
    found = pattern.search(doc)
    doc = doc[: found.start()] + block + doc[found.end():] if found else doc.rstrip("\n") + "\n\n" + block
    write_bytes_atomic(path, (doc.rstrip("\n") + "\n").encode())
