"""Procedural ShapeNet-like category collections: SDF shapes, samplers, a renderer and a writer.

- :mod:`~nerfmeta.collection.sdf`: signed-distance primitives and combinators (pure functions).
- :mod:`~nerfmeta.collection.shapes`: a shape as typed parts, its ``sdf``/``albedo``, JSON round trip.
- :mod:`~nerfmeta.collection.categories`: one random sampler per category, in a registry.
- :mod:`~nerfmeta.collection.render`: batched sphere tracing with shading and supersampling.
- :mod:`~nerfmeta.collection.generate`: :class:`CollectionConfig` and :func:`generate_collection`.
"""

from nerfmeta.collection.categories import CATEGORIES, sample_shape
from nerfmeta.collection.generate import CollectionConfig, generate_collection, load_collection, scene_sdf
from nerfmeta.collection.render import RenderConfig, render_shape
from nerfmeta.collection.shapes import Shape, shape_albedo, shape_from_json, shape_sdf, shape_to_json

__all__ = [
    "CATEGORIES",
    "CollectionConfig",
    "RenderConfig",
    "Shape",
    "generate_collection",
    "load_collection",
    "render_shape",
    "sample_shape",
    "scene_sdf",
    "shape_albedo",
    "shape_from_json",
    "shape_sdf",
    "shape_to_json",
]
