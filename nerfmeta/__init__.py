"""nerfmeta: category-aware NeRF transfer and meta-learning toolkit."""

__version__ = "0.1.0"
