"""Feed-forward starts for the voxel grid, computed from a new scene's own posed training views.

:mod:`nerfmeta.priors.carve`: a visual hull (silhouette carving) and the mean projected colour,
where the views have alpha or a uniform background; skipped, with the reason, where they do not.
"""
