"""HeatmapCodec (CODECS): encode / decode against independent computations, config round trips and
the mapping of the older separate fields."""

import math

import numpy as np
import pytest
import torch

from kpd6d.kpd.codec import HeatmapCodec, build_codec, codec_config
from kpd6d.registry import CODECS, REGISTRIES, build_from_cfg


def _target_by_hand(x, y, input_size, stride, sigma):
    """The paper's target written out pixel by pixel: heatmap pixel (i, j) covers crop pixels
    [s*i, s*(i+1)), so its centre is at crop px s*i + (s-1)/2; the Gaussian is exp(-d^2 / sigma^2) in
    heatmap px."""
    n = input_size // stride
    out = np.zeros((n, n))
    for j in range(n):
        for i in range(n):
            cx, cy = stride * i + (stride - 1) / 2, stride * j + (stride - 1) / 2
            d2 = ((cx - x) ** 2 + (cy - y) ** 2) / stride**2
            out[j, i] = math.exp(-d2 / sigma**2)
    return out


def test_registered_and_a_registry_like_the_others():
    assert "heatmap" in CODECS.names()
    assert REGISTRIES["codec"] is CODECS
    codec = build_from_cfg(CODECS, {"name": "heatmap", "input_size": 64, "out_stride": 4})
    assert isinstance(codec, HeatmapCodec) and codec.heatmap_size == 16
    with pytest.raises(ValueError, match="multiple of out_stride"):
        CODECS.build("heatmap", input_size=66, out_stride=4)
    with pytest.raises(ValueError, match="sigma"):
        CODECS.build("heatmap", sigma=0.0)


@pytest.mark.parametrize("stride,sigma", [(4, 2.0), (2, 1.5), (1, 3.0)])
def test_encode_matches_the_target_written_out(stride, sigma):
    codec = HeatmapCodec(input_size=32, out_stride=stride, sigma=sigma)
    pts = torch.tensor([[[13.3, 7.9], [0.0, 31.0], [40.0, -5.0]]])  # one inside, one at a corner, one outside
    targets, weights = codec.encode(pts, torch.tensor([[1.0, 1.0, 0.0]]))
    n = 32 // stride
    assert targets.shape == (1, 3, n, n) and targets.dtype == torch.float32
    for k, (x, y) in enumerate(pts[0].tolist()):
        np.testing.assert_allclose(targets[0, k].numpy(), _target_by_hand(x, y, 32, stride, sigma), atol=1e-6)
    assert weights.tolist() == [[1.0, 1.0, 0.0]]
    _, ones = codec.encode(pts)
    assert torch.equal(ones, torch.ones(1, 3))
    with pytest.raises(ValueError, match="visibility shape"):
        codec.encode(pts, torch.ones(1, 2))


@pytest.mark.parametrize("decoder,tol", [({"name": "subpixel"}, 0.05), ({"name": "subpixel", "method": "taylor"}, 0.05),
                                         ({"name": "soft_argmax"}, 0.05), ({"name": "subpixel", "method": "quadratic"}, 0.2)])
def test_encode_decode_round_trip_in_crop_pixels(decoder, tol):
    """Known sub-pixel crop points -> targets -> decoded crop points (stride 4: a heatmap px is 4 crop px)."""
    codec = HeatmapCodec(input_size=128, out_stride=4, sigma=2.0, decoder=decoder)
    rng = np.random.default_rng(0)
    pts = rng.uniform(20, 108, (2, 7, 2))
    targets, _ = codec.encode(torch.from_numpy(pts))
    xy, conf = codec.decode(targets)
    assert xy.shape == (2, 7, 2) and conf.shape == (2, 7)
    err = np.abs(xy.double().numpy() - pts).max()
    assert err < tol, err
    # confidence: the heatmap maximum (1 at an on-grid peak, slightly less off the grid)
    assert torch.all(conf <= 1.0 + 1e-6) and torch.all(conf > 0.8)


def test_argmax_decode_is_the_nearest_heatmap_pixel_centre():
    codec = HeatmapCodec(input_size=64, out_stride=4, sigma=2.0, decoder="argmax")
    pts = torch.tensor([[[10.0, 21.0], [33.7, 50.2]]])
    xy, _ = codec.decode(codec.encode(pts)[0])
    # nearest heatmap px of (crop + 0.5) / 4 - 0.5, mapped back to its centre in crop px
    want = (torch.round((pts + 0.5) / 4 - 0.5) + 0.5) * 4 - 0.5
    assert torch.equal(xy, want)


def test_crop_affine_maps_the_box_centre_to_the_crop_centre():
    codec = HeatmapCodec(input_size=64, crop_scale=1.5)
    box = np.array([40.0, 30.0, 20.0, 10.0])
    A = codec.crop_affine(box)
    centre = A @ np.array([50.0, 35.0, 1.0])
    np.testing.assert_allclose(centre, [31.5, 31.5])
    # the crop spans crop_scale x the longer side: 30 image px -> 64 crop px
    assert A[0, 0] == pytest.approx(64 / 30)
    At = codec.crop_affine(torch.from_numpy(box)[None])
    assert isinstance(At, torch.Tensor) and torch.allclose(At[0], torch.from_numpy(A))


def test_config_round_trip_and_legacy_fields():
    codec = HeatmapCodec(input_size=96, out_stride=4, sigma=1.5, crop_scale=1.5,
                         decoder={"name": "soft_argmax", "window": 3})
    cfg = codec.config()
    assert cfg == {"name": "heatmap", "input_size": 96, "out_stride": 4, "sigma": 1.5, "crop_scale": 1.5,
                   "decoder": {"name": "soft_argmax", "window": 3}}
    again = build_codec(cfg)
    assert again.config() == cfg and again.decoder.window == 3
    assert build_codec(codec) is codec
    # the separate fields (KPDCropDataset / KPDModule before the codec, old checkpoints) map onto one node
    legacy = codec_config(input_size=96, sigma=1.5, crop_scale=1.5, out_stride=4,
                          decoder={"name": "soft_argmax", "window": 3})
    assert build_codec(legacy).config() == cfg
    assert build_codec().config() == {"name": "heatmap", "input_size": 256, "out_stride": 4, "sigma": 2.0,
                                      "crop_scale": 1.25, "decoder": {"name": "subpixel"}}
    with pytest.raises(ValueError, match="not both"):
        codec_config({"name": "heatmap"}, sigma=2.0)
    with pytest.raises(TypeError, match="unknown codec field"):
        codec_config(sigmaa=2.0)


def _compose(name, overrides):
    from hydra import compose, initialize_config_dir

    from kpd6d.config import config_dir

    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        return compose(config_name=name, overrides=overrides)


def test_one_codec_node_in_the_stage_config():
    cfg = _compose("train", ["kpd@stage.kpd=cpu_small", "decoder@stage.kpd.codec.decoder=soft_argmax",
                             "stage.kpd.codec.sigma=3.0"])
    codec = build_codec(cfg.stage.kpd.codec)
    assert codec.config() == {"name": "heatmap", "input_size": 96, "out_stride": 4, "sigma": 3.0, "crop_scale": 1.25,
                              "decoder": {"name": "soft_argmax", "temperature": 1.0, "window": 5}}
    # one node: the separate fields of earlier versions are gone from the stage
    k = cfg.stage.kpd
    assert not any(key in k for key in ("input_size", "out_stride", "sigma", "crop_scale")) and "decoder" not in cfg.stage
    run = _compose("run", ["experiment=linemod"])
    assert run.kpd_stage.kpd.codec.input_size == 256 and run.kpd_stage.kpd.codec.decoder.name == "subpixel"


def test_old_codec_spellings_name_the_new_ones():
    from kpd6d.config import check_stage_config, renamed_overrides

    assert renamed_overrides(["kpd_stage.kpd.input_size=64", "decoder@stage.decoder=argmax", "stage.kpd.sigma=3",
                              "stage.kpd.codec.sigma=3", "kpd_stage.kpd.batch_size=8"]) == [
        "kpd_stage.kpd.input_size is now kpd_stage.kpd.codec.input_size",
        "stage.decoder is now stage.kpd.codec.decoder (decoder@stage.kpd.codec.decoder=NAME)",
        "stage.kpd.sigma is now stage.kpd.codec.sigma",
    ]
    with pytest.raises(ValueError, match=r"kpd_stage\.kpd\.crop_scale is now kpd_stage\.kpd\.codec\.crop_scale"):
        check_stage_config({"kpd": {"crop_scale": 1.5, "batch_size": 8}}, "kpd_stage")
    check_stage_config(_compose("run", []).kpd_stage, "kpd_stage")  # the shipped configs are clean


def test_old_decoder_override_names_the_new_spelling():
    from hydra.errors import ConfigCompositionException

    with pytest.raises(ConfigCompositionException, match=r"decoder@stage\.kpd\.codec\.decoder"):
        _compose("train", ["decoder@stage.decoder=soft_argmax"])
