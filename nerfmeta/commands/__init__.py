"""One module per CLI command; see :mod:`nerfmeta.cli`."""
