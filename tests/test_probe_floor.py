"""scripts/probe_floor.py: where an SDF along a line changes sign."""

from __future__ import annotations

import numpy as np
import pytest

from probe_floor import sign_changes


def test_a_plate_crossed_by_a_vertical_line_gives_its_two_faces():
    z = np.linspace(0.0, 10.0, 101)
    plate = np.abs(z - 2.0) - 0.5  # a slab from 1.5 to 2.5: inside (< 0) between
    assert sign_changes(plate, z) == pytest.approx([1.6, 2.5])  # the first sample inside, then the first not inside (0 counts as out)
    two = np.minimum(plate, np.abs(z - 7.0) - 1.0)  # and a second, thicker one above
    assert sign_changes(two, z) == pytest.approx([1.6, 2.5, 6.1, 8.0])


def test_a_line_that_never_meets_the_surface_has_no_crossings():
    z = np.linspace(0.0, 1.0, 11)
    assert sign_changes(np.ones_like(z), z) == [] and sign_changes(-np.ones_like(z), z) == []
