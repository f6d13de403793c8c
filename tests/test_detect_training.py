"""Detector training: augmentation geometry/colour, the BOP detection dataset, box-error matching,
a tiny CenterNet overfit, and the Lightning stage (`kpd6d-train stage=detector`) end to end."""

from __future__ import annotations

import colorsys
import csv
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from kpd6d.detection import build_detector, load_detector
from kpd6d.detection.augment import adjust_hsv, random_scale_shift
from kpd6d.detection.box_stats import BoxErrorCollector, match_boxes
from kpd6d.detection.dataset import DetectionDataset, collate_detection

ROOT = Path(__file__).resolve().parents[1]
STEPS = 60  # 40 already suffice; margin for other platforms
COLOURS = {1: (230, 40, 40), 2: (40, 200, 60), 5: (50, 80, 230)}  # obj_id -> RGB


def _toy_image(rng, W, H, objects):
    """Noise background with a filled rectangle (obj 1), ellipse (obj 2) or triangle (obj 5) per entry
    (obj_id, x, y, w, h); returns the image and the tight pixel boxes (BOP convention)."""
    import cv2

    img = rng.integers(0, 120, (H, W, 3), dtype=np.uint8)
    boxes = []
    for oid, x, y, w, h in objects:
        c = COLOURS[oid]
        if oid == 1:
            cv2.rectangle(img, (x, y), (x + w, y + h), c, -1)
        elif oid == 2:
            cv2.ellipse(img, (x + w // 2, y + h // 2), (w // 2, h // 2), 0, 0, 360, c, -1)
        else:
            cv2.fillPoly(img, [np.array([[x, y + h], [x + w, y + h], [x + w // 2, y]], np.int32)], c)
        mask = np.all(img == np.array(c, np.uint8), axis=2)
        ys, xs = np.nonzero(mask)
        boxes.append([int(xs.min()), int(ys.min()), int(xs.max() - xs.min()), int(ys.max() - ys.min())])
    return img, boxes


def _write_toy_bop(root: Path, split: str, n: int, seed: int, W: int = 96, H: int = 64) -> Path:
    from kpd6d.data import (
        atomic_write_image,
        save_camera,
        save_scene_camera,
        save_scene_gt,
        save_scene_gt_info,
    )

    rng = np.random.default_rng(seed)
    K = np.array([[100.0, 0, W / 2], [0, 100.0, H / 2], [0, 0, 1]])
    sd = root / split / "000000"
    gt, cam, info = {}, {}, {}
    for i in range(n):
        objs = []
        for k, oid in enumerate(rng.permutation(list(COLOURS))[:2]):
            w, h = int(rng.integers(14, 26)), int(rng.integers(14, 22))
            x = int(rng.integers(2 + k * W // 2, W // 2 * (k + 1) - w - 2))
            objs.append((int(oid), x, int(rng.integers(2, H - h - 2)), w, h))
        img, boxes = _toy_image(rng, W, H, objs)
        atomic_write_image(sd / "rgb" / f"{i:06d}.png", img)
        gt[i] = [{"obj_id": o[0], "R": np.eye(3), "t": [0, 0, 500]} for o in objs]
        cam[i] = {"K": K}
        info[i] = [{"bbox_obj": [b[0] - 1, b[1] - 1, b[2] + 2, b[3] + 2], "bbox_visib": b, "px_count_visib": b[2] * b[3],
                    "px_count_all": b[2] * b[3], "visib_fract": 1.0} for b in boxes]
    if n > 1:  # a barely visible instance, to be filtered out by min_visib_fract
        info[1][0]["visib_fract"] = 0.05
    save_scene_gt(sd / "scene_gt.json", gt)
    save_scene_camera(sd / "scene_camera.json", cam)
    save_scene_gt_info(sd / "scene_gt_info.json", info)
    save_camera(root / "camera.json", K, W, H)
    return root


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def toy_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("toy_bop")
    _write_toy_bop(root, "train", 8, seed=0)
    _write_toy_bop(root, "val", 4, seed=1)
    return root


def test_adjust_hsv_matches_colorsys():
    g = torch.Generator().manual_seed(0)
    img = torch.rand(2, 3, 4, 5, generator=g)
    sat, val, hue = torch.tensor([1.3, 0.7]), torch.tensor([0.8, 1.4]), torch.tensor([0.1, -0.05])
    out = adjust_hsv(img, sat, val, hue)
    for b in range(2):
        for y in range(4):
            for x in range(5):
                h, s, v = colorsys.rgb_to_hsv(*img[b, :, y, x].tolist())
                r = colorsys.hsv_to_rgb((h + float(hue[b])) % 1.0, min(s * float(sat[b]), 1.0), min(v * float(val[b]), 1.0))
                np.testing.assert_allclose(out[b, :, y, x].numpy(), r, atol=2e-3)


def test_random_scale_shift_moves_boxes_with_the_pixels():
    H, W = 60, 80
    images = torch.zeros(6, 3, H, W)
    box = [20, 15, 24, 18]  # pixels x in [20, 44), y in [15, 33)
    images[:, :, 15:33, 20:44] = 1.0
    targets = [{"boxes": torch.tensor([[19.5, 14.5, 24.0, 18.0]]), "labels": torch.tensor([0]), "obj_ids": torch.tensor([4])}
               for _ in range(6)]  # pixel-edge box of the filled block (pixel centres at integers)
    out, new = random_scale_shift(images, targets, torch.Generator().manual_seed(1), scale=0.2, translate=0.1)
    moved = 0
    for b in range(6):
        m = out[b, 0] > 0.5
        ys, xs = torch.nonzero(m, as_tuple=True)
        assert len(new[b]["boxes"]) == 1 and new[b]["obj_ids"].tolist() == [4]
        x, y, w, h = new[b]["boxes"][0].tolist()
        # the thresholded block spans the transformed box (to within a pixel of resampling)
        assert abs(float(xs.min()) - 0.5 - x) <= 1.0 and abs(float(xs.max()) + 0.5 - (x + w)) <= 1.0
        assert abs(float(ys.min()) - 0.5 - y) <= 1.0 and abs(float(ys.max()) + 0.5 - (y + h)) <= 1.0
        moved += abs(x - (box[0] - 0.5)) > 1
    assert moved >= 3  # the augmentation does something
    # a box pushed out of the image is dropped
    t_out = [{"boxes": torch.tensor([[0.0, 0.0, 3.0, 3.0]]), "labels": torch.tensor([0])}]
    _, new = random_scale_shift(torch.zeros(1, 3, H, W), t_out, torch.Generator().manual_seed(0), scale=0.0, translate=0.3)
    assert len(new[0]["boxes"]) in (0, 1) and (len(new[0]["boxes"]) == 0 or float(new[0]["boxes"][0, 2]) >= 2)


def test_detection_dataset_reads_bop_boxes(toy_root):
    ds = DetectionDataset(toy_root, "train", input_size=[48, 32])
    assert ds.obj_ids == [1, 2, 5] and len(ds) == 8
    img, t = ds[0]
    assert img.shape == (3, 32, 48) and img.dtype == torch.float32 and 0 <= float(img.min()) <= float(img.max()) <= 1
    raw = json.loads((toy_root / "train" / "000000" / "scene_gt_info.json").read_text())["0"]
    gt_ids = [e["obj_id"] for e in json.loads((toy_root / "train" / "000000" / "scene_gt.json").read_text())["0"]]
    torch.testing.assert_close(t["orig_boxes"], torch.tensor([e["bbox_visib"] for e in raw], dtype=torch.float32))
    torch.testing.assert_close(t["boxes"], t["orig_boxes"] / 2)  # 96x64 -> 48x32
    assert t["obj_ids"].tolist() == gt_ids and t["labels"].tolist() == [ds.obj_ids.index(o) for o in gt_ids]
    assert len(ds[1][1]["boxes"]) == 1  # the visib_fract=0.05 instance is left out
    assert len(DetectionDataset(toy_root, "train", min_visib_fract=0.0)[1][1]["boxes"]) == 2
    full = DetectionDataset(toy_root, "train", box="bbox_obj", input_size=None)[0][1]["boxes"]
    torch.testing.assert_close(full, torch.tensor([e["bbox_obj"] for e in raw], dtype=torch.float32))
    images, targets = collate_detection([ds[0], ds[2]])
    assert images.shape == (2, 3, 32, 48) and len(targets) == 2
    with pytest.raises(ValueError, match="box must be one of"):
        DetectionDataset(toy_root, "train", box="bbox")
    with pytest.raises(FileNotFoundError, match="split 'nope' does not exist"):
        DetectionDataset(toy_root, "nope")


def test_detection_dataset_clips_full_boxes_to_the_image(tmp_path):
    root = _write_toy_bop(tmp_path / "bop", "train", 2, seed=3)
    info_path = root / "train" / "000000" / "scene_gt_info.json"
    info = json.loads(info_path.read_text())
    e0, e1 = info["0"]
    e0["bbox_obj"] = [-7, 5, 30, 20]  # 7 px past the left edge
    e1["bbox_obj"] = [80, -4, 30, 70]  # past the right (W 96), top and bottom (H 64) edges
    info_path.write_text(json.dumps(info))
    boxes = DetectionDataset(root, "train", box="bbox_obj", input_size=None)[0][1]["orig_boxes"]
    # by hand: x0 = max(x, 0), x1 = min(x + w, W), likewise in y
    torch.testing.assert_close(boxes, torch.tensor([[0.0, 5, 23, 20], [80.0, 0, 16, 64]]))
    half = DetectionDataset(root, "train", box="bbox_obj", input_size=[48, 32])[0][1]["boxes"]
    torch.testing.assert_close(half, boxes / 2)
    visib = DetectionDataset(root, "train", input_size=None)[0][1]["orig_boxes"]
    torch.testing.assert_close(visib, torch.tensor([e["bbox_visib"] for e in info["0"]], dtype=torch.float32))


def test_detection_dataset_train_crop_windows_and_clips_the_boxes(toy_root):
    full = DetectionDataset(toy_root, "train", input_size=None, min_visib_fract=0.0)
    ds = DetectionDataset(toy_root, "train", input_size=None, min_visib_fract=0.0, train_crop=[40, 30], min_kept=0.2)
    torch.manual_seed(0)
    origins = set()
    for i in range(len(ds)):
        img, t = ds[i]
        whole, tf = full[i]
        assert img.shape == (3, 30, 40)
        # where the window lies: the one position where it equals the whole image (found by search)
        hits = [(x, y) for y in range(whole.shape[1] - 29) for x in range(whole.shape[2] - 39)
                if torch.equal(whole[:, y:y + 30, x:x + 40], img)]
        assert len(hits) == 1
        x0, y0 = hits[0]
        origins.add((x0, y0))
        # the expected boxes: each whole-image box clipped to the window, kept when >= 2 px and >= 20 % of its area
        exp, ids = [], []
        for b, oid in zip(tf["boxes"].tolist(), tf["obj_ids"].tolist()):
            lo = (max(b[0] - x0, 0.0), max(b[1] - y0, 0.0))
            hi = (min(b[0] + b[2] - x0, 40.0), min(b[1] + b[3] - y0, 30.0))
            w, h = hi[0] - lo[0], hi[1] - lo[1]
            if w >= 2 and h >= 2 and w * h >= 0.2 * b[2] * b[3]:
                exp.append([lo[0], lo[1], w, h])
                ids.append(oid)
        assert len(exp) >= 1  # the window holds a box's centre, so that box keeps >= 1/4 of its area
        torch.testing.assert_close(t["boxes"], torch.tensor(exp, dtype=torch.float32).reshape(-1, 4))
        assert t["obj_ids"].tolist() == ids and t["labels"].tolist() == [ds.obj_ids.index(o) for o in ids]
        torch.testing.assert_close(t["orig_boxes"], t["boxes"] + torch.tensor([x0, y0, 0.0, 0.0]))
    assert len(origins) >= 4  # the windows move
    # a window larger than the image is the whole image; bad sizes are refused with the value
    img, t = DetectionDataset(toy_root, "train", input_size=[48, 32], train_crop=[64, 64])[0]
    assert img.shape == (3, 32, 48) and len(t["boxes"]) == 2
    for bad in ([0, 10], 64, [64, 48, 3], ["a", 4]):
        with pytest.raises(ValueError, match="train_crop must be"):
            DetectionDataset(toy_root, "train", train_crop=bad)
    with pytest.raises(ValueError, match="min_kept must be"):
        DetectionDataset(toy_root, "train", min_kept=1.5)


def test_match_boxes_and_box_error_stats():
    gt = torch.tensor([[10.0, 10, 20, 20], [50, 50, 10, 10], [80, 10, 10, 10]])
    gt_ids = torch.tensor([1, 2, 2])
    pred = torch.tensor([[51.0, 50, 10, 10], [12, 10, 20, 22], [10, 10, 20, 20], [80, 40, 10, 10]])
    pred_ids = torch.tensor([2, 1, 2, 2])
    p, g = match_boxes(pred, pred_ids, gt, gt_ids)
    assert p.tolist() == [0, 1] and g.tolist() == [1, 0]  # pred 2 has the wrong id, pred 3 no overlap
    col = BoxErrorCollector()
    col.add(pred, pred_ids, gt, gt_ids)
    stats = col.stats()
    assert stats["recall"] == pytest.approx(2 / 3)
    # offsets (dx/w, dy/h, log w'/w, log h'/h), computed by hand
    expect = np.array([[1 / 10, 0, 0, 0], [2 / 20, 1 / 20, 0, math.log(22 / 20)]])
    np.testing.assert_allclose(np.asarray(stats["offsets"]), expect, atol=1e-9)
    assert sorted(stats["per_object"]) == ["1", "2"]


def test_centernet_overfits_two_images():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    imgs, targets = [], []
    for objs in ([(1, 8, 10, 30, 24), (2, 60, 30, 26, 28)], [(5, 40, 6, 28, 30), (1, 70, 40, 20, 16)]):
        img, boxes = _toy_image(rng, 112, 80, objs)
        imgs.append(torch.from_numpy(img).permute(2, 0, 1).float() / 255)
        targets.append({"boxes": torch.tensor(boxes, dtype=torch.float32) + torch.tensor([-0.5, -0.5, 1, 1]),
                        "labels": torch.tensor([[1, 2, 5].index(o[0]) for o in objs]),
                        "obj_ids": torch.tensor([o[0] for o in objs])})
    images = torch.stack(imgs)
    det = build_detector("centernet", obj_ids=[1, 2, 5], backbone="resnet10t", neck_channels=32, head_channels=32,
                         input_size=None, score_threshold=0.3, one_per_object=True)
    opt = torch.optim.AdamW(det.parameters(), lr=3e-3)
    det.train()
    for _ in range(STEPS):
        loss = det.training_losses(images, targets)["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    from torchvision.ops import box_iou

    from kpd6d.detection.detections import xywh_to_xyxy

    for d, t in zip(det.predict(images), targets):
        assert len(d) == len(t["obj_ids"]), (d, t)
        for box, oid in zip(t["boxes"], t["obj_ids"].tolist()):
            hit = d.boxes[d.obj_ids == oid]
            assert len(hit) == 1
            assert float(box_iou(xywh_to_xyxy(hit), xywh_to_xyxy(box[None]))) > 0.5


def _read_csv_metrics(path: Path) -> list[dict]:
    with open(path) as f:
        return list(csv.DictReader(f))


@pytest.mark.slow
def test_train_cli_end_to_end_and_resume(toy_root, tmp_path):
    run = tmp_path / "run"
    args = [sys.executable, "-m", "kpd6d.cli.train", "stage=detector", "detector=centernet_tiny",
            f"data.root={toy_root}", f"hydra.run.dir={run}", "detector_recipe@stage=fast", "stage.trainer.max_epochs=2",
            "stage.num_threads=1", "stage.batch_size=4", "detector.input_size=[96,64]", "stage.augment.scale=0.1",
            "stage.ema_decay=0.9", "stage.train_crop=[64,48]",  # trains on 64x48 windows, validates on 96x64
            "stage.box=bbox_obj",  # an amodal detector: the checkpoint says so
            "stage.malloc.mmap_threshold_mb=32", "stage.malloc.trim_threshold_mb=1024"]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    res = subprocess.run(args, cwd=tmp_path, capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "stage: glibc malloc mmap_threshold 32 MiB, trim_threshold 1024 MiB" in res.stdout
    det = load_detector(run / "detector.pt", obj_ids=[1, 5])
    assert det.obj_ids == [1, 2, 5] and det.input_size == (96, 64)
    assert det.box_field == "bbox_obj"
    assert det.box_stats is None or "offsets" in det.box_stats
    from kpd6d.box_errors import load_box_error_stats

    if (run / "box_stats.json").is_file():  # only when some prediction matched after 2 epochs
        assert load_box_error_stats(run / "box_stats.json")["offsets"].shape[1] == 4
    rows = _read_csv_metrics(run / "csv" / "metrics.csv")
    assert any(r.get("val/map_50") not in (None, "") for r in rows)
    assert any(r.get("train/loss_epoch") not in (None, "") for r in rows)
    assert list((run / "tb").rglob("events.out.tfevents*"))
    summary = json.loads((run / "metrics.json").read_text())
    assert summary["epochs"] == 2 and 0.0 <= summary["map_50"] <= 1.0
    # weight averaging: the checkpoint carries its state; the exported detector is the average
    assert torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)["callbacks"]["WeightEMA"]["num_updates"] > 0
    # the Lightning checkpoint loads as a detector too, without the config
    ckpt = load_detector(run / "checkpoints" / "last.ckpt")
    x = torch.rand(1, 3, 64, 96)
    torch.testing.assert_close(ckpt.predict(x)[0].scores, det.predict(x)[0].scores)
    assert ckpt.box_field == "bbox_obj"
    # rerunning in the same folder resumes from last.ckpt and trains only the missing epoch
    args3 = [a if a != "stage.trainer.max_epochs=2" else "stage.trainer.max_epochs=3" for a in args]
    res = subprocess.run(args3,
                         cwd=tmp_path, capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "Restoring states from the checkpoint" in res.stderr + res.stdout
    bad = {"stage.train_crop=[64,48]": "stage.train_crop=[0,48]", f"hydra.run.dir={run}": f"hydra.run.dir={tmp_path / 'bad'}"}
    res = subprocess.run([bad.get(a, a) for a in args], cwd=tmp_path, capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode != 0 and "train_crop must be (width, height) > 0, got [0, 48]" in res.stderr + res.stdout
    assert json.loads((run / "metrics.json").read_text())["epochs"] == 3


def test_module_rejects_bad_settings():
    from kpd6d.detection.module import DetectorModule

    cfg = {"name": "centernet", "obj_ids": [1], "backbone": "resnet10t"}
    with pytest.raises(ValueError, match="unknown optimizer setting"):
        DetectorModule(cfg, optimizer={"learning_rate": 1})
    with pytest.raises(ValueError, match="unknown augment setting"):
        DetectorModule(cfg, augment={"flip": 0.5})
    with pytest.raises(ValueError, match=r"augment.photometric: unknown photometric setting\(s\) \['sharpness'\]"):
        DetectorModule(cfg, augment={"photometric": {"sharpness": 2.0}})
    m = DetectorModule(cfg, augment={"photometric": {"contrast": 1.4}})
    assert m.aug_cfg["photometric"]["contrast"] == 1.4 and m.aug_cfg["photometric"]["blur_p"] == 0.0
    with pytest.raises(ValueError, match="not trainable"):
        DetectorModule({"name": "oracle"})


def test_prepare_data_generates_a_procedural_dataset_when_root_is_null(tmp_path):
    from omegaconf import OmegaConf

    from kpd6d.synth import prepare_data

    cfg = OmegaConf.create({
        "data": {"root": None, "train_split": "train", "val_split": "val"},
        "generate": {"obj_ids": [1, 2, 3], "num_train": 2, "num_val": 1, "seed": 1, "workers": 1,
                     "options": {"width": 64, "height": 48, "objects_per_image": [2, 3], "designator": None}},
    })
    root = prepare_data(cfg.data.root, tmp_path, cfg.generate, [cfg.data.train_split, cfg.data.val_split])
    assert root == tmp_path / "data"
    train = DetectionDataset(root, "train", input_size=None, min_visib_fract=0.0)
    val = DetectionDataset(root, "val", input_size=None, min_visib_fract=0.0)
    assert len(train) == 2 and len(val) == 1
    assert set(train.obj_ids) <= {1, 2, 3}
    img, t = train[0]
    assert img.shape == (3, 48, 64) and len(t["obj_ids"]) >= 1
    cfg.data.root = str(tmp_path / "missing")
    with pytest.raises(FileNotFoundError, match="missing"):
        prepare_data(cfg.data.root, tmp_path, cfg.generate, [cfg.data.train_split, cfg.data.val_split])
