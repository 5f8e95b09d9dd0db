"""nerfmeta.compat: torchvision imports where its compiled ops cannot load, from several threads at once."""

from __future__ import annotations

import subprocess
import sys
import textwrap


def test_first_import_from_several_threads_at_once_defines_the_shim_once():
    # A fresh interpreter: in this one torchvision is imported already. Before the lock, two threads
    # both defined the "torchvision" op library and the second raised "Only a single TORCH_LIBRARY ...".
    code = textwrap.dedent("""
        from concurrent.futures import ThreadPoolExecutor
        from nerfmeta.compat import import_torchvision
        with ThreadPoolExecutor(4) as pool:
            modules = list(pool.map(lambda _: import_torchvision(), range(4)))
        assert len({id(m) for m in modules}) == 1
        modules[0].models.resnet18(weights=None)
        print("ok")
    """)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "ok"
