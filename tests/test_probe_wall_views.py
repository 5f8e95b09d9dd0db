"""scripts/probe_wall_views.py: a shell thickened towards its cavity keeps its outside and its rim's top."""

from __future__ import annotations

import pytest
import torch

from nerfmeta.collection.shapes import Material, Part, Revolution, Shape
from probe_wall_views import retextured, thickened_inwards

R, H, T, DELTA = 0.4, 1.0, 0.02, 0.01  # cup radius, height, half-thickness of its shell, how much thicker


def _cup() -> Shape:
    body = Part("body", Revolution(((0.0, 0.0), (R, 0.0), (R, H)), T), Material((0.5, 0.5, 0.5), texture="stripes",
                                                                            color2=(0.1, 0.2, 0.3)))
    return Shape("mug", (body,))


def _sdf(shape: Shape, r: float, z: float) -> float:
    return float(shape.sdf(torch.tensor([[r, 0.0, z]], dtype=torch.float64))[0])


@pytest.mark.parametrize("r,z,before,after", [
    (R + T, 0.5, 0.0, 0.0),                  # the outside of the wall stays
    (0.2, -T, 0.0, 0.0),                     # the underside of the floor stays
    (R - T, 0.5, 0.0, -DELTA),               # the old inner wall is now DELTA inside the solid
    (R - T - DELTA, 0.5, DELTA, 0.0),        # the new inner wall is DELTA further in
    (0.2, T + DELTA, DELTA, 0.0),            # the floor's top rises by DELTA
    (R - DELTA / 2, H + T, None, 0.0),       # the rim's crest stays at its height (half DELTA further in)
])
def test_the_shell_grows_towards_the_cavity_only(r, z, before, after):
    cup = _cup()
    if before is not None:
        assert _sdf(cup, r, z) == pytest.approx(before, abs=1e-9)
    assert _sdf(thickened_inwards(cup, DELTA), r, z) == pytest.approx(after, abs=1e-6)


def test_textures_are_swapped_on_every_part_and_kept_on_request():
    cup = _cup()
    assert retextured(cup, "keep") is cup
    assert [p.material.texture for p in retextured(cup, "plain").parts] == ["plain"]
    checker = retextured(cup, "checker").parts[0].material
    assert checker.texture == "checker" and checker.color2 == (0.1, 0.2, 0.3)
