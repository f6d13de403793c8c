"""kornia batch augmentation: keypoints move with the image under geometric transforms."""

import torch

from kpd6d.kpd.augment import BatchAugment
from kpd6d.kpd.heatmaps import gaussian_heatmaps
from kpd6d.registry import DECODERS


def _dot_images(kp, size=64, sigma=2.5):
    return gaussian_heatmaps(kp, size, sigma).expand(kp.shape[0], 3, size, size).contiguous()


def test_geometric_augmentation_moves_keypoints_with_the_image():
    torch.manual_seed(0)
    aug = BatchAugment(rotation_deg=30, scale=(0.8, 1.2), translate=0.1, geometric_p=1.0,
                       color_p=0, blur_p=0, noise_p=0, erase_p=0)
    kp = torch.rand(16, 1, 2) * 30 + 17
    out, moved, M = aug(_dot_images(kp), kp)
    assert not torch.allclose(moved, kp, atol=1.0)  # they did move
    # find the warped dot's centre independently (intensity centroid around its peak)
    found, _ = DECODERS.build("soft_argmax", window=7)(out[:, :1])
    assert (found - moved).abs().max() < 0.1
    # the returned matrix is what moved them
    hom = torch.cat([kp[:, 0], torch.ones(16, 1)], -1)
    assert torch.allclose((M @ hom[..., None])[..., :2, 0], moved[:, 0], atol=1e-4)


def test_no_geometric_means_no_motion_and_photometric_range():
    torch.manual_seed(0)
    aug = BatchAugment(hue=0.05, saturation=1.5, exposure=1.5, blur_p=0.5, noise_p=0.5, erase_p=0.5)
    assert aug.geometric is None
    img = torch.rand(8, 3, 32, 32) * 0.5 + 0.25
    kp = torch.rand(8, 4, 2) * 31
    out, moved, M = aug(img, kp)
    assert torch.equal(moved, kp) and torch.equal(M, torch.eye(3).expand(8, 3, 3))
    assert out.shape == img.shape and out.min() >= 0 and out.max() <= 1
    assert not torch.allclose(out, img)


def test_exposure_factor_bounds():
    torch.manual_seed(0)
    aug = BatchAugment(hue=0.0, saturation=1.0, exposure=1.5, blur_p=0, noise_p=0, erase_p=0)
    img = torch.full((200, 3, 4, 4), 0.4)
    out, _, _ = aug(img)
    f = out[:, 0, 0, 0] / 0.4
    assert f.min() >= 1 / 1.5 - 1e-4 and f.max() <= 1.5 + 1e-4
    assert f.min() < 0.75 and f.max() > 1.35  # the full range is used
