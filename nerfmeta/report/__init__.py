"""Plots and reports: error against iterations and against wall-clock time.

- :mod:`~nerfmeta.report.plots`: PSNR curves, mean +- sd bands, render strips and image grids.
- :mod:`~nerfmeta.report.snapshots`: renders at chosen iterations of a fit (``RUN/snapshots/``).
- :mod:`~nerfmeta.report.curves`: numbers read off PSNR curves (PSNR at N, reaching a target, ahead).
- :mod:`~nerfmeta.report.compare`: one scene, a routed fit against its baseline (``write_comparison``).
- :mod:`~nerfmeta.report.aggregate`: many runs (``nerfmeta report``).
"""
