"""Training-time photometric augmentation (kpd6d.photo_augment), shared by the detector and the KPD."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from kpd6d.photo_augment import amplitude_mix_batch, check_photometric, gaussian_blur_batch, photometric_batch


def _images(B=4, H=40, W=50, lo=0.3, hi=0.7, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand((B, 3, H, W), generator=g) * (hi - lo) + lo


def test_check_names_unknown_and_bad_settings():
    with pytest.raises(ValueError, match=r"unknown photometric setting\(s\) \['contrst'\].*contrast"):
        check_photometric({"contrst": 1.2})
    with pytest.raises(ValueError, match=r"augment.photometric.gamma is a factor >= 1"):
        check_photometric({"gamma": 0.8}, "augment.photometric")
    with pytest.raises(ValueError, match="blur_p is a probability"):
        check_photometric({"blur_p": 1.5})
    with pytest.raises(ValueError, match="blur_sigma"):
        check_photometric({"blur_sigma": [2.0, 1.0]})
    with pytest.raises(ValueError, match="channel_gain"):
        check_photometric({"channel_gain": 1.0})


def test_all_off_is_the_identity():
    x = _images()
    assert photometric_batch(x, check_photometric({})) is x


def test_contrast_scales_about_the_image_mean():
    x = _images()
    y = photometric_batch(x, check_photometric({"contrast": 1.5}), torch.Generator().manual_seed(1))
    # mid-range images: nothing clipped, so the mean is kept and deviations scale by one factor per image
    torch.testing.assert_close(y.mean(dim=(1, 2, 3)), x.mean(dim=(1, 2, 3)), atol=1e-5, rtol=0)
    dx, dy = x - x.mean(dim=(1, 2, 3), keepdim=True), y - y.mean(dim=(1, 2, 3), keepdim=True)
    c = (dy * dx).sum(dim=(1, 2, 3)) / (dx * dx).sum(dim=(1, 2, 3))
    torch.testing.assert_close(dy, dx * c[:, None, None, None], atol=1e-5, rtol=0)
    assert ((c >= 1 / 1.5 - 1e-6) & (c <= 1.5 + 1e-6)).all() and c.std() > 0  # drawn per image


def test_channel_gain_and_gamma_are_per_image_per_channel_factors():
    x = _images()
    y = photometric_batch(x, check_photometric({"channel_gain": 0.2}), torch.Generator().manual_seed(2))
    ratio = y / x  # one gain per (image, channel)
    torch.testing.assert_close(ratio, ratio[:, :, :1, :1].expand_as(ratio), atol=1e-5, rtol=0)
    assert ((ratio - 1).abs() <= 0.2 + 1e-5).all() and (ratio - 1).abs().max() > 0.02
    z = photometric_batch(x, check_photometric({"gamma": 1.4}), torch.Generator().manual_seed(3))
    g = torch.log(z) / torch.log(x)  # one exponent per image
    torch.testing.assert_close(g, g[:, :1, :1, :1].expand_as(g), atol=1e-4, rtol=0)
    assert ((g >= 1 / 1.4 - 1e-4) & (g <= 1.4 + 1e-4)).all()


def test_blur_matches_opencv():
    x = torch.rand((2, 3, 30, 36), generator=torch.Generator().manual_seed(4))
    sigma = torch.tensor([0.8, 1.7])
    y = gaussian_blur_batch(x, sigma)
    r = int(np.ceil(3 * 1.7))
    for b, s in enumerate(sigma.tolist()):
        img = x[b].permute(1, 2, 0).numpy()
        ref = cv2.GaussianBlur(img, (2 * r + 1, 2 * r + 1), s, borderType=cv2.BORDER_REFLECT_101)
        np.testing.assert_allclose(y[b].permute(1, 2, 0).numpy(), ref, atol=2e-5)
    torch.testing.assert_close(gaussian_blur_batch(x, torch.zeros(2)), x)  # sigma 0: unchanged


def test_blur_and_noise_probabilities_and_seeding():
    x = _images(B=64)
    cfg = check_photometric({"blur_p": 0.5, "blur_sigma": [1.0, 2.0], "noise_p": 0.5, "noise_std": 0.05})
    y1 = photometric_batch(x, cfg, torch.Generator().manual_seed(5))
    y2 = photometric_batch(x, cfg, torch.Generator().manual_seed(5))
    torch.testing.assert_close(y1, y2)  # the generator makes a run repeatable
    changed = (y1 - x).abs().flatten(1).max(1).values > 1e-6
    assert 10 < int(changed.sum()) < 64  # some images left alone: each effect has its probability
    # noise alone: zero-mean, std up to noise_std
    n = photometric_batch(x, check_photometric({"noise_p": 1.0, "noise_std": 0.05}), torch.Generator().manual_seed(6))
    d = (n - x).flatten(1)
    assert d.mean().abs() < 2e-3 and (d.std(1) <= 0.05 * 1.05).all() and d.std(1).max() > 0.02


def test_sharpening_is_an_unsharp_mask():
    x = _images(B=3, H=30, W=36) * 0.6 + 0.2  # away from 0 and 1: the clip stays out of the comparison
    y = photometric_batch(x, check_photometric({"sharpen_p": 1.0, "sharpen_amount": [0.8, 0.8]}))
    for b in range(3):  # OpenCV's Gaussian (sigma 1, radius 3, reflect-101 border) as the reference blur
        img = x[b].permute(1, 2, 0).numpy()
        ref = np.clip(img + 0.8 * (img - cv2.GaussianBlur(img, (7, 7), 1.0, borderType=cv2.BORDER_REFLECT_101)), 0, 1)
        np.testing.assert_allclose(y[b].permute(1, 2, 0).numpy(), ref, atol=2e-5)
    # amount drawn per image, some images left alone with sharpen_p 0.5; the mean level is kept
    cfg = check_photometric({"sharpen_p": 0.5, "sharpen_amount": [0.3, 1.5]})
    many = _images(B=64) * 0.6 + 0.2
    z = photometric_batch(many, cfg, torch.Generator().manual_seed(7))
    changed = (z - many).abs().flatten(1).max(1).values > 1e-6
    assert 10 < int(changed.sum()) < 54
    assert (z - many).mean().abs() < 2e-3 and (z - many).abs().max() > 0.05
    for bad in ([1.0, 0.5], [-0.1, 1.0]):
        with pytest.raises(ValueError, match=r"augment.sharpen_amount must be \[lo, hi\]"):
            check_photometric({"sharpen_amount": bad})
    with pytest.raises(ValueError, match=r"augment.sharpen_p is a probability"):
        check_photometric({"sharpen_p": 2.0})


def test_both_stages_apply_it():
    from kpd6d.detection.augment import augment_batch
    from kpd6d.kpd.augment import BatchAugment

    x = _images(B=2, H=48, W=64)
    targets = [{"boxes": torch.tensor([[10.0, 10.0, 20.0, 15.0]]), "labels": torch.tensor([1])}] * 2
    cfg = check_photometric({"contrast": 1.5, "channel_gain": 0.2})
    y, t = augment_batch(x, targets, torch.Generator().manual_seed(0), hsv=1.0, scale=0.0, photometric=cfg)
    assert not torch.allclose(y, x) and torch.equal(t[0]["boxes"], targets[0]["boxes"])
    aug = BatchAugment(hue=0, saturation=1, exposure=1, blur_p=0, noise_p=0, erase_p=0, contrast=1.5, channel_gain=0.2)
    kps = torch.rand(2, 5, 2) * 40
    y, k, _ = aug(x, kps)
    assert not torch.allclose(y, x) and torch.equal(k, kps)  # photometric only: keypoints stay
    with pytest.raises(ValueError, match="gamma"):
        BatchAugment(gamma=0.5)


def _numpy_amplitude_mix(a: np.ndarray, b: np.ndarray, w: float) -> np.ndarray:
    """Independent reference: full 2D FFT per channel, amplitude blended, a's phase kept."""
    fa, fb = np.fft.fft2(a.astype(np.float64)), np.fft.fft2(b.astype(np.float64))
    out = np.fft.ifft2(((1 - w) * np.abs(fa) + w * np.abs(fb)) * np.exp(1j * np.angle(fa)))
    assert np.abs(out.imag).max() < 1e-9  # a blend of two Hermitian amplitude spectra keeps the image real
    return out.real


def test_amplitude_mix_matches_numpy_and_keeps_the_phase():
    x = _images(B=3, H=24, W=31)  # odd width: the real FFT's last axis is not symmetric
    w = torch.tensor([0.0, 0.4, 1.0])
    partner = torch.tensor([1, 2, 0])
    y = amplitude_mix_batch(x, w, partner)
    for i in range(3):
        ref = _numpy_amplitude_mix(x[i].numpy(), x[partner[i]].numpy(), float(w[i]))
        np.testing.assert_allclose(y[i].numpy(), ref, atol=1e-5)
    np.testing.assert_allclose(y[0].numpy(), x[0].numpy(), atol=1e-5)  # weight 0: the image itself
    # weight 1: the partner's amplitude (so its mean grey, the DC term), the image's own phase
    fy, fx, fp = (np.fft.fft2(v.numpy().astype(np.float64)) for v in (y[2], x[2], x[0]))
    np.testing.assert_allclose(np.abs(fy), np.abs(fp), atol=1e-3)
    strong = np.abs(fp) > 1e-2
    dphi = np.angle(fy[strong] * np.conj(fx[strong]))
    assert np.abs(dphi).max() < 1e-3


def test_amplitude_mixing_in_the_batch_pipeline():
    x = _images(B=6, H=32, W=32, lo=0.2, hi=0.8)
    cfg = check_photometric({"amplitude_p": 1.0, "amplitude_mix": 0.5})
    y = photometric_batch(x, cfg, torch.Generator().manual_seed(3))
    y2 = photometric_batch(x, cfg, torch.Generator().manual_seed(3))
    assert torch.equal(y, y2)  # seeded: repeatable
    assert y.min() >= 0 and y.max() <= 1
    assert all(not torch.allclose(y[i], x[i], atol=1e-3) for i in range(6))  # every image mixed (p = 1)
    # a weight of at most 0.5 keeps each image closer to itself than to any other image of the batch
    d = torch.cdist(y.flatten(1), x.flatten(1))
    assert torch.equal(d.argmin(dim=1), torch.arange(6))
    off = photometric_batch(x, check_photometric({"amplitude_p": 0.0}))
    assert off is x
    single = x[:1]
    assert torch.equal(photometric_batch(single, cfg), single)  # no partner in a batch of one: unchanged
    for bad, match in (({"amplitude_p": 1.5}, "amplitude_p is a probability"),
                       ({"amplitude_mix": 1.2}, r"amplitude_mix is the largest weight.*\[0, 1\]")):
        with pytest.raises(ValueError, match=match):
            check_photometric(bad)
    from kpd6d.kpd.augment import BatchAugment

    aug = BatchAugment(hue=0, saturation=1, exposure=1, blur_p=0, noise_p=0, erase_p=0, amplitude_p=1.0)
    kps = torch.rand(6, 5, 2) * 30
    out, k, _ = aug(x, kps)
    assert not torch.allclose(out, x) and torch.equal(k, kps)
