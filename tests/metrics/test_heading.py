"""Heading error of planned poses: wrapped degrees, median and mean of summed counts."""

from __future__ import annotations

import math

import numpy as np
import pytest

from renderworld.metrics.heading import (
    HEADING_BIN_DEG,
    heading_counts,
    heading_error_deg,
    heading_from_counts,
)


def test_heading_error_wraps_around():
    err = heading_error_deg(np.radians([179.0, -90.0, 10.0]), np.radians([-179.0, 90.0, 12.5]))
    assert err == pytest.approx([2.0, 180.0, 2.5])


def test_median_and_mean_of_counts_summed_over_shards_match_numpy():
    rng = np.random.default_rng(0)
    gt = rng.uniform(-np.pi, np.pi, (9, 6))
    pred = gt + np.radians(rng.normal(0, 3, (9, 6)))
    valid = np.ones((9, 6), dtype=bool)
    valid[7:, 4:] = False  # two windows end before 2.5 s
    shards = [heading_counts(pred[a:b], gt[a:b], valid[a:b]) for a, b in ((0, 4), (4, 9))]
    hist, total, count = (sum(s[i] for s in shards) for i in range(3))
    res = heading_from_counts(hist, total, count, (2, 4, 6))
    err = heading_error_deg(pred, gt)
    for i, k in enumerate((2, 4, 6)):
        e = err[valid[:, k - 1], k - 1]
        assert res["mean"][i] == pytest.approx(e.mean())
        assert abs(res["median"][i] - np.median(e)) <= HEADING_BIN_DEG / 2 + 1e-9
    assert count.tolist() == [9, 9, 9, 9, 7, 7]


def test_even_count_median_is_the_mean_of_the_two_middle_errors():
    gt = np.zeros((2, 1))
    hist, total, count = heading_counts(np.radians([[1.0], [9.0]]), gt, np.ones((2, 1), bool))
    res = heading_from_counts(hist, total, count, (1,))
    assert res["median"][0] == pytest.approx(5.0, abs=HEADING_BIN_DEG)
    # Straight driving: a zero error is reported as zero to the reported 0.01 degree.
    hist, total, count = heading_counts(
        np.zeros((3, 1)), gt[:1].repeat(3, 0), np.ones((3, 1), bool)
    )
    assert heading_from_counts(hist, total, count, (1,))["median"][0] < 0.005
    # Large errors land in the coarse bins (0.1 degree) and still count.
    hist, total, count = heading_counts(np.radians([[120.0]]), gt[:1], np.ones((1, 1), bool))
    assert heading_from_counts(hist, total, count, (1,))["median"][0] == pytest.approx(
        120.0, abs=0.05
    )
    empty = heading_from_counts(hist * 0, total * 0, count * 0, (1,))
    assert math.isnan(empty["median"][0]) and math.isnan(empty["mean"][0])
