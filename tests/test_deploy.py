"""ONNX export and the torch-free runtime (kpd6d.deploy): ONNX Runtime and OpenVINO match torch.

Tolerances (docs/deployment.md): network outputs (KPD heatmaps scaled to O(1), detector heatmap
probabilities / sizes / offsets) within 1e-4 abs on the same input; the numpy crops within 1e-4 of
kornia's; end to end, confidences (heatmap maxima) within 1e-3, decoded
keypoints within 0.05 px; detector boxes within 0.01 px; poses within 0.1 mm and 0.01 deg.

Tiny random networks whose last layers are rescaled so that their outputs have O(1) structure (a
random-init network's heatmaps are ~1e-6 flat noise, which would make any decoder comparison
meaningless). These tests need onnx, onnxruntime and openvino (``pip install kpd6d[deploy]``;
in the dev extra): a missing package fails, never skips.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from kpd6d.geometry import LINEMOD_K, rotation_error_deg

BACKENDS = ("onnxruntime", "openvino")
K_PTS = 8

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _require(name: str):
    try:
        return __import__(name)
    except ImportError:
        pytest.fail(f"{name} is not installed: pip install kpd6d[deploy] (the dev extra includes it)")


def _rescale_last(conv: torch.nn.Conv2d, out: torch.Tensor, target: float = 1.0, bias=None) -> None:
    with torch.no_grad():
        conv.weight.mul_(target / out.abs().max().clamp(min=1e-30))
        if bias is not None:
            conv.bias.copy_(torch.as_tensor(bias, dtype=conv.bias.dtype))


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    for name in ("onnx", "onnxruntime", "openvino"):
        _require(name)
    from kpd6d.deploy.export import export_models
    from kpd6d.detection import build_detector, save_detector
    from kpd6d.kpd.module import KPDModule

    torch.set_num_threads(1)
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    kpd = KPDModule(obj_ids=[3, 7], keypoints_3d=[rng.uniform(-40, 40, (K_PTS, 3)) for _ in range(2)],
                    diameters=[120.0, 90.0], model_points=[rng.uniform(-40, 40, (60, 3)) for _ in range(2)],
                    backbone={"name": "tiny", "width": 8}, head={"name": "deconv", "deconv_channels": 16},
                    codec={"input_size": 64, "out_stride": 4, "sigma": 1.5, "crop_scale": 1.5,
                           "decoder": {"name": "subpixel", "method": "dark"}}).eval()
    with torch.no_grad():
        _rescale_last(kpd.net.head.final, kpd.net(torch.rand(4, 3, 64, 64)))
    det = build_detector("centernet", obj_ids=[3, 7], backbone="resnet10t", neck_channels=8, head_channels=8,
                         input_size=[96, 72], score_threshold=0.05, max_detections=4).eval()
    with torch.no_grad():
        out = det(torch.rand(1, 3, 72, 96))
        _rescale_last(det.heat_head[-1], out["heatmap"] + 2.19, 3.0)
        _rescale_last(det.wh_head[-1], out["wh"], 2.0, bias=[12.0, 10.0])
        _rescale_last(det.offset_head[-1], out["offset"], 0.4, bias=[0.5, 0.5])
    d = tmp_path_factory.mktemp("deploy")
    torch.save({"hyper_parameters": dict(kpd.hparams), "state_dict": kpd.state_dict()}, d / "kpd.ckpt")
    save_detector(det, d / "det.pt")
    export_models(d / "kpd.ckpt", d / "det.pt", d / "export", opset=17)
    return {"kpd": kpd, "det": det, "dir": d, "export": d / "export"}


def _image(seed=0, size=(160, 120)):
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8)
    return np.ascontiguousarray(np.repeat(np.repeat(img[::4, ::4], 4, 0), 4, 1)[: size[1], : size[0]])


def test_export_writes_graphs_and_a_sidecar(models):
    side = json.loads((models["export"] / "kpd6d_export.json").read_text())
    assert (models["export"] / "kpd.onnx").is_file() and (models["export"] / "detector.onnx").is_file()
    assert side["format"] == "kpd6d_export" and side["opset"] == 17
    k = side["kpd"]
    assert k["obj_ids"] == [3, 7] and np.asarray(k["keypoints_3d"]).shape == (2, K_PTS, 3)
    np.testing.assert_allclose(k["keypoints_3d"][1], models["kpd"].keypoints_3d[7])
    assert k["codec"] == models["kpd"].codec.config() and k["num_groups"] == 2
    assert k["normalization"]["in_graph"] and len(k["normalization"]["mean"]) == 3
    dn = side["detector"]
    assert dn["name"] == "centernet" and dn["input_size"] == [96, 72] and dn["obj_ids"] == [3, 7]
    assert dn["max_detections"] == 4 and dn["score_threshold"] == pytest.approx(0.05)
    assert {"kpd6d", "torch", "onnx"} <= set(side["versions"])


@pytest.mark.parametrize("backend", BACKENDS)
def test_kpd_heatmaps_match_torch_over_a_dynamic_batch(models, backend):
    from kpd6d.deploy.runtime import Session

    sess = Session(models["export"] / "kpd.onnx", backend)
    for n in (1, 5):
        x = torch.rand(n, 3, 64, 64, generator=torch.Generator().manual_seed(n))
        with torch.no_grad():
            ref = models["kpd"].net(x).numpy()
        got = sess(x.numpy())[0]
        assert got.shape == ref.shape == (n, 2 * K_PTS, 16, 16)
        assert np.abs(ref).max() > 0.1  # O(1) maps, not flat noise
        np.testing.assert_allclose(got, ref, atol=1e-4, rtol=0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_detector_outputs_and_boxes_match_torch(models, backend):
    from kpd6d.deploy.runtime import RuntimeDetector, Session, read_sidecar
    from kpd6d.pipeline import images_to_tensor

    det = models["det"]
    x = torch.rand(2, 3, 72, 96, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        ref = det(x)
    got = Session(models["export"] / "detector.onnx", backend)(x.numpy())
    np.testing.assert_allclose(got[0], torch.sigmoid(ref["heatmap"]).numpy(), atol=1e-4, rtol=0)
    np.testing.assert_allclose(got[1], ref["wh"].numpy(), atol=1e-4, rtol=0)
    np.testing.assert_allclose(got[2], ref["offset"].numpy(), atol=1e-4, rtol=0)
    # whole detector: resize (160x120 -> 96x72, antialiased) + decoding + post-processing
    images = [_image(2), _image(3)]
    rdet = RuntimeDetector(models["export"], read_sidecar(models["export"])["detector"], backend)
    want = det.predict(images_to_tensor(images))
    have = rdet.predict(np.stack(images).astype(np.float32) / np.float32(255))
    assert sum(len(d) for d in want) >= 4
    for w, h in zip(want, have):
        np.testing.assert_array_equal(h.obj_ids, w.obj_ids.numpy())
        np.testing.assert_allclose(h.scores, w.scores.numpy(), atol=1e-4)
        np.testing.assert_allclose(h.boxes, w.boxes.numpy(), atol=0.01)
    with pytest.raises(ValueError, match=r"runs at one input size .* test_scales \[1, 1.5\] needs the PyTorch checkpoint"):
        RuntimeDetector(models["export"], read_sidecar(models["export"])["detector"], backend, test_scales=[1, 1.5])


def test_numpy_ops_match_torch():
    """The runtime's crops, resize and decoders against kornia / torch on the same inputs."""
    from kpd6d.deploy.ops import resize_bilinear_antialias, warp_affine_bilinear
    from kpd6d.kpd.codec import HeatmapCodec
    from kpd6d.kpd.crops import inference_crops
    from kpd6d.kpd.decoders_numpy import build_numpy_decoder
    from kpd6d.registry import DECODERS, build_from_cfg

    g = torch.Generator().manual_seed(0)
    img = torch.rand(1, 3, 50, 70, generator=g)
    for size in ((35, 25), (48, 31), (100, 80)):
        ref = torch.nn.functional.interpolate(img, size=size[::-1], mode="bilinear", align_corners=False,
                                              antialias=True).numpy()
        np.testing.assert_allclose(resize_bilinear_antialias(img.numpy(), size), ref, atol=1e-5)
    codec = HeatmapCodec(input_size=32, out_stride=4, crop_scale=1.3)
    boxes = np.array([[10.0, 5.0, 30.0, 20.0], [-8.0, 30.0, 25.0, 40.0], [40.2, 11.7, 13.3, 9.1]])
    crops, _ = inference_crops(img, torch.as_tensor(boxes), torch.zeros(3, dtype=torch.long), codec)
    mine = warp_affine_bilinear(img[0].permute(1, 2, 0).numpy(), codec.crop_affine(boxes), 32)
    np.testing.assert_allclose(mine, crops.numpy(), atol=1e-4)
    # the separable path (scale + shift, the codec's crops) and the general one (here: a rotation)
    # against kornia, on boxes inside, across and beyond the image's edges, at several sizes
    import kornia

    rng = np.random.default_rng(3)
    for size in (32, (24, 40)):
        for _ in range(8):
            box = np.array([[*rng.uniform(-40, 80, 2), *rng.uniform(3, 60, 2)]])
            for angle in (0.0, 0.3):
                A = codec.crop_affine(box)
                if angle:
                    R = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0],
                                  [0.0, 0.0, 1.0]])
                    A = (R @ np.vstack([A[0], [0.0, 0.0, 1.0]]))[None, :2]
                hw = (size, size) if isinstance(size, int) else size[::-1]
                ref = kornia.geometry.transform.warp_affine(img, torch.as_tensor(A, dtype=torch.float32), hw,
                                                            align_corners=True)
                np.testing.assert_allclose(warp_affine_bilinear(img[0].permute(1, 2, 0).numpy(), A, size),
                                           ref.numpy(), atol=1e-4, err_msg=f"{box} {angle} {size}")
    # peaked maps with noise: each decoder agrees with its torch twin within 0.01 heatmap px
    yy, xx = torch.meshgrid(torch.arange(16.0), torch.arange(16.0), indexing="ij")
    c = torch.rand(3, 4, 2, generator=g) * 12 + 2
    hm = torch.exp(-((xx - c[..., 0, None, None]) ** 2 + (yy - c[..., 1, None, None]) ** 2) / 2.25)
    hm = hm + 0.02 * torch.rand(hm.shape, generator=g)
    for cfg in ({"name": "argmax"}, {"name": "soft_argmax"}, {"name": "soft_argmax", "window": None},
                {"name": "subpixel", "method": "taylor"}, {"name": "subpixel", "method": "dark"},
                {"name": "subpixel", "method": "quadratic"}):
        xy_t, conf_t = build_from_cfg(DECODERS, dict(cfg))(hm)
        xy_n, conf_n = build_numpy_decoder(cfg)(hm.numpy())
        np.testing.assert_allclose(xy_n, xy_t.numpy(), atol=0.01, err_msg=str(cfg))
        np.testing.assert_allclose(conf_n, conf_t.numpy(), atol=1e-6, err_msg=str(cfg))
    with pytest.raises(ValueError, match="no numpy implementation"):
        build_numpy_decoder({"name": "nonsense"})


def _compare_poses(want, have):
    n_ok = 0
    assert [len(w) for w in want] == [len(h) for h in have]
    for ws, hs in zip(want, have):
        for w, h in zip(ws, hs):
            assert h["obj_id"] == w["obj_id"]
            np.testing.assert_allclose(h["box"], w["box"], atol=0.01)
            np.testing.assert_allclose(h["keypoints_2d"], w["keypoints_2d"], atol=0.05)
            np.testing.assert_allclose(h["confidences"], w["confidences"], atol=1e-3)  # crops differ by float32 rounding
            assert h["ok"] == w["ok"]
            assert h["confidence"] == pytest.approx(w["confidence"], abs=1e-3)
            if w["ok"]:
                n_ok += 1
                assert np.abs(h["t"] - w["t"]).max() < 0.1
                assert rotation_error_deg(h["R"], w["R"]) < 0.01
    return n_ok


def _targets():
    return [{"boxes": np.array([[20.0, 15.0, 60.0, 50.0], [70.0, 40.0, 45.0, 55.0]]), "obj_ids": np.array([3, 7])},
            {"boxes": np.array([[30.0, 30.0, 80.0, 70.0]]), "obj_ids": np.array([7])}]


@pytest.mark.parametrize("backend", BACKENDS)
def test_pipeline_from_export_matches_torch_end_to_end(models, backend):
    from kpd6d.pipeline import PosePipeline
    from kpd6d.registry import DETECTORS

    images = [_image(4), _image(5)]
    K = LINEMOD_K * [[0.25], [0.25], [1.0]]
    # the untrained tiny KPD gives poor poses: the PnP validity gate is off so that poses get compared
    kw = {"pnp": {"name": "epnp", "max_relative_residual": None}, "top_l": 6}
    # oracle boxes: the KPD, decoding, top-l and PnP stages (and box refinement)
    torch_pipe = PosePipeline(DETECTORS.build("oracle"), models["kpd"], device="cpu", refine_boxes=1, **kw)
    rt = PosePipeline.from_export(models["export"], backend=backend, detector="oracle", refine_boxes=1, **kw)
    assert rt.backend == backend and rt.refine_boxes == 1
    want, have = torch_pipe.predict_batch(images, K, _targets()), rt.predict_batch(images, K, _targets())
    assert _compare_poses(want, have) >= 1
    # KPD + PnP on given boxes (what tracking runs): the same poses as the oracle's boxes gave
    boxes = [(b, box, oid) for b, tg in enumerate(_targets()) for box, oid in zip(tg["boxes"], tg["obj_ids"])]
    args = ([B[1] for B in boxes], [B[2] for B in boxes], [B[0] for B in boxes])
    assert _compare_poses(want, rt.predict_boxes(images, K, *args)) >= 1
    assert _compare_poses(want, torch_pipe.predict_boxes(images, K, *args)) >= 1
    # crops on grown boxes (box_scale) with 3 test-time crops each (crop_tta), refined on depth-calibrated
    # poses: the same in both
    grown = [PosePipeline(DETECTORS.build("oracle"), models["kpd"], device="cpu", refine_boxes=1, box_scale=1.2,
                          depth_calibration={"default": 0.9}, crop_tta=3, **kw),
             PosePipeline.from_export(models["export"], backend=backend, detector="oracle", refine_boxes=1,
                                      box_scale=1.2, depth_calibration={"default": 0.9}, crop_tta=3, **kw)]
    assert grown[1].box_scale == 1.2 and grown[1].crop_tta == 3
    # the exported runtime takes the depth calibration through the shared core
    assert grown[1].depth_calibration_default == 0.9 and grown[1].depth_factors([1, 2]).tolist() == [0.9, 0.9]
    # (keypoints, confidences and boxes: the poses of this untrained KPD are so ill-conditioned that
    # keypoints equal within 1e-3 px give rotations 0.02 deg apart)
    g_want, g_have = (g.predict_batch(images, K, _targets()) for g in grown)
    for ws, hs in zip(g_want, g_have):
        for w, h in zip(ws, hs):
            np.testing.assert_allclose(h["box"], w["box"], atol=0.01)
            np.testing.assert_allclose(h["keypoints_2d"], w["keypoints_2d"], atol=0.05)
            np.testing.assert_allclose(h["confidences"], w["confidences"], atol=1e-3)
    # and they differ from the crops on the boxes as given
    assert not np.allclose(g_want[0][0]["keypoints_2d"], want[0][0]["keypoints_2d"], atol=0.05)
    # the exported detector, end to end
    torch_pipe = PosePipeline(models["det"], models["kpd"], device="cpu", **kw)
    rt = PosePipeline.from_export(models["export"], backend=backend, **kw)
    want, have = torch_pipe.predict_batch(images, K), rt.predict_batch(images, K)
    assert sum(map(len, want)) >= 2
    _compare_poses(want, have)
    assert set(rt.last_timings) == {"detect", "kpd", "pnp", "total"}


def test_from_export_torch_backend_loads_the_source_checkpoints(models):
    from kpd6d.pipeline import PosePipeline

    pipe = PosePipeline.from_export(models["export"], backend="torch", top_l=6)
    assert isinstance(pipe, PosePipeline) and pipe.kpd.obj_ids == [3, 7]
    with pytest.raises(ValueError, match="backend"):
        PosePipeline.from_export(models["export"], backend="tensorrt")
    with pytest.raises(FileNotFoundError, match=r"kpd6d_export\.json"):
        PosePipeline.from_export(models["dir"], backend="onnxruntime")


def test_runtime_never_imports_torch(models):
    """Predicting from an export in a fresh process leaves torch (and kornia, the KPD module) unimported."""
    code = f"""
import sys, numpy as np
from kpd6d.deploy.runtime import RuntimePipeline
from kpd6d.geometry import LINEMOD_K
img = (np.random.default_rng(0).random((120, 160, 3)) * 255).astype(np.uint8)
for backend in ("onnxruntime", "openvino"):
    pipe = RuntimePipeline({str(models["export"])!r}, backend=backend, pnp="epnp", top_l=6)
    poses = pipe(img, LINEMOD_K)
    assert len(poses) >= 1, poses
bad = sorted(m for m in sys.modules if m.split(".")[0] in ("torch", "kornia", "pytorch_lightning", "torchvision")
             or m == "kpd6d.kpd.module")
print("BAD", bad)
"""
    src = str(Path(__file__).resolve().parents[1] / "src")
    env = {"PYTHONPATH": src, "OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"}
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "BAD []" in res.stdout, res.stdout


def test_export_cli_then_predict_cli_on_each_backend(models, tmp_path, monkeypatch):
    """kpd6d-export, then kpd6d-predict backend=torch|onnxruntime|openvino: the same poses.json."""
    import cv2

    from kpd6d.cli.export import main as export_main
    from kpd6d.cli.predict import main as predict_main

    d = models["dir"]
    monkeypatch.setattr(sys, "argv", ["kpd6d-export", f"kpd_ckpt={d / 'kpd.ckpt'}", f"detector_ckpt={d / 'det.pt'}",
                                      f"hydra.run.dir={tmp_path / 'exp'}"])
    export_main()
    assert json.loads((tmp_path / "exp" / "kpd6d_export.json").read_text())["detector"]["obj_ids"] == [3, 7]
    cv2.imwrite(str(tmp_path / "in.png"), _image(6)[:, :, ::-1])
    common = [f"input={tmp_path / 'in.png'}", "progress=false", "overlays=false", "select.top_l=6", "pnp=epnp"]
    poses = {}
    for backend in ("torch", *BACKENDS):
        run = tmp_path / backend
        args = ([f"kpd_ckpt={d / 'kpd.ckpt'}", f"detector_ckpt={d / 'det.pt'}", "device=cpu"] if backend == "torch"
                else [f"backend={backend}", f"export_dir={tmp_path / 'exp'}"])  # no checkpoints needed
        monkeypatch.setattr(sys, "argv", ["kpd6d-predict", *common, *args, f"hydra.run.dir={run}"])
        predict_main()
        poses[backend] = json.loads((run / "poses.json").read_text())["frames"][0]["poses"]
    assert len(poses["torch"]) >= 1
    for backend in BACKENDS:
        assert [p["obj_id"] for p in poses[backend]] == [p["obj_id"] for p in poses["torch"]]
        for p, q in zip(poses[backend], poses["torch"]):
            assert p["ok"] == q["ok"]
            np.testing.assert_allclose(p["box"], q["box"], atol=0.01)
            if q["ok"]:
                np.testing.assert_allclose(p["t"], q["t"], atol=0.1)


def test_benchmark_pipeline_reports_backends_side_by_side(capsys):
    from kpd6d.benchmarks.pipeline import main

    assert main(["--configs", "tiny", "--batch-sizes", "1", "--repeats", "1", "--warmup", "1", "--objects", "2",
                 "--keypoints", "8", "--top-l", "6", "--device", "cpu", "--threads", "1",
                 "--backends", "torch,onnxruntime,openvino"]) == 0
    out = capsys.readouterr().out
    assert "| config | backend | device |" in out and "x torch |" in out
    head = next(ln for ln in out.splitlines() if ln.startswith("| config | backend |"))
    col = [c.strip() for c in head.split("|")].index("x torch")
    for backend in BACKENDS:
        line = next(ln for ln in out.splitlines() if ln.startswith(f"| tiny | {backend} | cpu | 1 | 2 |"))
        ratio = float(line.split("|")[col])
        assert ratio > 0
    assert "| tiny | torch | cpu | 1 | 2 |" in out
    with pytest.raises(SystemExit):
        main(["--backends", "tensorrt"])


def test_evaluate_cli_runs_an_export_without_checkpoints(tmp_path, monkeypatch):
    """kpd6d-evaluate backend=onnxruntime export_dir=... (no kpd_ckpt; oracle boxes) evaluates every
    instance and records the backend (an untrained KPD on black images: the metrics say little, the
    pose parity is the end-to-end tests' job)."""
    from kpd6d.cli.evaluate import main
    from kpd6d.deploy.export import export_models
    from test_evaluate import _tiny_kpd_checkpoint, make_dataset

    root, _, _ = make_dataset(tmp_path / "ds", n_frames=2)
    ckpt = _tiny_kpd_checkpoint(tmp_path / "kpd.ckpt")
    export_models(ckpt, "oracle", tmp_path / "export")
    common = [f"data.root={root}", "progress=false", "overlays=0", "pnp=epnp", "select.top_l=8"]
    metrics = {}
    for backend, args in (("torch", [f"kpd_ckpt={ckpt}", "device=cpu"]),
                          ("onnxruntime", ["backend=onnxruntime", f"export_dir={tmp_path / 'export'}"])):
        monkeypatch.setattr(sys, "argv", ["kpd6d-evaluate", *common, *args, f"hydra.run.dir={tmp_path / backend}"])
        main()
        metrics[backend] = json.loads((tmp_path / backend / "metrics.json").read_text())
    got, want = metrics["onnxruntime"], metrics["torch"]
    assert got["run"]["backend"] == "onnxruntime" and "backend" not in want["run"]
    assert got["mean"]["n"] == want["mean"]["n"] == 4
    for key in ("add_s_01d", "proj2d_5px"):
        assert got["mean"][key] == pytest.approx(want["mean"][key], abs=1e-9), key


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_missing_backend_package_says_what_to_install(backend, tmp_path, monkeypatch):
    from kpd6d.deploy.runtime import BackendUnavailableError, Session

    (tmp_path / "m.onnx").write_bytes(b"")
    monkeypatch.setitem(sys.modules, backend, None)  # import fails as if not installed
    with pytest.raises(BackendUnavailableError, match=r"pip install kpd6d\[deploy\]"):
        Session(tmp_path / "m.onnx", backend)
    with pytest.raises(ValueError, match="backend 'tensorrt' unknown"):
        Session(tmp_path / "m.onnx", "tensorrt")


def test_openvino_bf16_compiles_in_bfloat16_and_stays_close_to_torch(models):
    """backend=openvino_bf16: OpenVINO with INFERENCE_PRECISION_HINT=bf16 where the CPU has bf16
    (f32 elsewhere); heatmaps within bf16's precision of torch's float32 (not the 1e-4 of f32)."""
    _require("openvino")
    import openvino as ov

    from kpd6d.deploy import BACKENDS as ALL
    from kpd6d.deploy.runtime import Session

    assert "openvino_bf16" in ALL
    sess = Session(models["export"] / "kpd.onnx", "openvino_bf16")
    caps = ov.Core().get_property("CPU", "OPTIMIZATION_CAPABILITIES")
    hint = sess._compiled.get_property("INFERENCE_PRECISION_HINT")
    hint = "bf16" if hint == ov.Type.bf16 else "f32" if hint == ov.Type.f32 else str(hint)
    assert hint == ("bf16" if "BF16" in caps else "f32"), (hint, caps)
    x = torch.rand(4, 3, 64, 64, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        ref = models["kpd"].net(x).numpy()
    got = sess(x.numpy())[0]
    scale = np.abs(ref).max()
    err = np.abs(got - ref).max()
    assert err <= 0.05 * scale, (err, scale)  # bf16 keeps 8 bits of mantissa
    if hint == "bf16":
        assert err > 1e-5  # and it is not float32 in disguise
