"""Scenes: typed data and one parser per file format."""

from nerfmeta.data.registry import LoadOptions, load_scene
from nerfmeta.data.scene import Normalization, RayBatch, Scene

__all__ = ["LoadOptions", "Normalization", "RayBatch", "Scene", "load_scene"]
