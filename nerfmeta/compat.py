"""Import torchvision where its compiled ops cannot load.

The torchvision 0.28.0 wheel on PyPI is built against CUDA torch. Beside the CPU build of
torch 2.13.0 its ``_C`` extension fails to load (it links ``libtorch_cuda.so``), and
``torchvision/_meta_registrations.py`` then crashes at import, registering fake kernels for
``torchvision::nms`` / ``qnms`` ops that were never defined. nerfmeta uses only torchvision's
pure-Python parts (ResNet builders, transforms), so when the ops are missing we define those two
schemas (no kernels) before importing. Detection/ops that need the kernels still raise
torchvision's own "Couldn't load custom C++ ops" error if someone calls them.
"""

from __future__ import annotations

import functools
import threading
from types import ModuleType

import torch

_MISSING_OP_SCHEMAS = {
    "nms": "nms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor",
    "qnms": "qnms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor",
}
_shim_library: torch.library.Library | None = None
_lock = threading.Lock()  # the first import defines the shim once, even when several threads ask at the same time


def _torchvision_ops_load() -> bool:
    from importlib.util import find_spec

    spec = find_spec("torchvision")
    if spec is None or not spec.submodule_search_locations:
        return True  # let the real import raise its own ImportError
    from pathlib import Path

    for folder in spec.submodule_search_locations:
        for lib in Path(folder).glob("_C*.so"):
            try:
                torch.ops.load_library(str(lib))
                return True
            except (OSError, RuntimeError):
                return False
    return True


@functools.lru_cache(maxsize=None)
def import_torchvision() -> ModuleType:
    """Return the ``torchvision`` module, importable even when its C++ ops are unavailable (thread-safe)."""
    global _shim_library
    with _lock:
        if _shim_library is None and not _torchvision_ops_load():
            _shim_library = torch.library.Library("torchvision", "DEF")
            for schema in _MISSING_OP_SCHEMAS.values():
                _shim_library.define(schema)
        import torchvision

    return torchvision
