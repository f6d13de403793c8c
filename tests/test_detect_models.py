"""Detector inference API: shapes, dtypes, score order, the oracle, CenterNet decoding and targets,
bad input and checkpoints."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from kpd6d.detection import DetectionInputError, Detections, build_detector, load_detector, save_detector
from kpd6d.detection.centernet import (
    CenterNet,
    centernet_targets,
    decode_centernet,
    focal_loss,
    gaussian_radius,
    giou_loss,
)
from kpd6d.detection.detections import keep_best_per_class, merge_scales
from kpd6d.registry import DETECTORS, UnknownNameError, build_from_cfg

OBJ_IDS = [3, 7, 11]


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _check_detections(dets, n_images, device="cpu", max_det=None, obj_ids=OBJ_IDS):
    assert isinstance(dets, list) and len(dets) == n_images
    for d in dets:
        assert isinstance(d, Detections)
        n = len(d)
        assert d.boxes.shape == (n, 4) and d.obj_ids.shape == (n,) and d.scores.shape == (n,)
        assert d.boxes.dtype == torch.float32 and d.scores.dtype == torch.float32 and d.obj_ids.dtype == torch.long
        assert d.boxes.device.type == device
        if n > 1:
            assert bool((d.scores[:-1] >= d.scores[1:]).all()), d.scores
        if max_det is not None:
            assert n <= max_det
        assert set(d.obj_ids.tolist()) <= set(obj_ids)


def test_registry_lists_the_detectors():
    assert {"centernet", "fcos", "faster_rcnn", "oracle"} <= set(DETECTORS.names())
    with pytest.raises(UnknownNameError, match="centernet"):
        DETECTORS.build("yolo9000")


@pytest.mark.parametrize("name", ["centernet", "fcos", "faster_rcnn"])
def test_learned_detectors_inference_shapes_and_order(name):
    torch.manual_seed(0)
    det = build_detector(name, obj_ids=OBJ_IDS, input_size=[96, 64], score_threshold=0.0, max_detections=7)
    images = torch.rand(2, 3, 128, 192)  # resized to 96x64 inside, boxes mapped back
    dets = det.predict(images)
    _check_detections(dets, 2, max_det=7)
    assert sum(len(d) for d in dets) > 0  # untrained nets still score something with threshold 0
    for d in dets:  # boxes are in the input image's frame (x2 of the network's)
        assert float(d.boxes[:, 0].min()) > -192 and float(d.boxes[:, 0].max()) < 2 * 192
    # a high threshold keeps only what passes it
    det.score_threshold = 0.99
    for d in det.predict(images):
        assert bool((d.scores >= 0.99).all())


def test_centernet_one_per_object_and_device_and_training_mode_kept():
    torch.manual_seed(1)
    det = build_detector("centernet", obj_ids=OBJ_IDS, backbone="resnet10t", input_size=None, score_threshold=0.0,
                         max_detections=50, one_per_object=True)
    det.train()
    dets = det.predict(torch.rand(3, 3, 64, 96))
    assert det.training  # predict restores the mode
    _check_detections(dets, 3)
    for d in dets:
        ids = d.obj_ids.tolist()
        assert len(ids) == len(set(ids)) == len(OBJ_IDS)


def test_keep_best_per_class_against_a_loop():
    g = torch.Generator().manual_seed(0)
    labels = torch.randint(0, 4, (5, 12), generator=g)
    valid = torch.rand((5, 12), generator=g) > 0.3
    mask = keep_best_per_class(labels, valid, 4)
    for b in range(5):
        seen, expect = set(), []
        for j in range(12):
            ok = bool(valid[b, j]) and int(labels[b, j]) not in seen
            if ok:
                seen.add(int(labels[b, j]))
            expect.append(ok)
        assert mask[b].tolist() == expect


def test_centernet_decoding_of_a_hand_made_heatmap():
    # two images, 2 classes, 8x10 grid, stride 4: peaks placed by hand, sizes/offsets at the peaks
    heat = torch.zeros(2, 2, 8, 10)
    wh = torch.zeros(2, 2, 8, 10)
    off = torch.zeros(2, 2, 8, 10)
    peaks = [  # (image, class, y, x, score, w, h, ox, oy)
        (0, 0, 2, 3, 0.9, 5.0, 4.0, 0.25, 0.5),
        (0, 1, 6, 8, 0.7, 2.0, 3.0, 0.0, 0.75),
        (1, 1, 4, 4, 0.8, 6.0, 2.0, 0.5, 0.5),
    ]
    for b, c, y, x, s, w, h, ox, oy in peaks:
        heat[b, c, y, x] = s
        wh[b, :, y, x] = torch.tensor([w, h])
        off[b, :, y, x] = torch.tensor([ox, oy])
    heat[0, 0, 2, 4] = 0.6  # a neighbour of the first peak: not a local maximum, must be suppressed
    heat[1, 0, 0, 0] = 0.05  # a weak isolated peak (survives decoding; thresholded later)
    boxes, labels, scores = decode_centernet(heat, wh, off, stride=4, k=3)
    assert boxes.shape == (2, 3, 4) and labels.shape == (2, 3) and scores.shape == (2, 3)

    def box(y, x, w, h, ox, oy):  # independent: centre (cell + offset) * stride, size * stride
        cx, cy = (x + ox) * 4, (y + oy) * 4
        return [cx - w * 4 / 2, cy - h * 4 / 2, w * 4, h * 4]

    torch.testing.assert_close(scores[0, :2], torch.tensor([0.9, 0.7]))
    assert labels[0, :2].tolist() == [0, 1]
    torch.testing.assert_close(boxes[0, 0], torch.tensor(box(2, 3, 5, 4, 0.25, 0.5)))
    torch.testing.assert_close(boxes[0, 1], torch.tensor(box(6, 8, 2, 3, 0.0, 0.75)))
    assert float(scores[0, 2]) == 0.0  # the suppressed neighbour is gone
    torch.testing.assert_close(scores[1, :2], torch.tensor([0.8, 0.05]))
    assert labels[1, :2].tolist() == [1, 0]
    torch.testing.assert_close(boxes[1, 0], torch.tensor(box(4, 4, 6, 2, 0.5, 0.5)))


def test_centernet_targets_round_trip_through_decoding():
    boxes = torch.tensor([[10.0, 12.0, 20.0, 16.0], [40.5, 3.0, 9.0, 30.0]])
    targets = [{"boxes": boxes, "labels": torch.tensor([1, 0])}, {"boxes": torch.zeros(0, 4), "labels": torch.zeros(0)}]
    heat, batch, index, wh, off, weight = centernet_targets(targets, num_classes=2, out_hw=(16, 20), stride=4)
    assert weight.tolist() == [1.0, 1.0]
    assert heat.shape == (2, 2, 16, 20) and float(heat[1].max()) == 0.0
    # exactly one 1.0 per box, at floor(centre / 4)
    assert int((heat == 1).sum()) == 2
    centres = (boxes[:, :2] + boxes[:, 2:] / 2) / 4
    for (cx, cy), lab in zip(centres.tolist(), [1, 0]):
        assert float(heat[0, lab, math.floor(cy), math.floor(cx)]) == 1.0
    assert batch.tolist() == [0, 0]
    torch.testing.assert_close(wh, boxes[:, 2:] / 4)
    torch.testing.assert_close(off, centres - torch.floor(centres))
    # the heatmap decays away from the centre and stays in [0, 1]
    assert float(heat.min()) >= 0.0 and float(heat[0, 1, 5, 4]) < 1.0
    # decoding the targets recovers the boxes exactly
    B, _, h, w = heat.shape
    wh_map, off_map = torch.zeros(B, 2, h * w), torch.zeros(B, 2, h * w)
    wh_map[batch, :, index] = wh
    off_map[batch, :, index] = off
    dboxes, dlabels, dscores = decode_centernet(heat, wh_map.view(B, 2, h, w), off_map.view(B, 2, h, w), 4, k=2)
    assert sorted(dlabels[0].tolist()) == [0, 1] and dscores[0].tolist() == [1.0, 1.0]
    got = {int(lab): b for lab, b in zip(dlabels[0], dboxes[0])}
    torch.testing.assert_close(got[1], boxes[0])
    torch.testing.assert_close(got[0], boxes[1])


def test_centernet_dense_targets_point_every_splat_cell_at_its_box():
    boxes = torch.tensor([[10.0, 12.0, 40.0, 36.0], [44.5, 3.0, 30.0, 50.0]])
    targets = [{"boxes": boxes, "labels": torch.tensor([1, 0])}]
    sparse = centernet_targets(targets, num_classes=2, out_hw=(16, 20), stride=4)
    dense = centernet_targets(targets, num_classes=2, out_hw=(16, 20), stride=4, dense=True)
    torch.testing.assert_close(dense.heatmap, sparse.heatmap)
    h, w = 16, 20
    centres = (boxes[:, :2] + boxes[:, 2:] / 2) / 4
    for j in range(2):
        # samples of box j: found by their size target (the two boxes differ)
        sel = (dense.wh == boxes[j, 2:] / 4).all(1)
        n = int(sel.sum())
        assert n > 4  # more than the centre cell
        torch.testing.assert_close(dense.weight[sel].sum(), torch.tensor(1.0))
        cells = torch.stack([dense.index[sel] % w, dense.index[sel] // w], 1).float()
        # cell + offset is the box centre for every sample
        torch.testing.assert_close(cells + dense.offset[sel], centres[j].expand(n, 2))
        # exactly the cells within the central 0.54 of the box (independent count)
        half = 0.54 * boxes[j, 2:] / 4 / 2
        c0 = torch.floor(centres[j])
        xs = torch.arange(w).float()
        ys = torch.arange(h).float()
        inside = ((ys[:, None] - c0[1]).abs() <= half[1]) & ((xs[None, :] - c0[0]).abs() <= half[0])
        assert n == int(inside.sum())
        # the centre cell is among them and weighs the most
        ci = int(math.floor(centres[j, 1]) * w + math.floor(centres[j, 0]))
        k = int(torch.nonzero(dense.index[sel] == ci)[0, 0])
        assert float(dense.weight[sel][k]) == float(dense.weight[sel].max())
    assert dense.batch.tolist() == [0] * len(dense.index)
    assert abs(float(dense.weight.sum()) - 2.0) < 1e-5


def test_gaussian_radius_keeps_the_iou():
    # IoU of the (h, w) box with its three displaced versions, computed from box corners
    def iou(a, b):
        ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
        iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
        inter = ix * iy
        area = lambda q: (q[2] - q[0]) * (q[3] - q[1])  # noqa: E731
        return inter / (area(a) + area(b) - inter)

    for h, w in [(10.0, 20.0), (40.0, 12.0), (5.0, 5.0), (3.0, 60.0)]:
        r = float(gaussian_radius(torch.tensor(h), torch.tensor(w), 0.7))
        box = (0.0, 0.0, w, h)
        ious = [iou(box, (r, r, w + r, h + r)), iou(box, (r, r, w - r, h - r)), iou(box, (-r, -r, w + r, h + r))]
        assert min(ious) == pytest.approx(0.7, abs=1e-4)  # the binding case sits exactly on the limit
        assert all(v >= 0.7 - 1e-4 for v in ious)


def test_giou_loss_of_hand_computed_boxes():
    # boxes as (centre offset, size) about the same cell; expected 1 - GIoU from their corners
    off = torch.tensor([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    wh = torch.tensor([[2.0, 2.0], [2.0, 2.0], [2.0, 2.0], [-1.0, 2.0]])
    off_gt = torch.tensor([[0.0, 0.0], [1.0, 0.0], [4.0, 0.0], [0.0, 0.0]])
    wh_gt = torch.full((4, 2), 2.0)
    # same box: 0; shifted by half: IoU 2/6, hull area 6 = union -> 2/3; disjoint: IoU 0, hull 12, union 8
    # -> 1 + 4/12; a negative width is an empty box: IoU 0, hull = union -> 1
    expect = [0.0, 2.0 / 3.0, 1.0 + 4.0 / 12.0, 1.0]
    assert giou_loss(off, wh, off_gt, wh_gt).tolist() == pytest.approx(expect, abs=1e-6)


def test_centernet_giou_term_trains_the_size_head():
    net = CenterNet(obj_ids=[1, 2], backbone="resnet18", input_size=None, dense_regression=True, giou_weight=2.0)
    # start from boxes of a few cells (at init the sizes are ~0: empty boxes inside the target give
    # the centre no GIoU gradient; the L1 terms handle that phase)
    torch.nn.init.constant_(net.wh_head[-1].bias, 4.0)
    images = torch.rand(2, 3, 64, 96)
    targets = [{"boxes": torch.tensor([[10.0, 12.0, 30.0, 20.0]]), "labels": torch.tensor([1])},
               {"boxes": torch.tensor([[40.0, 8.0, 24.0, 40.0]]), "labels": torch.tensor([0])}]
    losses = net.training_losses(images, targets)
    expect = (losses["loss_heatmap"] + net.wh_weight * losses["loss_wh"] + net.offset_weight * losses["loss_offset"]
              + 2.0 * losses["loss_giou"])
    assert float(losses["loss"].detach()) == pytest.approx(float(expect.detach()), rel=1e-6)
    assert 0.0 < float(losses["loss_giou"].detach()) <= 2.0
    net.zero_grad()
    losses["loss_giou"].backward()
    assert net.wh_head[-1].weight.grad.abs().sum() > 0 and net.offset_head[-1].weight.grad.abs().sum() > 0
    assert net.heat_head[-1].weight.grad is None or net.heat_head[-1].weight.grad.abs().sum() == 0
    no_giou = CenterNet(obj_ids=[1], input_size=None, giou_weight=0.0)
    assert "loss_giou" not in no_giou.training_losses(images, [targets[1]] * 2)


def test_focal_loss_matches_a_direct_formula():
    g = torch.Generator().manual_seed(0)
    logits = torch.randn(1, 2, 5, 6, generator=g)
    gt = torch.rand(1, 2, 5, 6, generator=g) * 0.9
    gt[0, 0, 2, 3] = 1.0
    gt[0, 1, 1, 1] = 1.0
    p = 1 / (1 + np.exp(-logits.double().numpy()))
    y = gt.double().numpy()
    pos = y == 1
    expect = (-(((1 - p) ** 2) * np.log(p))[pos].sum() - (((1 - y) ** 4) * (p**2) * np.log(1 - p))[~pos].sum()) / 2
    assert float(focal_loss(logits, gt)) == pytest.approx(expect, rel=1e-5)


def test_oracle_is_exact_and_filters():
    det = build_detector("oracle")
    targets = [
        {"boxes": [[10, 20, 30, 40], [1, 2, 3, 4]], "obj_ids": [5, 2], "scores": [0.5, 0.9]},
        {"boxes": np.zeros((0, 4)), "obj_ids": []},
    ]
    dets = det.predict(torch.rand(2, 3, 8, 8), targets)
    _check_detections(dets, 2, obj_ids=[2, 5])
    torch.testing.assert_close(dets[0].boxes, torch.tensor([[1.0, 2, 3, 4], [10, 20, 30, 40]]))
    assert dets[0].obj_ids.tolist() == [2, 5]
    torch.testing.assert_close(dets[0].scores, torch.tensor([0.9, 0.5]))
    assert len(dets[1]) == 0
    only5 = build_detector("oracle", obj_ids=[5]).predict(None, targets[:1])[0]
    assert only5.obj_ids.tolist() == [5]
    with pytest.raises(DetectionInputError, match="needs targets"):
        det.predict(torch.rand(1, 3, 8, 8))
    with pytest.raises(DetectionInputError, match="2 targets for 1 images"):
        det.predict(torch.rand(1, 3, 8, 8), targets)


def test_oracle_jitter_statistics_and_seed():
    n = 20000
    boxes = torch.tensor([[100.0, 50.0, 40.0, 80.0]]).repeat(n, 1)
    t = [{"boxes": boxes, "obj_ids": torch.ones(n, dtype=torch.long)}]
    det = build_detector("oracle", scale_sigma=0.1, shift_sigma=0.05, seed=3, max_detections=n)
    a = det.predict(None, t)[0].boxes.double()
    assert a.shape == (n, 4)
    det2 = build_detector("oracle", scale_sigma=0.1, shift_sigma=0.05, seed=3, max_detections=n)
    torch.testing.assert_close(det2.predict(None, t)[0].boxes.double(), a)  # same seed, same boxes
    det2.reset_seed(4)
    assert not torch.allclose(det2.predict(None, t)[0].boxes.double(), a)
    log_w, log_h = torch.log(a[:, 2] / 40), torch.log(a[:, 3] / 80)
    dcx = (a[:, 0] + a[:, 2] / 2 - 120) / 40
    dcy = (a[:, 1] + a[:, 3] / 2 - 90) / 80
    for v, sigma in [(log_w, 0.1), (log_h, 0.1), (dcx, 0.05), (dcy, 0.05)]:
        assert abs(float(v.mean())) < 4 * sigma / math.sqrt(n)
        assert float(v.std()) == pytest.approx(sigma, rel=0.03)
    assert abs(float(np.corrcoef(log_w.numpy(), dcx.numpy())[0, 1])) < 0.05  # independent coordinates


@pytest.mark.parametrize(
    ("images", "match"),
    [
        (torch.rand(1, 3, 0, 16), "empty"),
        (torch.rand(1, 4, 16, 16), "3 \\(RGB\\) channels"),
        (torch.rand(1, 16, 16, 3), "channels-last"),
        (torch.rand(3, 16, 16), "unsqueeze"),
        (torch.randint(0, 255, (1, 3, 16, 16), dtype=torch.uint8), "float\\(\\) / 255"),
        (torch.rand(1, 3, 16, 16) * 255, "divide by 255"),
        (np.zeros((1, 3, 16, 16), dtype=np.float32), "torch.Tensor"),
    ],
)
def test_bad_images_raise_clear_errors(images, match):
    det = build_detector("centernet", obj_ids=[1], backbone="resnet10t", input_size=None)
    with pytest.raises(DetectionInputError, match=match):
        det.predict(images)


def test_bad_configuration_errors():
    with pytest.raises(DetectionInputError, match="obj_ids is required"):
        build_detector("centernet")
    with pytest.raises(DetectionInputError, match="distinct"):
        build_detector("fcos", obj_ids=[1, 1])
    with pytest.raises(DetectionInputError, match="unknown backbone 'vgg'"):
        build_detector("faster_rcnn", obj_ids=[1], backbone="vgg")
    with pytest.raises(TypeError, match="accepts"):
        build_from_cfg(DETECTORS, {"name": "centernet", "obj_ids": [1], "bogus": 3})
    with pytest.raises(FileNotFoundError, match=r"no_such\.pth"):
        build_detector("centernet", obj_ids=[1], backbone_weights_path="/tmp/no_such.pth")


def test_checkpoint_round_trip_and_wrong_objects(tmp_path):
    torch.manual_seed(0)
    det = build_from_cfg(DETECTORS, {"name": "centernet", "obj_ids": OBJ_IDS, "backbone": "resnet10t",
                                     "input_size": [64, 48], "score_threshold": 0.0, "max_detections": 5})
    det.box_stats = {"mean": [0.0, 0.0, 0.0, 0.0]}
    path = save_detector(det, tmp_path / "det.pt")
    loaded = load_detector(path)
    assert loaded.obj_ids == OBJ_IDS and loaded.input_size == (64, 48) and not loaded.training
    assert loaded.box_stats == {"mean": [0.0, 0.0, 0.0, 0.0]}
    assert loaded.box_field == "bbox_visib"  # the default: a detector of visible boxes
    det.box_field = "bbox_obj"
    assert load_detector(save_detector(det, tmp_path / "amodal.pt")).box_field == "bbox_obj"
    x = torch.rand(2, 3, 48, 64)
    a, b = det.eval().predict(x), loaded.predict(x)
    for da, db in zip(a, b):
        torch.testing.assert_close(da.boxes, db.boxes)
        assert da.obj_ids.tolist() == db.obj_ids.tolist()
    assert load_detector(path, obj_ids=[7, 3], max_detections=2).max_detections == 2
    assert load_detector(path, score_threshold=0.3, max_detections=None).score_threshold == 0.3  # None: the checkpoint's
    with pytest.raises(DetectionInputError, match=r"cannot override \['input_size'\]; known: score_threshold"):
        load_detector(path, input_size=[32, 32])
    with pytest.raises(DetectionInputError, match=r"trained for obj_ids \[3, 7, 11\].*\[1, 2\]"):
        load_detector(path, obj_ids=[1, 2, 3])
    torch.save({"state_dict": {}}, tmp_path / "other.pt")
    with pytest.raises(DetectionInputError, match="not a kpd6d detector checkpoint"):
        load_detector(tmp_path / "other.pt")
    with pytest.raises(FileNotFoundError, match=r"missing\.pt"):
        load_detector(tmp_path / "missing.pt")


def test_merge_scales_keeps_the_best_of_overlapping_boxes_per_object():
    # image 0: object 0 found at both scales (IoU 0.81 -> one, the 0.9), object 1 on the same spot (kept: another
    # class), a second object-0 box elsewhere (kept); image 1: only padding at scale 2
    a = (torch.tensor([[[10.0, 10, 20, 20], [10, 10, 20, 20], [0, 0, 1, 1]], [[5, 5, 10, 10], [0, 0, 0, 0], [0, 0, 0, 0]]]),
         torch.tensor([[0, 1, 0], [2, 0, 0]]), torch.tensor([[0.6, 0.5, -1.0], [0.4, -1.0, -1.0]]))
    b = (torch.tensor([[[11.0, 11, 18, 18], [60, 60, 10, 10]], [[0, 0, 0, 0], [0, 0, 0, 0]]]),
         torch.tensor([[0, 0], [0, 0]]), torch.tensor([[0.9, 0.3], [-1.0, -1.0]]))
    boxes, labels, scores = merge_scales([a, b], iou=0.5)
    assert boxes.shape == (2, 5, 4) and labels.shape == scores.shape == (2, 5)
    assert scores[0, :3].tolist() == pytest.approx([0.9, 0.5, 0.3]) and (scores[0, 3:] == -1).all()
    assert labels[0, :3].tolist() == [0, 1, 0]
    assert boxes[0, 0].tolist() == [11, 11, 18, 18] and boxes[0, 2].tolist() == [60, 60, 10, 10]
    assert scores[1, 0] == pytest.approx(0.4) and labels[1, 0] == 2 and (scores[1, 1:] == -1).all()
    # below the IoU threshold both stay: IoU of the two object-0 boxes is 18^2 / 20^2 = 0.81
    assert (merge_scales([a, b], iou=0.85)[2][0] > 0).sum() == 4


def test_test_scales_run_the_network_at_each_size_and_merge(tmp_path, monkeypatch):
    torch.manual_seed(0)
    det = build_from_cfg(DETECTORS, {"name": "centernet", "obj_ids": OBJ_IDS, "backbone": "resnet10t",
                                     "input_size": [64, 48], "score_threshold": 0.0, "max_detections": 100}).eval()
    x = torch.rand(2, 3, 96, 128)
    single = {}
    for s in (1.0, 1.5):
        det.set_test_scales([s])
        single[s] = det.predict(x)
    seen = []
    raw = det.raw_predict
    monkeypatch.setattr(det, "raw_predict", lambda im: seen.append(tuple(im.shape[-2:])) or raw(im))
    det.set_test_scales([1, 1.5])
    both = det.predict(x)
    assert seen == [(48, 64), (72, 96)]
    from torchvision.ops import box_iou

    from kpd6d.detection.detections import xywh_to_xyxy

    for i, d in enumerate(both):
        # every merged box is one of the single-scale boxes (same score), and the best box of each scale
        # survives unless a same-object box of higher score overlaps it
        pool = torch.cat([single[1.0][i].boxes, single[1.5][i].boxes])
        pool_s = torch.cat([single[1.0][i].scores, single[1.5][i].scores])
        for box, score in zip(d.boxes, d.scores):
            j = torch.nonzero((pool == box).all(1)).flatten()
            assert len(j) and torch.isclose(pool_s[j], score).any()
        top = max((single[1.0][i], single[1.5][i]), key=lambda e: float(e.scores[0]))
        assert torch.equal(d.boxes[0], top.boxes[0]) and d.obj_ids[0] == top.obj_ids[0]
        iou = box_iou(xywh_to_xyxy(d.boxes), xywh_to_xyxy(d.boxes))
        same = (d.obj_ids[:, None] == d.obj_ids[None]) & ~torch.eye(len(d), dtype=torch.bool)
        assert not (iou[same] > det.SCALE_NMS_IOU).any()
    path = save_detector(det, tmp_path / "det.pt")
    assert load_detector(path).test_scales == (1.0,)  # an inference setting, not saved with the weights
    assert load_detector(path, test_scales=[1, 1.5]).test_scales == (1.0, 1.5)
    with pytest.raises(DetectionInputError, match=r"test_scales must hold positive numbers"):
        load_detector(path, test_scales=[-1])
    with pytest.raises(DetectionInputError, match=r"OracleDetector cannot run at other input sizes"):
        DETECTORS.build("oracle").set_test_scales([1, 2])
    DETECTORS.build("oracle").set_test_scales([1])


def test_checkpoint_records_every_constructor_parameter(tmp_path, monkeypatch):
    import inspect

    det = build_from_cfg(DETECTORS, {"name": "centernet", "obj_ids": OBJ_IDS, "backbone": "resnet10t",
                                     "input_size": [64, 48]})
    params = det.spec()["params"]
    signature = inspect.signature(CenterNet)
    assert set(params) == set(signature.parameters)
    assert params["neck_channels"] == signature.parameters["neck_channels"].default  # a default, recorded
    assert params["backbone"] == "resnet10t" and params["input_size"] == [64, 48]
    path = save_detector(det, tmp_path / "det.pt")
    # a later change of the class's defaults does not change what the checkpoint rebuilds
    names = [n for n in inspect.signature(CenterNet.__init__).parameters if n != "self"]
    defaults = list(CenterNet.__init__.__defaults__)
    assert len(defaults) == len(names)
    for n in ("neck_channels", "head_channels"):
        defaults[names.index(n)] = 16
    monkeypatch.setattr(CenterNet.__init__, "__defaults__", tuple(defaults))
    assert build_detector("centernet", obj_ids=OBJ_IDS, input_size=None).lateral[0].out_channels == 16
    assert build_detector("centernet", obj_ids=OBJ_IDS, input_size=None).spec()["params"]["neck_channels"] == 16
    loaded = load_detector(path)
    assert loaded.lateral[0].out_channels == params["neck_channels"] == det.lateral[0].out_channels != 16


def test_torchvision_checkpoint_round_trip(tmp_path):
    torch.manual_seed(0)
    det = build_detector("fcos", obj_ids=[1, 2], backbone="timm:resnet10t", input_size=[64, 64], score_threshold=0.0)
    loaded = load_detector(save_detector(det, tmp_path / "fcos.pt"))
    x = torch.rand(1, 3, 64, 64)
    torch.testing.assert_close(det.eval().predict(x)[0].scores, loaded.predict(x)[0].scores)


def test_postprocess_threshold_cap_one_per_object_and_id_mapping():
    det = build_detector("centernet", obj_ids=OBJ_IDS, backbone="resnet10t", score_threshold=0.2, max_detections=3)
    boxes = torch.arange(2 * 5 * 4, dtype=torch.float32).view(2, 5, 4)
    labels = torch.tensor([[2, 2, 0, 1, 0], [1, 0, 0, 2, 2]])
    scores = torch.tensor([[0.9, 0.8, 0.5, 0.3, 0.1], [0.6, 0.0, 0.0, 0.0, 0.0]])
    a, b = det.postprocess(boxes, labels, scores)
    assert a.obj_ids.tolist() == [11, 11, 3]  # class index -> obj id; capped at 3; 0.1 < threshold
    torch.testing.assert_close(a.boxes, boxes[0, :3])
    assert b.obj_ids.tolist() == [7] and b.scores.tolist() == [pytest.approx(0.6)]  # zero scores dropped
    det.one_per_object, det.max_detections = True, 10
    a, _ = det.postprocess(boxes, labels, scores)
    assert a.obj_ids.tolist() == [11, 3, 7]
    torch.testing.assert_close(a.boxes, boxes[0, [0, 2, 3]])


def test_centernet_loads_a_local_backbone_file_partially(tmp_path):
    """A local weights file loads into the backbone; entries of other shapes are skipped, and a file
    matching nothing is a clear error."""
    import torch

    from kpd6d.detection.detectors import build_detector

    src = build_detector("centernet", obj_ids=[1], backbone="resnet10t")
    state = {k: torch.full_like(v, 0.5) if v.is_floating_point() else v for k, v in src.backbone.state_dict().items()}
    state["not.a.parameter"] = torch.zeros(3)
    f = tmp_path / "bb.pth"
    torch.save(state, f)
    det = build_detector("centernet", obj_ids=[1], backbone="resnet10t", backbone_weights_path=str(f))
    loaded = det.backbone.state_dict()
    assert all(torch.equal(loaded[k], state[k]) for k in loaded)
    torch.save({"x": torch.zeros(2)}, tmp_path / "other.pth")
    with pytest.raises(Exception, match="matches none"):
        build_detector("centernet", obj_ids=[1], backbone="resnet10t", backbone_weights_path=str(tmp_path / "other.pth"))


def test_detection_evaluator_ap50_per_object():
    """Object 1 found exactly, object 2 only by a box that misses it (IoU < 0.5): AP@0.5 1 and 0."""
    from kpd6d.detection.metrics import DetectionEvaluator

    ev = DetectionEvaluator(per_object=True)
    gt = {"boxes": torch.tensor([[10.0, 10.0, 40.0, 30.0], [100.0, 80.0, 50.0, 50.0]]), "obj_ids": torch.tensor([1, 2])}
    det = Detections(boxes=torch.tensor([[10.0, 10.0, 40.0, 30.0], [130.0, 110.0, 50.0, 50.0]]),
                     scores=torch.tensor([0.9, 0.8]), obj_ids=torch.tensor([1, 2]))
    ev.update([det], [gt])
    res = ev.compute()
    assert res["ap50_per_object"] == {1: pytest.approx(1.0), 2: pytest.approx(0.0)}
    assert res["map_50"] == pytest.approx(0.5)
