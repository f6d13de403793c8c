"""recall_at / auc / accuracies against hand values and a numerical integral."""

from __future__ import annotations

import math

import numpy as np
import pytest

from kpd6d.evaluation import add_s_accuracy, auc, proj2d_accuracy, recall_at


def test_recall_at_hand_values_strict_threshold_and_failures():
    e = [1.0, 2.0, 3.0, math.nan, math.inf]
    assert recall_at(e, 2.5) == pytest.approx(2 / 5)
    assert recall_at(e, 2.0) == pytest.approx(1 / 5)  # e == threshold is not below it
    np.testing.assert_allclose(recall_at(e, [0.5, 1.5, 10.0, math.inf]), [0.0, 0.2, 0.6, 0.6])
    assert recall_at([], [1.0, 2.0]).tolist() == [0.0, 0.0]
    with pytest.raises(ValueError, match=">= 0"):
        recall_at([-1.0], 1.0)


def test_auc_hand_value_and_numerical_integral():
    # contributions max(0, 10 - e): 10, 5, 0, 0 (failure) -> mean 3.75 -> normalised 0.375
    assert auc([0.0, 5.0, 10.0, math.inf], 10.0) == pytest.approx(0.375)
    assert auc([0.0, 5.0, 10.0, math.inf], 10.0, normalized=False) == pytest.approx(3.75)
    assert auc([20.0, 30.0], 10.0) == 0.0 and auc([], 10.0) == 0.0
    rng = np.random.default_rng(0)
    e = np.r_[rng.exponential(30.0, 500), [math.nan] * 20]
    grid = np.linspace(0, 100.0, 200001)
    acc = recall_at(e, grid)
    numeric = np.sum((acc[1:] + acc[:-1]) / 2 * np.diff(grid)) / 100.0  # trapezoid rule
    assert auc(e, 100.0) == pytest.approx(numeric, abs=1e-4)
    with pytest.raises(ValueError, match="max_threshold"):
        auc(e, 0.0)


def test_add_s_accuracy_and_proj2d_accuracy():
    assert add_s_accuracy([5.0, 15.0, 9.99, math.nan], 100.0) == pytest.approx(2 / 4)
    # per-object diameters: 5 < 0.1*60 but 7 >= 0.1*70
    assert add_s_accuracy([5.0, 7.0], [60.0, 70.0]) == pytest.approx(0.5)
    assert add_s_accuracy([5.0, 7.0], [60.0, 70.0], fraction=0.2) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="diameters"):
        add_s_accuracy([1.0], [0.0])
    assert proj2d_accuracy([4.9, 5.0, 1.0]) == pytest.approx(2 / 3)
    assert proj2d_accuracy([4.9, 5.0, 1.0], threshold_px=10) == pytest.approx(1.0)
