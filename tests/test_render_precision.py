"""Float32 rendering and its gradient stay close to a float64 reference, adversarial cases included."""

import pytest

from nerfmeta.render.precision import compare_precision, standard_cases

CASES = standard_cases()


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_float32_close_to_float64(case):
    result = compare_precision(case)
    assert result.finite
    assert result.rgb_rel_error < 1e-5, result
    assert result.grad_color_rel_error < 1e-5, result
    assert result.grad_sigma_rel_error < 1e-4, result
