"""Top-l selection and PnP on the selected correspondences."""

import numpy as np
import pytest
import torch

from kpd6d.geometry import LINEMOD_K, project_points, random_rotation
from kpd6d.pnp import solve_top_l, top_l


def test_top_l_numpy_and_torch():
    c = np.array([[0.1, 0.9, 0.5, 0.7], [0.3, 0.2, 0.8, 0.1]])
    np.testing.assert_array_equal(top_l(c, 2), [[1, 3], [2, 0]])
    np.testing.assert_array_equal(top_l(c, None), [[1, 3, 2, 0], [2, 0, 1, 3]])
    np.testing.assert_array_equal(top_l(c, 10), top_l(c, None))
    assert torch.equal(top_l(torch.tensor(c), 2), torch.tensor([[1, 3], [2, 0]]))
    with pytest.raises(ValueError, match="l must be"):
        top_l(c, 0)


def test_solve_top_l_ignores_low_confidence_outliers():
    rng = np.random.default_rng(0)
    kp3 = rng.uniform(-50, 50, (12, 3))
    R, t = random_rotation(rng), np.array([10.0, -20.0, 600.0])
    uv = project_points(kp3, LINEMOD_K, R, t)
    conf = np.linspace(1.0, 0.5, 12)
    bad = uv.copy()
    bad[8:] += 80.0  # the 4 least confident keypoints are wrong
    est_top = solve_top_l({"name": "epnp"}, kp3, bad[None], LINEMOD_K, conf[None], l=8)[0]
    assert est_top.ok
    np.testing.assert_allclose(est_top.t, t, atol=1e-3)
    est_all = solve_top_l({"name": "epnp", "max_relative_residual": None}, kp3, bad[None], LINEMOD_K, conf[None],
                          l=None)[0]  # the validity gate off: the spoilt pose is measured, not rejected
    assert np.linalg.norm(est_all.t - t) > 1.0  # with all keypoints the outliers spoil the pose
