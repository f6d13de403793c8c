"""KPDModule: overfitting a tiny batch, pose metrics, Lightning fit/validate, checkpoint round trip,
and kornia inference crops against the cv2 training crops."""

import cv2
import numpy as np
import pytest
import pytorch_lightning as pl
import torch

from kpd6d.geometry import (
    LINEMOD_K,
    affine_apply,
    bbox_from_points,
    box_to_crop_affine,
    project_points,
    random_rotation,
)
from kpd6d.kpd.module import KPDModule

K_PTS = 6


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _module(**kw):
    rng = np.random.default_rng(0)
    cfg = dict(
        obj_ids=[3, 7], keypoints_3d=[rng.uniform(-40, 40, (K_PTS, 3)) for _ in range(2)], diameters=[120.0, 90.0],
        symmetric=[False, True], model_points=[rng.uniform(-40, 40, (50, 3)) for _ in range(2)],
        backbone={"name": "tiny", "width": 16}, head={"name": "deconv", "deconv_channels": 32},
        input_size=64, out_stride=4, sigma=1.5, crop_scale=1.5, decoder={"name": "subpixel"},
        optimizer={"name": "adam", "lr": 3e-3},
    )
    cfg.update(kw)
    return KPDModule(**cfg)


def _scene(module, n=4, seed=0, size=(160, 120)):
    """Images with a blob per keypoint, their GT poses and the crop items a KPDCropDataset would give."""
    rng = np.random.default_rng(seed)
    W, H = size
    K = LINEMOD_K.copy()
    K[0, 2], K[1, 2] = W / 2, H / 2
    items, images = [], []
    for i in range(n):
        oi = i % 2
        kp3 = np.asarray(module.hparams.keypoints_3d[oi])

        R, t = random_rotation(rng), np.array([rng.uniform(-30, 30), rng.uniform(-20, 20), 1000.0])
        uv = project_points(kp3, K, R, t)
        img = np.zeros((H, W, 3), np.uint8)
        img[:] = rng.integers(0, 60, 3)
        for j, (u, v) in enumerate(uv):
            cv2.circle(img, (round(u), round(v)), 2, (40 * j % 255, 255 - 30 * j, 120 + 20 * j), -1)
        box = bbox_from_points(uv)
        A = box_to_crop_affine(box, 64, scale=module.codec.crop_scale)
        crop = cv2.warpAffine(img, A, (64, 64), flags=cv2.INTER_LINEAR)
        images.append(img)
        items.append({
            "image": torch.from_numpy(crop.transpose(2, 0, 1).copy()).float() / 255, "keypoints": torch.from_numpy(affine_apply(A, uv)).float(),
            "keypoints_image": torch.from_numpy(uv).float(), "visibility": torch.ones(K_PTS), "affine": torch.from_numpy(A),
            "box": torch.from_numpy(box), "K": torch.from_numpy(K), "R": torch.from_numpy(R), "t": torch.from_numpy(t),
            "obj_id": module.obj_ids[oi], "obj_index": oi,
        })
    return images, items


def _collate(items):
    return torch.utils.data.default_collate(items)


def test_overfit_tiny_batch_recovers_keypoints():
    torch.manual_seed(0)
    module = _module()
    _, items = _scene(module)
    batch = _collate(items)
    target = module.targets(batch["keypoints"])
    opt = module.configure_optimizers()
    module.train()
    first = None
    for _ in range(200):
        loss = module.heatmap_loss(module(batch["image"], batch["obj_index"]), target, batch["visibility"])
        first = first if first is not None else loss.item()
        opt.zero_grad()
        loss.backward()
        opt.step()
    module.eval()
    with torch.no_grad():
        pred = module(batch["image"], batch["obj_index"])
        final = module.heatmap_loss(pred, target, None).item()
        kp, conf = module.decode(pred)
    assert final < 0.01 * first and final < 1e-3
    err = (kp - batch["keypoints"]).norm(dim=-1)
    assert err.max() < 1.0, err
    assert conf.min() > 0.5
    # and the same through the inference API, from the full images (crops by kornia)
    imgs = torch.stack([torch.from_numpy(im.transpose(2, 0, 1).copy()).float() / 255 for im in _scene(module)[0]])
    kp_img, _ = module.predict_keypoints(imgs, batch["box"], torch.arange(4), batch["obj_id"])
    assert (kp_img - batch["keypoints_image"]).norm(dim=-1).max() < 1.0 / 64 * 1.3 * batch["box"][:, 2:].max() + 0.5


def test_pose_metrics_exact_and_wrong_keypoints():
    module = _module()
    _, items = _scene(module, n=4, seed=3)
    b = _collate(items)
    conf = torch.ones(4, K_PTS)
    good = module.pose_metrics(b["keypoints_image"].double(), conf, b["obj_id"], b["K"], b["R"], b["t"])
    assert good == {"proj2d_acc_5px": 1.0, "add_acc_0.1d": 1.0, "pnp_fail_rate": 0.0}
    shifted = b["keypoints_image"].double() + torch.tensor([15.0, 0.0])  # 15 px off everywhere
    bad = module.pose_metrics(shifted, conf, b["obj_id"], b["K"], b["R"], b["t"])
    assert bad["proj2d_acc_5px"] == 0.0


def test_loss_visibility_weighting():
    module = _module(loss={"visibility_weighted": True, "invisible_weight": 0.0})
    pred = torch.zeros(1, 2, 4, 4)
    target = torch.zeros(1, 2, 4, 4)
    target[0, 1] = 1.0  # only the invisible keypoint is wrong
    assert module.heatmap_loss(pred, target, torch.tensor([[1.0, 0.0]])).item() == 0.0
    plain = _module()
    assert plain.heatmap_loss(pred, target, torch.tensor([[1.0, 0.0]])).item() == pytest.approx(0.5)
    with pytest.raises(ValueError, match="unknown loss option"):
        _module(loss={"focal": True})


def test_fit_validate_checkpoint_round_trip(tmp_path):
    torch.manual_seed(0)
    module = _module(augment={"rotation_deg": 10.0, "geometric_p": 0.5})
    _, items = _scene(module, n=4, seed=1)
    loader = torch.utils.data.DataLoader(items, batch_size=2, collate_fn=_collate)
    trainer = pl.Trainer(max_steps=2, accelerator="cpu", logger=False, enable_checkpointing=False,
                         enable_progress_bar=False, enable_model_summary=False, default_root_dir=tmp_path)
    trainer.fit(module, loader, loader)
    logged = trainer.callback_metrics
    for key in ("train/loss", "val/loss", "val/kp_err_px", "val/proj2d_acc_5px", "val/add_acc_0.1d"):
        assert key in logged and torch.isfinite(logged[key]), key
    path = tmp_path / "kpd.ckpt"
    trainer.save_checkpoint(path)

    loaded = KPDModule.load_checkpoint(path)
    module.eval()
    assert loaded.obj_ids == [3, 7]
    np.testing.assert_allclose(loaded.keypoints_3d[7], module.keypoints_3d[7])
    assert loaded.codec.input_size == 64 and loaded.hparams.codec["decoder"] == {"name": "subpixel"}
    images = torch.rand(2, 3, 120, 160)
    boxes = torch.tensor([[40.0, 30.0, 50.0, 40.0], [10.0, 20.0, 70.0, 60.0], [80.0, 50.0, 30.0, 30.0]])
    args = (images, boxes, torch.tensor([0, 1, 1]), torch.tensor([3, 7, 3]))
    kp_a, c_a = module.predict_keypoints(*args)
    kp_b, c_b = loaded.predict_keypoints(*args)
    assert kp_a.shape == (3, K_PTS, 2) and c_a.shape == (3, K_PTS)
    assert torch.equal(kp_a, kp_b) and torch.equal(c_a, c_b)
    with pytest.raises(KeyError, match=r"covers \[3, 7\]"):
        loaded.predict_keypoints(images, boxes[:1], torch.tensor([0]), torch.tensor([5]))
    with pytest.raises(FileNotFoundError, match=r"nothing\.ckpt"):
        KPDModule.load_checkpoint(tmp_path / "nothing.ckpt")


def test_kornia_inference_crop_matches_cv2_training_crop():
    module = _module()
    rng = np.random.default_rng(5)
    img = rng.integers(0, 256, (120, 160, 3)).astype(np.uint8)
    img = cv2.GaussianBlur(img, (0, 0), 2.0)  # smooth, so interpolation differences stay small
    box = np.array([37.3, 22.9, 61.2, 48.4])
    A = box_to_crop_affine(box, 64, scale=module.codec.crop_scale)
    ref = cv2.warpAffine(img.astype(np.float32), A, (64, 64), flags=cv2.INTER_LINEAR)
    from kornia.geometry.transform import warp_affine

    t = torch.from_numpy(img.transpose(2, 0, 1).copy()).float()[None]
    got = warp_affine(t, torch.from_numpy(A).float()[None], (64, 64), align_corners=True)[0].numpy().transpose(1, 2, 0)
    assert np.abs(got - ref).max() < 1.0  # grey levels out of 255


def test_optimizer_and_scheduler_config():
    m = _module(optimizer={"name": "sgd", "lr": 0.1, "momentum": 0.9}, scheduler={"name": "step", "step_size": 5})
    cfg = m.configure_optimizers()
    assert isinstance(cfg["optimizer"], torch.optim.SGD)
    assert isinstance(cfg["lr_scheduler"]["scheduler"], torch.optim.lr_scheduler.StepLR)
    assert isinstance(_module().configure_optimizers(), torch.optim.Adam)
    with pytest.raises(ValueError, match="unknown optimizer 'lion'"):
        _module(optimizer={"name": "lion"}).configure_optimizers()


def test_bf16_autocast_forward_loss_and_decode():
    module = _module()
    _, items = _scene(module, n=2, seed=4)
    b = _collate(items)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        pred = module(b["image"], b["obj_index"])
        loss = module.heatmap_loss(pred, module.targets(b["keypoints"]), b["visibility"])
    assert pred.dtype == torch.bfloat16 and loss.dtype == torch.float32 and torch.isfinite(loss)
    loss.backward()
    kp, conf = module.decode(pred)
    assert kp.dtype == torch.float32 and torch.isfinite(kp).all() and conf.shape == (2, K_PTS)


def test_validation_2d_error_uses_the_checkpoints_symmetries():
    """Object 7 is symmetric with a 180° symmetry about z in its hparams: keypoints of GT composed with
    that symmetry are a 2D hit in validation (the evaluation's symmetric 2D error), object 3's are not."""
    from kpd6d.geometry import project_points

    Sz = np.diag([-1.0, -1.0, 1.0, 1.0])
    sym = [{"symmetries_discrete": [], "symmetries_continuous": []},
           {"symmetries_discrete": [Sz.ravel().tolist()], "symmetries_continuous": []}]
    module = _module(symmetries=sym)
    assert module._symmetry_transforms(0) is None and module._symmetry_transforms(1).shape == (2, 4, 4)
    rng = np.random.default_rng(5)
    R = np.stack([random_rotation(rng) for _ in range(2)])
    t = np.array([[5.0, -3.0, 900.0], [0.0, 8.0, 900.0]])
    obj = torch.tensor([3, 7])
    kp = np.stack([project_points(np.asarray(module.hparams.keypoints_3d[i]), LINEMOD_K, R[i] @ Sz[:3, :3], t[i])
                   for i in range(2)])
    m = module.pose_metrics(torch.from_numpy(kp), torch.ones(2, K_PTS), obj, torch.from_numpy(np.stack([LINEMOD_K] * 2)),
                            torch.from_numpy(R), torch.from_numpy(t))
    assert m["proj2d_acc_5px"] == 0.5  # object 7 a hit (symmetric), object 3 a miss (rotated 180°)


def test_coordinate_loss_is_the_l1_error_of_the_decoded_centroid():
    """loss.coord_weight: the L1 distance (heatmap px) between the soft-argmax centroid and the target,
    checked against a centroid computed by hand; keypoints outside the heatmap weigh 0."""
    module = _module(loss={"coord_weight": 0.5, "coord_window": 1})  # decoded with the default subpixel
    S = module.codec.heatmap_size  # 16
    pred = torch.zeros(1, 2, S, S)
    pred[0, 0, 5, 7], pred[0, 0, 5, 8], pred[0, 0, 6, 7] = 1.0, 0.5, 0.25  # peak (7, 5), (x, y)
    pred[0, 1, 2, 2] = 1.0
    cx = (7 * 1.0 + 8 * 0.5 + 7 * 0.25) / 1.75
    cy = (5 * 1.0 + 5 * 0.5 + 6 * 0.25) / 1.75
    target_hm = torch.tensor([[[6.0, 6.0], [40.0, 2.0]]])  # the second keypoint lies outside the heatmap
    kps_crop = (target_hm + 0.5) * module.codec.out_stride - 0.5
    num, den = module.coordinate_loss_terms(pred, kps_crop, None)
    assert den.item() == 1.0
    assert num.item() == pytest.approx(abs(cx - 6.0) + abs(cy - 6.0), rel=1e-5)
    # visibility-weighted: an invisible keypoint inside the heatmap weighs invisible_weight (here 0)
    weighted = _module(loss={"coord_weight": 0.5, "coord_window": 1, "visibility_weighted": True})
    inside_both = (torch.tensor([[[6.0, 6.0], [3.0, 2.0]]]) + 0.5) * module.codec.out_stride - 0.5
    n_all, d_all = module.coordinate_loss_terms(pred, inside_both, torch.tensor([[0.0, 1.0]]))
    n_vis, d_vis = weighted.coordinate_loss_terms(pred, inside_both, torch.tensor([[0.0, 1.0]]))
    assert d_all.item() == 2.0 and d_vis.item() == 1.0
    assert n_vis.item() == pytest.approx(n_all.item() - num.item(), rel=1e-5)  # only the second keypoint's error
    # gradient descent on the (positive) heatmap values alone moves the centroid onto the target
    h = (pred + 0.1).requires_grad_(True)
    opt = torch.optim.SGD([h], lr=0.05)
    for _ in range(200):
        n, _ = module.coordinate_loss_terms(h, kps_crop[:, :1], None)
        opt.zero_grad()
        n.backward()
        opt.step()
    assert module.coordinate_loss_terms(h.detach(), kps_crop[:, :1], None)[0].item() < 0.1 * num.item()


def test_training_step_adds_the_weighted_coordinate_loss():
    torch.manual_seed(0)
    module = _module(loss={"coord_weight": 2.0})
    _, items = _scene(module)
    batch = _collate(items)
    batch["heatmaps"] = module.targets(batch["keypoints"])
    with torch.no_grad():
        total = module.training_step(batch, 0)
        pred = module(batch["image"], batch["obj_index"])
        heat = module.heatmap_loss(pred, batch["heatmaps"], batch["visibility"])
        num, den = module.coordinate_loss_terms(pred, batch["keypoints"], batch["visibility"])
    assert den.item() == 4 * K_PTS
    assert total.item() == pytest.approx(heat.item() + 2.0 * num.item() / den.item(), rel=1e-5)
    with pytest.raises(ValueError, match="coord_window must be an integer >= 1"):
        _module(loss={"coord_weight": 1.0, "coord_window": 0})
    with pytest.raises(ValueError, match="coord_weight must be a number >= 0"):
        _module(loss={"coord_weight": -1.0})


def test_training_step_negative_crops_learn_empty_heatmaps():
    """A crop flagged ``negative`` (kpd6d.kpd.crops) is trained towards all-zero heatmaps with full weight,
    even with visibility weighting, and adds nothing to the coordinate loss; positive crops are unchanged."""
    torch.manual_seed(0)
    module = _module(loss={"coord_weight": 2.0, "visibility_weighted": True, "invisible_weight": 0.0})
    _, items = _scene(module)
    batch = _collate(items)
    batch["heatmaps"] = module.targets(batch["keypoints"])
    batch["negative"] = torch.tensor([0.0, 1.0, 0.0, 1.0])
    batch["visibility"] = batch["visibility"] * (1 - batch["negative"])[:, None]  # as the dataset gives them
    with torch.no_grad():
        total = module.training_step(batch, 0)
        pred = module(batch["image"], batch["obj_index"]).float()
    pos = torch.tensor([0, 2])
    neg = torch.tensor([1, 3])
    per_kp_pos = ((pred[pos] - batch["heatmaps"][pos]) ** 2).mean(dim=(-1, -2))  # (2, k)
    per_kp_neg = (pred[neg] ** 2).mean(dim=(-1, -2))  # towards zero everywhere
    heat = module.loss_scale * (per_kp_pos.sum() + per_kp_neg.sum()) / (4 * K_PTS)
    num, den = module.coordinate_loss_terms(pred[pos], batch["keypoints"][pos], batch["visibility"][pos])
    assert total.item() == pytest.approx(heat.item() + 2.0 * num.item() / den.item(), rel=1e-5)
