"""Scenes: typed data and one parser per file format."""

from nerfmeta.data.registry import LoadOptions, load_scene
from nerfmeta.data.scene import RayBatch, Scene

__all__ = ["LoadOptions", "RayBatch", "Scene", "load_scene"]
