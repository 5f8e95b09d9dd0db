"""nerfmeta: category-aware NeRF transfer and meta-learning toolkit."""

import os
import sys

__version__ = "0.1.0"

if "torch" not in sys.modules:
    # PyTorch's OpenMP workers (libgomp) spin for ~300,000 rounds after each parallel region before they sleep, i.e.
    # through most of a fit step. The fused grid lookups (nerfmeta.fields.grid_kernels) run a second thread of their
    # own, which then shares its core with a spinning worker: a short spin is what lets them split (BENCHMARKS.md,
    # *Fused grid lookups*). libgomp reads this when torch is first imported, so it is set only if torch has not
    # been, and never over the user's own value.
    os.environ.setdefault("GOMP_SPINCOUNT", "10000")
