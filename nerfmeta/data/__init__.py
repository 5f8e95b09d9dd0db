"""Scenes: typed data and one parser per file format."""

from nerfmeta.data.scene import RayBatch, Scene

__all__ = ["RayBatch", "Scene"]
