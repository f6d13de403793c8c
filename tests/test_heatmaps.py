"""Gaussian heatmap targets and the heatmap <-> crop pixel mapping, against independent computations."""

import math

import numpy as np
import pytest
import torch

from kpd6d.kpd.heatmaps import crop_to_heatmap, gaussian_heatmaps, heatmap_to_crop


def test_gaussian_matches_pointwise_formula():
    coords = torch.tensor([[[3.3, 5.7], [10.0, 2.0], [-4.0, 6.5]]])
    hm = gaussian_heatmaps(coords, (12, 9), sigma=2.0)
    assert hm.shape == (1, 3, 9, 12)
    for k, (x, y) in enumerate(coords[0].tolist()):
        for py in range(9):
            for px in range(12):
                want = math.exp(-((px - x) ** 2 + (py - y) ** 2) / 4.0)
                assert hm[0, k, py, px].item() == pytest.approx(want, abs=1e-6)
    # the peak of an on-grid keypoint is exactly 1
    assert hm[0, 1, 2, 10].item() == pytest.approx(1.0)


def test_invisible_and_nonfinite_keypoints():
    hm = gaussian_heatmaps(torch.tensor([[100.0, 100.0], [float("nan"), 3.0]]), 16, sigma=2.0)
    assert hm.shape == (2, 16, 16)
    assert hm.max() < 1e-6  # far outside and NaN: (near-)empty maps, not errors
    with pytest.raises(ValueError, match="sigma"):
        gaussian_heatmaps(torch.zeros(1, 2), 8, sigma=0.0)
    with pytest.raises(ValueError, match="K, 2"):
        gaussian_heatmaps(torch.zeros(1, 3), 8, sigma=1.0)


@pytest.mark.parametrize("stride", [1, 2, 4, 8])
def test_stride_mapping_pixel_centres(stride):
    # heatmap pixel i covers crop pixels [s*i, s*(i+1)); its centre is the mean of their centres
    for i in range(5):
        crop_centres = np.arange(stride * i, stride * (i + 1), dtype=np.float64)
        assert heatmap_to_crop(np.array(float(i)), stride) == pytest.approx(crop_centres.mean())
    x = np.random.default_rng(0).uniform(-3, 70, size=(10, 2))
    np.testing.assert_allclose(heatmap_to_crop(crop_to_heatmap(x, stride), stride), x)
    # the edges of the image coincide: crop -0.5 and S-0.5 <-> heatmap -0.5 and S/s-0.5
    assert crop_to_heatmap(-0.5, stride) == pytest.approx(-0.5)
    assert crop_to_heatmap(64 * stride - 0.5, stride) == pytest.approx(63.5)


def test_stride_mapping_matches_area_downsampling():
    # a crop-resolution Gaussian, area-averaged by the stride, peaks where crop_to_heatmap says
    s = 4
    kp = torch.tensor([[37.3, 21.8]])
    fine = gaussian_heatmaps(kp, 64, sigma=6.0)
    coarse = torch.nn.functional.avg_pool2d(fine[None], s)[0]
    hm = coarse[0]
    w = hm / hm.sum()
    ys, xs = torch.meshgrid(torch.arange(16.0), torch.arange(16.0), indexing="ij")
    centroid = torch.stack([(w * xs).sum(), (w * ys).sum()])
    assert torch.allclose(centroid, crop_to_heatmap(kp[0], s), atol=0.02)
