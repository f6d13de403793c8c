"""The KPD checkpoint schema (kpd6d.kpd.checkpoint): the codec record, checkpoints from before the
codec, and the validation pose metrics of kpd6d.evaluation.kpd_metrics."""

import json

import numpy as np
import pytest
import torch

from kpd6d.evaluation.kpd_metrics import keypoint_error_px, pose_metrics
from kpd6d.geometry import LINEMOD_K, random_rotation
from kpd6d.kpd.checkpoint import read_kpd_checkpoint, upgrade_hparams
from kpd6d.kpd.module import KPDModule
from kpd6d.pnp.base import BatchPoseEstimate

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _module(**kw):
    rng = np.random.default_rng(0)
    cfg = dict(obj_ids=[3, 7], keypoints_3d=[rng.uniform(-40, 40, (6, 3)) for _ in range(2)], diameters=[120.0, 90.0],
               backbone={"name": "tiny", "width": 16}, head={"name": "deconv", "deconv_channels": 32})
    cfg.update(kw)
    return KPDModule(**cfg)


def _save(module, path, hparams=None):
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(hparams or module.hparams)}, path)
    return path


def _predict(module):
    images = torch.rand(2, 3, 120, 160, generator=torch.Generator().manual_seed(0))
    boxes = torch.tensor([[40.0, 30.0, 50.0, 40.0], [10.0, 20.0, 70.0, 60.0]])
    return module.eval().predict_keypoints(images, boxes, torch.tensor([0, 1]), torch.tensor([3, 7]))


def test_checkpoint_records_one_codec_node(tmp_path):
    torch.manual_seed(0)
    m = _module(codec={"input_size": 64, "sigma": 1.5, "crop_scale": 1.5, "decoder": {"name": "soft_argmax"}})
    hp = read_kpd_checkpoint(_save(m, tmp_path / "new.ckpt"))["hyper_parameters"]
    assert hp["codec"] == {"name": "heatmap", "input_size": 64, "out_stride": 4, "sigma": 1.5, "crop_scale": 1.5,
                           "decoder": {"name": "soft_argmax"}}
    assert not {"input_size", "out_stride", "sigma", "crop_scale", "decoder"} & set(hp)
    loaded = KPDModule.load_checkpoint(tmp_path / "new.ckpt")
    assert loaded.codec.config() == m.codec.config() and loaded.heatmap_size == 16
    kp_a, c_a = _predict(m)
    kp_b, c_b = _predict(loaded)
    assert torch.equal(kp_a, kp_b) and torch.equal(c_a, c_b)


def test_checkpoint_from_before_the_codec_loads(tmp_path):
    """hyper_parameters with the separate input_size / out_stride / sigma / crop_scale / decoder fields
    (as KPD checkpoints were written before the codec) map onto the same codec and predictions."""
    torch.manual_seed(0)
    m = _module(input_size=64, out_stride=4, sigma=1.5, crop_scale=1.5, decoder={"name": "subpixel", "method": "taylor"})
    old = {k: v for k, v in m.hparams.items() if k != "codec"}
    old.update(input_size=64, out_stride=4, sigma=1.5, crop_scale=1.5, decoder={"name": "subpixel", "method": "taylor"})
    assert upgrade_hparams(old)["codec"] == m.hparams.codec
    loaded = KPDModule.load_checkpoint(_save(m, tmp_path / "old.ckpt", old))
    assert loaded.codec.config() == {"name": "heatmap", "input_size": 64, "out_stride": 4, "sigma": 1.5,
                                     "crop_scale": 1.5, "decoder": {"name": "subpixel", "method": "taylor"}}
    kp_a, c_a = _predict(m)
    kp_b, c_b = _predict(loaded)
    assert torch.equal(kp_a, kp_b) and torch.equal(c_a, c_b)


def test_codec_and_separate_fields_together_is_an_error():
    with pytest.raises(ValueError, match="not both"):
        _module(codec={"input_size": 64}, sigma=2.0)
    with pytest.raises(ValueError, match="multiple of out_stride"):
        _module(input_size=66)


def test_read_kpd_checkpoint_names_what_is_wrong(tmp_path):
    (tmp_path / "empty.ckpt").write_bytes(b"")
    with pytest.raises(ValueError, match="empty"):
        read_kpd_checkpoint(tmp_path / "empty.ckpt")
    torch.save({"kpd6d_detector": {}}, tmp_path / "det.pt")
    with pytest.raises(ValueError, match="detector checkpoint"):
        read_kpd_checkpoint(tmp_path / "det.pt")
    torch.save({"state_dict": {}}, tmp_path / "other.ckpt")
    with pytest.raises(ValueError, match="not a kpd6d KPD checkpoint"):
        read_kpd_checkpoint(tmp_path / "other.ckpt")


def test_pose_metrics_count_hits_and_failures():
    rng = np.random.default_rng(1)
    pts = [rng.uniform(-40, 40, (30, 3)) for _ in range(3)]
    R = np.stack([random_rotation(rng) for _ in range(3)])
    t = np.tile([0.0, 0.0, 800.0], (3, 1))
    K = np.broadcast_to(LINEMOD_K, (3, 3, 3))
    t_est = t.copy()
    t_est[2, 0] += 50.0  # instance 2: 50 mm off (a miss on both), instance 1: PnP failed
    poses = BatchPoseEstimate(R=R, t=t_est, ok=np.array([True, False, True]), inliers=np.ones((3, 30), bool),
                              reasons=["", "degenerate", ""])
    m = pose_metrics(poses, R, t, K, pts, [False, True, False], [100.0, 100.0, 100.0])
    assert m == {"proj2d_acc_5px": pytest.approx(1 / 3), "add_acc_0.1d": pytest.approx(1 / 3),
                 "pnp_fail_rate": pytest.approx(1 / 3)}
    # 9 mm off: within 0.1 d (10 mm) for ADD but well over 5 px in projection at 800 mm
    t_est[2, 0] = 9.0
    m = pose_metrics(poses, R, t, K, pts, [False, True, False], [100.0, 100.0, 100.0])
    assert m["add_acc_0.1d"] == pytest.approx(2 / 3) and m["proj2d_acc_5px"] == pytest.approx(1 / 3)


def test_keypoint_error_px_maps_crop_keypoints_back():
    A = torch.tensor([[[2.0, 0.0, -10.0], [0.0, 2.0, -20.0]]], dtype=torch.float64)  # crop = 2 * image - (10, 20)
    img = torch.tensor([[[10.0, 15.0], [30.0, 40.0]]], dtype=torch.float64)
    crop = 2 * img - torch.tensor([10.0, 20.0], dtype=torch.float64)
    err, back = keypoint_error_px(crop + torch.tensor([6.0, 8.0], dtype=torch.float64), A, img)
    assert err.item() == pytest.approx(5.0)  # (6, 8) crop px = (3, 4) image px
    np.testing.assert_allclose(back.numpy(), (img + torch.tensor([3.0, 4.0], dtype=torch.float64)).numpy())


def test_pose_metrics_symmetric_2d_error_takes_the_symmetry_into_account():
    """The validation's 2D accuracy for a symmetric object: a pose equal to GT up to its 180° symmetry
    is a hit with its symmetry transforms and a miss without them (the evaluation's rule)."""
    from kpd6d.evaluation.errors import symmetry_transforms

    rng = np.random.default_rng(2)
    half = rng.uniform(-40, 40, (25, 3))
    Rz = np.diag([-1.0, -1.0, 1.0])  # 180° about the model z axis; the point set has that symmetry
    pts = [np.concatenate([half, half @ Rz.T])]
    R = random_rotation(rng)[None]
    t = np.array([[10.0, -5.0, 700.0]])
    poses = BatchPoseEstimate(R=R @ Rz, t=t.copy(), ok=np.array([True]), inliers=np.ones((1, 50), bool), reasons=[""])
    S = symmetry_transforms({"symmetries_discrete": [np.block([[Rz, np.zeros((3, 1))], [np.zeros((1, 3)), 1.0]]).ravel()]})
    K = LINEMOD_K[None]
    plain = pose_metrics(poses, R, t, K, pts, [True], [100.0])
    sym = pose_metrics(poses, R, t, K, pts, [True], [100.0], [S])
    assert plain["proj2d_acc_5px"] == 0.0 and sym["proj2d_acc_5px"] == 1.0
    assert plain["add_acc_0.1d"] == sym["add_acc_0.1d"] == 1.0  # ADD-S accepts it either way


def test_manifest_member_list_averages_networks(tmp_path):
    """A manifest member given as a list of checkpoints: each keypoint is the coordinate-wise median of
    the networks' estimates (the mean of two), its confidence their mean; each checkpoint is loaded once;
    networks with other keypoints are refused, naming the manifest and the object."""
    from kpd6d.kpd.ensemble import KPDAverage, load_kpd, read_manifest, write_manifest

    paths = []
    for seed in range(3):
        torch.manual_seed(seed)
        paths.append(_save(_module(), tmp_path / f"net{seed}.ckpt"))
    man = write_manifest(tmp_path / "avg.json", {3: paths, 7: paths[:2]})
    assert json.loads(man.read_text())["members"] == {"3": ["net0.ckpt", "net1.ckpt", "net2.ckpt"],
                                                      "7": ["net0.ckpt", "net1.ckpt"]}
    assert read_manifest(man)[3] == [p.resolve() for p in paths]
    ens = load_kpd(man)
    three, two = ens.member(3), ens.member(7)
    assert isinstance(three, KPDAverage) and isinstance(two, KPDAverage)
    assert three.nets[0] is two.nets[0] and three.nets[1] is two.nets[1]  # loaded once
    single = [_predict(KPDModule.load_checkpoint(p)) for p in paths]
    kp, conf = _predict(ens)
    kps = np.stack([s[0].numpy() for s in single])
    confs = np.stack([s[1].numpy() for s in single])
    assert not np.allclose(kps[0], kps[1], atol=0.5)  # the networks disagree: the combination matters
    np.testing.assert_allclose(kp[0].numpy(), np.median(kps[:, 0], axis=0), atol=1e-4)  # object 3: median of 3
    np.testing.assert_allclose(kp[1].numpy(), kps[:2, 1].mean(0), atol=1e-4)  # object 7: mean of 2
    np.testing.assert_allclose(conf[0].numpy(), confs[:, 0].mean(0), atol=1e-5)
    np.testing.assert_allclose(conf[1].numpy(), confs[:2, 1].mean(0), atol=1e-5)
    assert ens.keypoints_3d[3].shape == (6, 3)

    rng = np.random.default_rng(5)
    other = _save(_module(keypoints_3d=[rng.uniform(-40, 40, (6, 3)) for _ in range(2)]), tmp_path / "other.ckpt")
    write_manifest(man, {3: [paths[0], other]})
    with pytest.raises(ValueError, match=r"avg.json', object 3: KPDAverage: network 1 does not have network 0's "
                                         r"objects and keypoints"):
        load_kpd(man)
    man.write_text(json.dumps({"format": "kpd6d-kpd-networks", "version": 1, "members": {"3": []}}))
    with pytest.raises(ValueError, match=r"object 3's member must be a checkpoint path or a non-empty list"):
        read_manifest(man)
    man.write_text(json.dumps({"format": "kpd6d-kpd-networks", "version": 1, "members": {"3": 5}}))
    with pytest.raises(ValueError, match=r"object 3's member must be a checkpoint path .*got 5"):
        read_manifest(man)
