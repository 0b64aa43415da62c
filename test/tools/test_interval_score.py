"""The interval score of Gneiting & Raftery (2007, eq. 43), the figure the restated population and real-Panda lines
compare observers by: a hand-computed example, and the metrics.json figures built on it."""
from __future__ import annotations

import numpy as np
import pytest

from kvark_ros.tools.metrics import calibration_metrics, interval_score


def test_the_interval_score_of_hand_computed_intervals():
    """[−1, 1] at α = 0.05 (2/α = 40): a truth inside pays the width 2; 1.5 misses by 0.5: 2 + 40 · 0.5 = 22; −3
    misses below by 2: 2 + 40 · 2 = 82. A narrower [0, 0.5] around a truth of 0.25 pays only its width 0.5."""
    lower = np.array([-1.0, -1.0, -1.0, 0.0])
    upper = np.array([1.0, 1.0, 1.0, 0.5])
    truth = np.array([0.0, 1.5, -3.0, 0.25])
    np.testing.assert_allclose(interval_score(lower, upper, truth, 0.05), [2.0, 22.0, 82.0, 0.5], rtol=0, atol=1e-12)
    # α = 0.5 (a 50 % interval) penalises a miss 4 ×: 2 + 4 · 0.5 = 4
    assert interval_score(np.array(-1.0), np.array(1.0), np.array(1.5), 0.5) == pytest.approx(4.0, abs=1e-12)
    with pytest.raises(ValueError, match="alpha"):
        interval_score(lower, upper, truth, 1.0)


def test_metrics_give_the_mean_interval_score_of_the_95_percent_interval():
    """3 samples, 2 joints, σ = 1 (±1.96, width 3.92): errors 0.5 and −0.5 inside; 2.0 misses by 0.04 (40 · 0.04 =
    1.6); −3.0 by 1.04 (41.6) and 2.5 by 0.54 (21.6). Joint 0: (3.92 · 3 + 1.6 + 41.6) / 3 = 18.32; joint 1: (3.92 · 3
    + 21.6) / 3 = 11.12; all samples 14.72."""
    error = np.array([[0.5, -0.5], [2.0, 0.0], [-3.0, 2.5]])
    entry = calibration_metrics(error, np.ones((3, 2)), None)
    assert entry["interval_score95_per_joint"] == pytest.approx([18.32, 11.12], abs=1e-6)
    assert entry["interval_score95"] == pytest.approx(14.72, abs=1e-6)
    # the score of a calibrated and a too-wide interval on the same errors: doubling σ covers every sample and still
    # scores worse where the errors are small
    wide = calibration_metrics(np.array([[0.1, -0.1]]), 2.0 * np.ones((1, 2)), None)
    sharp = calibration_metrics(np.array([[0.1, -0.1]]), np.ones((1, 2)), None)
    assert wide["interval_score95"] == pytest.approx(7.84) and sharp["interval_score95"] == pytest.approx(3.92)
