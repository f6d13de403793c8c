"""kpd6d-predict: intrinsics files, image / folder / video inputs, outputs; CLI with real tiny checkpoints."""

from __future__ import annotations

import json
import sys

import cv2
import numpy as np
import pytest

from kpd6d.evaluation.results_io import read_bop_results
from kpd6d.geometry import LINEMOD_K, pose_from_view, project_points
from kpd6d.predict import load_intrinsics, predict_inputs

K = np.array([[500.0, 0, 80], [0, 500.0, 60], [0, 0, 1]])
CORNERS = {1: np.array([[x, y, z] for z in (-20, 20) for y in (-20, 20) for x in (-20, 20)], float)}


def test_load_intrinsics_formats(tmp_path):
    assert np.array_equal(load_intrinsics(None), LINEMOD_K)
    (tmp_path / "camera.json").write_text(json.dumps({"fx": 500, "fy": 501, "cx": 80, "cy": 60, "width": 160}))
    np.testing.assert_array_equal(load_intrinsics(tmp_path / "camera.json"), [[500, 0, 80], [0, 501, 60], [0, 0, 1]])
    (tmp_path / "k.json").write_text(json.dumps(K.tolist()))
    np.testing.assert_array_equal(load_intrinsics(tmp_path / "k.json"), K)
    (tmp_path / "k2.json").write_text(json.dumps({"cam_K": K.reshape(-1).tolist()}))
    np.testing.assert_array_equal(load_intrinsics(tmp_path / "k2.json"), K)
    (tmp_path / "k.txt").write_text("500 0 80\n0 500 60\n0 0 1\n")
    np.testing.assert_array_equal(load_intrinsics(tmp_path / "k.txt"), K)
    (tmp_path / "bad.txt").write_text("1 2 3")
    with pytest.raises(ValueError, match=r"bad\.txt: expected 9 finite numbers"):
        load_intrinsics(tmp_path / "bad.txt")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_intrinsics(tmp_path / "nope.json")


class FixedPosePipeline:
    """One object 1 at a fixed pose in every image (what a perfect pipeline would return)."""

    def __init__(self):
        self.R, self.t = pose_from_view(0.5, 0.6, 400.0)
        self.seen = []

    def predict_batch(self, images, K_):
        self.seen.append(len(images))
        uv = project_points(CORNERS[1], K_, self.R, self.t)
        p = {"obj_id": 1, "R": self.R, "t": self.t, "score": 0.9, "ok": True, "keypoints_2d": uv,
             "confidences": np.ones(8), "used": np.ones(8, bool), "box": np.r_[uv.min(0), uv.max(0) - uv.min(0)]}
        return [[p] for _ in images]


def _blue_pixels(rgb):
    return int((np.abs(rgb.astype(int) - [30, 90, 255]).sum(-1) < 80).sum())


def test_image_and_folder_inputs(tmp_path):
    img = np.full((120, 160, 3), 50, np.uint8)
    folder = tmp_path / "imgs"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"im{i}.png"), img)
    (folder / "notes.txt").write_text("not an image")
    pipe = FixedPosePipeline()
    info = predict_inputs(pipe, folder, K, tmp_path / "out", CORNERS, batch_size=2, progress=False)
    assert info == {"frames": 3, "poses": 3, "out_dir": str(tmp_path / "out"), "errors": []}
    assert pipe.seen == [2, 1]
    data = json.loads((tmp_path / "out" / "poses.json").read_text())
    assert [f["name"] for f in data["frames"]] == ["im0.png", "im1.png", "im2.png"]
    np.testing.assert_allclose(data["frames"][1]["poses"][0]["t"], pipe.t)
    res = read_bop_results(tmp_path / "out" / "poses.csv")
    assert [r.im_id for r in res] == [0, 1, 2] and np.allclose(res[0].R, pipe.R)
    ov = cv2.cvtColor(cv2.imread(str(tmp_path / "out" / "overlays" / "im0.png")), cv2.COLOR_BGR2RGB)
    assert _blue_pixels(ov) > 50  # the projected box is drawn
    single = predict_inputs(FixedPosePipeline(), folder / "im1.png", K, tmp_path / "one", CORNERS, progress=False)
    assert single["frames"] == 1 and (tmp_path / "one" / "overlays" / "im1.png").is_file()
    with pytest.raises(FileNotFoundError, match="does not exist"):
        predict_inputs(FixedPosePipeline(), tmp_path / "missing.png", K, tmp_path / "x", CORNERS, progress=False)


def test_a_bad_image_in_a_folder_is_recorded_and_the_others_are_still_predicted(tmp_path):
    img = np.full((120, 160, 3), 50, np.uint8)
    folder = tmp_path / "imgs"
    folder.mkdir()
    for i in (0, 2, 3):
        cv2.imwrite(str(folder / f"im{i}.png"), img)
    (folder / "im1.png").write_bytes(b"not a png")
    before = (folder / "im1.png").read_bytes()
    info = predict_inputs(FixedPosePipeline(), folder, K, tmp_path / "out", CORNERS, batch_size=2, progress=False)
    assert info["frames"] == 3 and info["poses"] == 3
    assert [(e["index"], e["name"]) for e in info["errors"]] == [(1, "im1.png")]
    assert "cannot be read as an image" in info["errors"][0]["error"]
    data = json.loads((tmp_path / "out" / "poses.json").read_text())
    assert [f["name"] for f in data["frames"]] == ["im0.png", "im2.png", "im3.png"] and data["errors"] == info["errors"]
    assert [r.im_id for r in read_bop_results(tmp_path / "out" / "poses.csv")] == [0, 2, 3]
    assert (folder / "im1.png").read_bytes() == before  # inputs untouched
    # stop_on_error: stops at the bad image, and what was computed before it is written
    with pytest.raises(ValueError, match=r"im1\.png: cannot be read as an image"):
        predict_inputs(FixedPosePipeline(), folder, K, tmp_path / "stop", CORNERS, batch_size=1, progress=False,
                       stop_on_error=True)
    assert [f["name"] for f in json.loads((tmp_path / "stop" / "poses.json").read_text())["frames"]] == ["im0.png"]


def test_video_in_video_out(tmp_path):
    path = tmp_path / "clip.mp4"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (160, 120))
    assert w.isOpened()
    for i in range(5):
        w.write(np.full((120, 160, 3), 20 * i, np.uint8))
    w.release()
    info = predict_inputs(FixedPosePipeline(), path, K, tmp_path / "out", CORNERS, batch_size=2, progress=False)
    assert info["frames"] == 5 and info["poses"] == 5
    cap = cv2.VideoCapture(str(tmp_path / "out" / "overlay.mp4"))
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(f, cv2.COLOR_BGR2RGB))
    assert len(frames) == 5 and frames[0].shape == (120, 160, 3)
    assert _blue_pixels(frames[2]) > 30  # lossy codec: a looser colour match
    assert not list((tmp_path / "out").glob(".overlay.*"))
    names = [f["name"] for f in json.loads((tmp_path / "out" / "poses.json").read_text())["frames"]]
    assert names == [f"frame_{i:06d}" for i in range(5)]


def test_cli_with_real_untrained_checkpoints(tmp_path, monkeypatch, capsys):
    import pytorch_lightning as pl
    import torch

    from kpd6d.cli.predict import main
    from kpd6d.detection import build_detector, save_detector
    from kpd6d.kpd.module import KPDModule

    torch.manual_seed(0)
    det = build_detector("centernet", obj_ids=[1], backbone="resnet10t", neck_channels=16, head_channels=16,
                         input_size=[128, 96], score_threshold=0.0, max_detections=3)
    save_detector(det, tmp_path / "det.pt")
    kpd = KPDModule(obj_ids=[1], keypoints_3d=[CORNERS[1]], diameters=[69.3], backbone={"name": "resnet18"},
                    head={"name": "deconv", "deconv_channels": 16}, input_size=64, out_stride=4)
    trainer = pl.Trainer(accelerator="cpu", logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, default_root_dir=tmp_path)
    trainer.strategy.connect(kpd)
    trainer.save_checkpoint(tmp_path / "kpd.ckpt")
    cv2.imwrite(str(tmp_path / "in.png"), np.random.default_rng(0).integers(0, 255, (120, 160, 3), dtype=np.uint8))
    (tmp_path / "k.json").write_text(json.dumps(K.tolist()))
    out = tmp_path / "run"
    monkeypatch.setattr(sys, "argv", ["kpd6d-predict", f"input={tmp_path / 'in.png'}", f"kpd_ckpt={tmp_path / 'kpd.ckpt'}",
                                      f"detector_ckpt={tmp_path / 'det.pt'}", f"camera={tmp_path / 'k.json'}",
                                      "device=cpu", "progress=false", "select.top_l=null", f"hydra.run.dir={out}"])
    main()
    data = json.loads((out / "poses.json").read_text())
    assert len(data["frames"]) == 1 and len(data["frames"][0]["poses"]) == 3  # max_detections boxes, each estimated
    np.testing.assert_array_equal(data["K"], K)
    assert (out / "poses.csv").is_file() and (out / "overlays" / "in.png").is_file()
    assert "poses in 1 frame(s)" in capsys.readouterr().out
    # detector_overrides: the checkpoint's max_detections (3) replaced for this run
    monkeypatch.setattr(sys, "argv", [*sys.argv[:-1], "detector_overrides.max_detections=1",
                                      f"hydra.run.dir={tmp_path / 'run1'}"])
    main()
    assert len(json.loads((tmp_path / "run1" / "poses.json").read_text())["frames"][0]["poses"]) == 1
    # the region refiner needs meshes: without refiner.models_dir a clear error before any image is read
    monkeypatch.setattr(sys, "argv", [*sys.argv[:-1], "refiner=region", f"hydra.run.dir={tmp_path / 'run2'}"])
    with pytest.raises(SystemExit):
        main()
    assert "refiner.models_dir is required" in capsys.readouterr().err
    assert not (tmp_path / "run2" / "poses.json").exists()
