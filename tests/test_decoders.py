"""DECODERS on synthetic heatmaps with sub-pixel peaks."""

import pytest
import torch

from kpd6d.kpd.heatmaps import gaussian_heatmaps
from kpd6d.registry import DECODERS, UnknownNameError


def _peaks(seed=0, B=3, K=9, size=64, margin=6):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(B, K, 2, generator=g) * (size - 2 * margin) + margin


def test_registered_names():
    assert {"argmax", "soft_argmax", "subpixel"} <= set(DECODERS.names())
    with pytest.raises(UnknownNameError, match="soft_argmax"):
        DECODERS.build("nope")


@pytest.mark.parametrize("sigma", [1.5, 2.0, 3.0])
@pytest.mark.parametrize(
    "name,params",
    [("soft_argmax", {}), ("soft_argmax", {"window": None}), ("subpixel", {}), ("subpixel", {"method": "taylor"}),
     ("subpixel", {"method": "quadratic"})],
)
def test_subpixel_decoders_recover_peaks(name, params, sigma):
    c = _peaks()
    amp = torch.linspace(0.3, 1.0, c.shape[1])
    hm = gaussian_heatmaps(c, 64, sigma) * amp[None, :, None, None]
    if name == "soft_argmax" and sigma == 3.0 and params.get("window", 5) == 5:
        params = {"window": 8}  # the window must hold the peak's mass
    xy, conf = DECODERS.build(name, **params)(hm)
    assert xy.shape == (3, 9, 2) and conf.shape == (3, 9)
    assert (xy - c).abs().max() < 0.1
    # confidence = heatmap maximum, which for an off-grid peak is slightly below the amplitude
    assert torch.all(conf <= amp + 1e-6) and torch.all(conf > 0.8 * amp)


def test_argmax_is_paper_eq1():
    c = _peaks()
    hm = gaussian_heatmaps(c, 64, 2.0)
    xy, conf = DECODERS.build("argmax")(hm)
    assert torch.equal(xy, torch.round(c))  # the nearest pixel centre
    flat = hm.flatten(2)
    assert torch.equal(conf, flat.max(-1).values)


def test_noisy_heatmaps_and_borders():
    torch.manual_seed(0)
    c = _peaks(seed=1)
    hm = gaussian_heatmaps(c, 64, 2.0) + 0.01 * torch.randn(3, 9, 64, 64)
    for name in ("soft_argmax", "subpixel"):
        xy, _ = DECODERS.build(name)(hm)
        assert (xy - c).abs().max() < 0.3
    # a peak on the border or outside: finite coords within the map, no exceptions
    edge = gaussian_heatmaps(torch.tensor([[[0.0, 10.0], [-3.0, 70.0]]]), 64, 2.0)
    for name in ("argmax", "soft_argmax", "subpixel"):
        xy, _ = DECODERS.build(name)(edge)
        assert torch.isfinite(xy).all() and (xy >= -1).all() and (xy <= 64).all()


def test_bad_input_and_params():
    with pytest.raises(ValueError, match="B, K, H, W"):
        DECODERS.build("argmax")(torch.zeros(3, 8, 8))
    with pytest.raises(ValueError, match="method"):
        DECODERS.build("subpixel", method="magic")
    with pytest.raises(TypeError, match="accepts"):
        DECODERS.build("argmax", window=3)
