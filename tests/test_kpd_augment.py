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


def _coordinate_images(B, S=64):
    """Crop b holds (b / B, y / (S - 1), x / (S - 1)) in its three channels: where each pixel came from."""
    ys, xs = torch.meshgrid(torch.arange(S, dtype=torch.float32), torch.arange(S, dtype=torch.float32), indexing="ij")
    img = torch.stack([torch.zeros(S, S), ys / (S - 1), xs / (S - 1)]).expand(B, 3, S, S).clone()
    img[:, 0] = (torch.arange(B, dtype=torch.float32) / B).view(B, 1, 1)
    return img


def test_paste_occluders_translate_an_ellipse_from_another_crops_centre():
    from kpd6d.kpd.augment import paste_occluders

    B, S = 32, 64
    img = _coordinate_images(B, S)
    g = torch.Generator().manual_seed(3)
    out = paste_occluders(img, 1.0, size=(0.1, 0.25), offset=(0.2, 0.45), generator=g)
    c = (S - 1) / 2
    for b in range(B):
        changed = (out[b] != img[b]).any(0)
        assert changed.sum() > 0, b
        yy, xx = torch.nonzero(changed, as_tuple=True)
        src = out[b][:, yy, xx]
        owner = torch.round(src[0] * B).long()
        assert (owner == owner[0]).all() and owner[0] != b          # one other crop
        sy, sx = torch.round(src[1] * (S - 1)), torch.round(src[2] * (S - 1))
        dy, dx = yy.float() - sy, xx.float() - sx
        assert (dy == dy[0]).all() and (dx == dx[0]).all()          # a pure translation
        assert 0.2 * S - 1 <= float(torch.hypot(dy[0], dx[0])) <= 0.45 * S + 1  # pasted off-centre, by `offset`
        r_src = torch.hypot(sy - c, sx - c)
        assert r_src.max() <= 0.25 * S + 1                          # cut around the other crop's centre
        assert changed.sum() <= torch.pi * (0.25 * S + 1) ** 2


def test_paste_occluders_probability_and_repeatability():
    from kpd6d.kpd.augment import paste_occluders

    img = _coordinate_images(400, 32)
    assert torch.equal(paste_occluders(img, 0.0), img)
    assert torch.equal(paste_occluders(img[:1], 1.0), img[:1])  # nothing to paste from
    a = paste_occluders(img, 0.3, generator=torch.Generator().manual_seed(0))
    b = paste_occluders(img, 0.3, generator=torch.Generator().manual_seed(0))
    assert torch.equal(a, b)
    share = (a != img).flatten(1).any(1).float().mean().item()
    assert 0.22 < share < 0.38  # 0.3 +- 4 binomial standard deviations (n = 400)


def test_paste_settings_are_checked():
    import pytest

    for kw, word in (({"paste_p": 1.5}, "paste_p"), ({"paste_size": [0.3, 0.1]}, "paste_size"),
                     ({"paste_offset": [0.1, 2.0]}, "paste_offset"), ({"paste_size": 0.2}, "paste_size")):
        with pytest.raises(ValueError, match=word):
            BatchAugment(**kw)
    aug = BatchAugment(hue=0, saturation=1, exposure=1, blur_p=0, noise_p=0, erase_p=0, paste_p=1.0)
    img = _coordinate_images(8, 32)
    kp = torch.rand(8, 5, 2) * 31
    out, moved, _ = aug(img, kp)
    assert torch.equal(moved, kp) and (out != img).flatten(1).any(1).all()  # targets stay, every crop occluded
