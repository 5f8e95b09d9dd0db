"""Hyperparameter studies: ``nerfmeta sweep`` (see :mod:`nerfmeta.sweep.study`)."""
