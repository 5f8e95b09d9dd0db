"""Shared pytest fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

from nerfmeta.data.synthetic import write_tiny_scene


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A Blender-format folder with the tiny analytic spheres scene: 8 train + 4 test views, 32x32 RGBA."""
    return write_tiny_scene(tmp_path_factory.mktemp("tiny_scene") / "spheres")
