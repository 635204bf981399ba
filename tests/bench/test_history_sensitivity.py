"""benchmarks/history_sensitivity.py: the perturbed history and the summary table."""

import numpy as np
import pytest

from benchmarks.history_sensitivity import perturbed_last_step, summary


def test_only_the_last_step_changes_along_its_own_direction():
    d = np.array([[3.0, 0.0], [3.0, 0.3], [2.4, 1.8]])  # the last step 3 m, turning left
    out = perturbed_last_step(d, -0.03)
    np.testing.assert_array_equal(out[:-1], d[:-1])
    assert np.hypot(*out[-1]) == pytest.approx(2.97)
    np.testing.assert_allclose(out[-1] / np.hypot(*out[-1]), d[-1] / 3.0)
    assert np.hypot(*perturbed_last_step(d, 0.03)[-1]) == pytest.approx(3.03)
    standing = np.array([[0.0, 0.0], [0.0, 0.0005]])
    np.testing.assert_array_equal(perturbed_last_step(standing, 0.03), standing)
    with pytest.raises(ValueError, match=r"displacements: expected \[H-1 >= 1, 2\]"):
        perturbed_last_step(np.zeros(4), 0.03)


def test_the_summary_gives_the_gain_per_speed_band():
    rows = [
        {"speed": 4.0, "shorter": -0.03, "longer": 0.03},  # follows the history one to one
        {"speed": 12.0, "shorter": -1.5, "longer": 0.6},
        {"speed": 14.0, "shorter": -0.9, "longer": 0.0},
    ]
    text = summary(rows, 0.03)
    assert "| all | 3 | -0.900 m; 0.810 m; 27.0x | +0.030 m; 0.210 m; 7.0x |" in text
    assert "| 0-5 | 1 | -0.030 m; 0.030 m; 1.0x | +0.030 m; 0.030 m; 1.0x |" in text
    assert "| 10-inf | 2 | -1.200 m; 1.200 m; 40.0x | +0.300 m; 0.300 m; 10.0x |" in text
    assert "| 5-10 |" not in text  # no window in that band
