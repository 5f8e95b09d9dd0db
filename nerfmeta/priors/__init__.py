"""Feed-forward starts for the voxel grid, computed from a new scene's own posed training views.

:mod:`nerfmeta.priors.carve`: a visual hull (silhouette carving) and the mean projected colour,
where the views have alpha or a uniform background; skipped, with the reason, where they do not.
:mod:`nerfmeta.priors.occupancy`: the same kind of start from a learned guess of the occupancy (a small 3-D CNN over
per-voxel multi-view features; ``--init occupancy``, the model zoo's network), measured by
``scripts/probe_occupancy_start.py`` and ``scripts/bench_priors.py``.
"""
