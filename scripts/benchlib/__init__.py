"""Code shared by the benchmark scripts and the tests, never installed with nerfmeta.

- :mod:`benchlib.stress`: the stiff and extreme cases (``scripts/stress.py``, ``tests/test_stress.py``).
- :mod:`benchlib.sections`: replacing a script's section of BENCHMARKS.md in place.
- :mod:`benchlib.workdir`: refusing a scratch ``--work`` folder that holds anything (nothing is deleted).

How it is found: a script run as a file has ``scripts/`` as ``sys.path[0]``, so ``import benchlib``
just works; pytest adds ``scripts/`` through ``pythonpath`` in ``pyproject.toml``.
"""
