"""``kpd6d-benchmark pipeline``: time per stage (detect, crop, KPD, decode, PnP) and end-to-end fps.

Untrained weights (timing only), 640x480 images, ``--objects`` boxes per image (fixed boxes, so the
number of KPD crops does not depend on what an untrained detector finds; the detector still runs on
the full images). Configurations:

* ``paper``: KPD resnet101 + deconv head (256 ch), 256x256 crops, 50 keypoints, EPnP on the top-10;
  CenterNet resnet18 detector at 320x240.
* ``fast``: KPD resnet18 + deconv head (64 ch), 128x128 crops, 50 keypoints, EPnP on the top-10;
  CenterNet resnet10t detector at 256x192.
* ``demo_resnet18``: the demo's networks until 2026-12 (KPD resnet18 + FPN head (64 ch), 96x96 crops;
  CenterNet resnet18 (32 ch) at 320x240), 50 keypoints, EPnP on the top-10.
* ``demo_lite0``: the same on EfficientNet-Lite0 (the ImageNet-pretrained backbone the demo uses now)
  in both stages.
* ``lmo``: the LM-O recipe's networks (``experiment=lmo``): KPD EfficientNet-Lite0 + FPN head (64 ch),
  96x96 crops; CenterNet EfficientNet-Lite0 (32 ch) at 320x240; use ``--objects 8``.
* ``tiny``: a few-layer KPD (64x64 crops) and an 8-channel CenterNet at 128x96, for smoke tests.

Each batch size is timed ``--repeats`` times after ``--warmup`` runs; the median is reported.
End-to-end = the sum of the stages (the same work ``PosePipeline.predict_batch`` does).

``--backends torch,onnxruntime,openvino``: the same networks exported to ONNX (a temporary folder,
:mod:`kpd6d.deploy.export`) and run by the torch-free runtime (:mod:`kpd6d.deploy.runtime`: numpy
crops, decoding and detector post-processing), reported side by side with the speed-up over eager
torch (``x torch``: fps / torch's fps for the same config and batch).

Tracking (:mod:`kpd6d.tracking`): a tracked frame skips the detector and crops on the boxes of the
previous frame's poses projected with K, so its cost is the crop, KPD, decode and PnP stages plus the
box projection (timed here, per object, with the tracker's own ``projected_box``). Each row gives the
steady-state tracked fps and, with ``--detect-every N`` (default 10), the fps when the detector also
runs on every N-th frame: ``1 / ((N - 1) / N * track + 1 / N * (track + detect))`` per frame. The
detect-every-frame figure is the row's ``fps``.

Arithmetic (:mod:`kpd6d.benchmarks.flops`): each torch row also gives the GFLOP per image of the
detector and of the KPD (counted by PyTorch's FlopCounterMode: convolutions and matrix products)
and the GFLOP/s each reached, next to the machine's measured float32 matmul peak (printed above the
table), so the distance to the machine's limit is visible.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time

import numpy as np
import torch

CONFIGS = {
    "paper": {"backbone": {"name": "resnet101"}, "head": {"name": "deconv", "deconv_channels": 256}, "input_size": 256,
              "detector": {"name": "centernet", "backbone": "resnet18", "neck_channels": 64, "head_channels": 64,
                           "input_size": [320, 240]}},
    "fast": {"backbone": {"name": "resnet18"}, "head": {"name": "deconv", "deconv_channels": 64}, "input_size": 128,
             "detector": {"name": "centernet", "backbone": "resnet10t", "neck_channels": 48, "head_channels": 48,
                          "input_size": [256, 192]}},
    "demo_resnet18": {"backbone": {"name": "resnet18"}, "head": {"name": "fpn", "fpn_channels": 64}, "input_size": 96,
                      "detector": {"name": "centernet", "backbone": "resnet18", "input_size": [320, 240]}},
    # pretrained: null: the same network with random weights (timing only, no weights file read)
    "demo_lite0": {"backbone": {"name": "efficientnet_lite0", "pretrained": None},
                   "head": {"name": "fpn", "fpn_channels": 64}, "input_size": 96,
                   "detector": {"name": "centernet", "backbone": "efficientnet_lite0", "input_size": [320, 240]}},
    # the LM-O recipe's networks (experiment=lmo: conf/kpd/cpu_pretrained.yaml, conf/detector/centernet_lite0.yaml);
    # run it with --objects 8 (the 8 LM-O objects per image)
    "lmo": {"backbone": {"name": "efficientnet_lite0", "pretrained": None},
            "head": {"name": "fpn", "fpn_channels": 64}, "input_size": 96,
            "detector": {"name": "centernet", "backbone": "efficientnet_lite0", "neck_channels": 32,
                         "head_channels": 32, "input_size": [320, 240]}},
    # smoke tests of the benchmark itself (not a model anyone deploys)
    "tiny": {"backbone": {"name": "tiny", "width": 8}, "head": {"name": "deconv", "deconv_channels": 16},
             "input_size": 64, "detector": {"name": "centernet", "backbone": "resnet10t", "neck_channels": 8,
                                            "head_channels": 8, "input_size": [128, 96]}},
}
STAGES = ("detect", "crop", "kpd", "decode", "pnp")


def _sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize()


def build(config: str, num_keypoints: int, num_objects: int, device):
    from kpd6d.detection import build_detector
    from kpd6d.kpd.module import KPDModule

    c = CONFIGS[config]
    rng = np.random.default_rng(0)
    obj_ids = list(range(1, num_objects + 1))
    kpd = KPDModule(obj_ids=obj_ids, keypoints_3d=[rng.uniform(-50, 50, (num_keypoints, 3)) for _ in obj_ids],
                    diameters=[150.0] * num_objects, backbone=c["backbone"], head=c["head"],
                    codec={"input_size": c["input_size"], "out_stride": 4}).to(device).eval()
    det = build_detector(**{**c["detector"], "obj_ids": obj_ids}).to(device).eval()
    return det, kpd


@torch.no_grad()
def time_batch(det, kpd, pnp, images, boxes, image_index, obj_ids, K, top_l, device) -> dict[str, float]:
    """Seconds per stage for one batch."""
    from kpd6d.geometry import affine_apply, invert_affine
    from kpd6d.kpd.crops import inference_crops
    from kpd6d.pnp.top_l import top_l as select_top_l

    t = {}
    _sync(device)
    t0 = time.perf_counter()
    det.predict(images)
    _sync(device)
    t1 = time.perf_counter()
    crops, A = inference_crops(images, boxes, image_index, kpd.codec)
    _sync(device)
    t2 = time.perf_counter()
    heat = kpd(crops, kpd.obj_indices(obj_ids))
    _sync(device)
    t3 = time.perf_counter()
    kp_crop, conf = kpd.decode(heat)
    kp_img = affine_apply(invert_affine(A), kp_crop.double())
    _sync(device)
    t4 = time.perf_counter()
    idx = select_top_l(conf, top_l).cpu().numpy()
    kp = kp_img.cpu().numpy()
    k3 = np.stack([kpd.keypoints_3d[int(o)] for o in obj_ids.tolist()])
    rows = np.arange(len(idx))[:, None]
    pnp.solve_batch(k3[rows, idx], kp[rows, idx], K, None)
    t5 = time.perf_counter()
    t.update(detect=t1 - t0, crop=t2 - t1, kpd=t3 - t2, decode=t4 - t3, pnp=t5 - t4)
    return t


def time_batch_runtime(rdet, rkpd, pnp, images, boxes, image_index, obj_ids, K, top_l) -> dict[str, float]:
    """Seconds per stage for one batch on the torch-free runtime (numpy (B, H, W, 3) float images)."""
    from kpd6d.geometry import affine_apply, invert_affine
    from kpd6d.kpd.decoders_numpy import heatmap_to_crop

    t0 = time.perf_counter()
    rdet.predict(images)
    t1 = time.perf_counter()
    crops, A = rkpd.crops(images, boxes, image_index)
    t2 = time.perf_counter()
    heat = rkpd.heatmaps(crops, obj_ids)
    t3 = time.perf_counter()
    coords, conf = rkpd.decoder(heat)
    kp = affine_apply(invert_affine(A), heatmap_to_crop(coords, rkpd.out_stride).astype(np.float64))
    t4 = time.perf_counter()
    idx = np.argsort(-conf, axis=-1, kind="stable")[:, :top_l]
    k3 = np.stack([rkpd.keypoints_3d[int(o)] for o in obj_ids])
    rows = np.arange(len(idx))[:, None]
    pnp.solve_batch(k3[rows, idx], kp[rows, idx], K, None)
    t5 = time.perf_counter()
    return {"detect": t1 - t0, "crop": t2 - t1, "kpd": t3 - t2, "decode": t4 - t3, "pnp": t5 - t4}


def _runtime(det, kpd, backend: str, threads: int | None):
    """The benchmark's networks exported to a temporary folder and loaded on ``backend``."""
    import tempfile

    from kpd6d.deploy.export import export_detector, export_kpd
    from kpd6d.deploy.runtime import RuntimeDetector, RuntimeKPD

    with tempfile.TemporaryDirectory(prefix="kpd6d-bench-") as d:
        knode, dnode = export_kpd(kpd, d), export_detector(det, d)
        return RuntimeDetector(d, dnode, backend, threads), RuntimeKPD(d, knode, backend, threads)


def projection_seconds(num_boxes: int, repeats: int = 20) -> float:
    """Seconds to project ``num_boxes`` objects' 3D box corners to their crop boxes (the tracker's
    per-frame work besides the KPD and PnP), median of ``repeats``."""
    from kpd6d.geometry import LINEMOD_K
    from kpd6d.tracking import projected_box

    corners = np.array([[x, y, z] for x in (-50, 50) for y in (-50, 50) for z in (-50, 50)], dtype=np.float64)
    R, t = np.eye(3), np.array([10.0, -5.0, 700.0])
    times = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        for _ in range(num_boxes):
            projected_box(corners, LINEMOD_K, R, t, (480, 640), margin=0.15)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def tracking_fps(stage_s: dict[str, float], proj_s: float, batch: int, detect_every: int) -> tuple[float, float]:
    """(steady-state tracked fps, fps with the detector on every ``detect_every``-th frame) from a
    batch's stage seconds and the box-projection seconds."""
    track = sum(stage_s[s] for s in STAGES if s != "detect") + proj_s
    n = max(1, int(detect_every))
    mixed = (n - 1) / n * track + (track + stage_s["detect"]) / n
    return batch / track, batch / mixed


def network_flops(det, kpd, images, boxes, image_index, obj_ids) -> tuple[int, int]:
    """(detector FLOPs, KPD FLOPs) of one batch: ``det.predict`` on the full images (resizing and
    decoding count nothing: only convolutions and matrix products are counted) and the KPD on the
    batch's crops."""
    from kpd6d.benchmarks.flops import count_flops
    from kpd6d.kpd.crops import inference_crops

    crops, _ = inference_crops(images, boxes, image_index, kpd.codec)
    return count_flops(det.predict, images), count_flops(kpd, crops, kpd.obj_indices(obj_ids))


def run(config: str, batch_sizes, num_objects: int, num_keypoints: int, top_l: int, repeats: int, warmup: int,
        device, backends=("torch",), threads: int | None = None, detect_every: int = 10) -> list[dict]:
    from kpd6d.geometry import LINEMOD_K
    from kpd6d.registry import PNP_SOLVERS

    det, kpd = build(config, num_keypoints, num_objects, device)
    pnp = PNP_SOLVERS.build("epnp")
    runtimes = {b: _runtime(det, kpd, b, threads) for b in backends if b != "torch"}
    if runtimes:
        det.to(device)
        kpd.to(device)
    rows = []
    for B in batch_sizes:
        g = torch.Generator().manual_seed(0)
        images = torch.rand(B, 3, 480, 640, generator=g).to(device)
        xy = torch.rand(B * num_objects, 2, generator=g) * torch.tensor([480.0, 340.0])
        wh = 60 + torch.rand(B * num_objects, 2, generator=g) * 80
        boxes = torch.cat([xy, wh], 1).to(device)
        image_index = torch.arange(B).repeat_interleave(num_objects).to(device)
        obj_ids = torch.arange(1, num_objects + 1).repeat(B).to(device)
        K = np.broadcast_to(LINEMOD_K, (B * num_objects, 3, 3))
        torch_fps = None
        det_flops, kpd_flops = network_flops(det, kpd, images, boxes, image_index, obj_ids)
        proj_s = projection_seconds(B * num_objects)
        for backend in backends:
            runs = []
            if backend != "torch":
                rdet, rkpd = runtimes[backend]
                np_images = np.ascontiguousarray(images.permute(0, 2, 3, 1).cpu().numpy())
                np_args = (np_images, boxes.cpu().numpy(), image_index.cpu().numpy(), obj_ids.cpu().tolist())
            for i in range(warmup + repeats):
                if backend == "torch":
                    r = time_batch(det, kpd, pnp, images, boxes, image_index, obj_ids, K, top_l, device)
                else:
                    r = time_batch_runtime(rdet, rkpd, pnp, *np_args, K, top_l)
                if i >= warmup:
                    runs.append(r)
            med = {s: statistics.median(r[s] for r in runs) for s in STAGES}
            total = sum(med.values())
            row = {"config": config, "batch": B, "objects_per_image": num_objects,
                   "device": str(device) if backend == "torch" else "cpu",
                   **{f"{s}_ms_per_image": 1000 * med[s] / B for s in STAGES},
                   "total_ms_per_image": 1000 * total / B, "fps": B / total}
            row["track_fps"], row["track_detect_every_fps"] = tracking_fps(med, proj_s, B, detect_every)
            row["detect_every"] = detect_every
            if backend == "torch":
                torch_fps = row["fps"]
                row.update(detect_gflop_per_image=det_flops / B / 1e9, kpd_gflop_per_image=kpd_flops / B / 1e9,
                           detect_gflops=det_flops / 1e9 / max(med["detect"], 1e-12),
                           kpd_gflops=kpd_flops / 1e9 / max(med["kpd"], 1e-12))
            if tuple(backends) != ("torch",):
                row["backend"] = backend
                row["vs_torch"] = None if torch_fps is None else row["fps"] / torch_fps
            rows.append(row)
    return rows


def format_table(rows: list[dict]) -> str:
    multi = any("backend" in r for r in rows)  # --backends: a backend column and the ratio to eager torch
    head = ("| config | " + ("backend | " if multi else "") + "device | batch | objects/img | "
            + " | ".join(f"{s} ms" for s in STAGES) + " | total ms | fps |" + (" x torch |" if multi else "")
            + " tracked fps | tracked fps, detect every N |"
            + " det GFLOP/img | det GFLOP/s | KPD GFLOP/img | KPD GFLOP/s |")
    lines = [head, "|" + "---|" * (len(STAGES) + 12 + 2 * multi)]
    for r in rows:
        ratio = "" if not multi else (" - |" if r.get("vs_torch") is None else f" {r['vs_torch']:.2f} |")
        lines.append(f"| {r['config']} | " + (f"{r['backend']} | " if multi else "")
                     + f"{r['device']} | {r['batch']} | {r['objects_per_image']} | "
                     + " | ".join(f"{r[f'{s}_ms_per_image']:.1f}" for s in STAGES)
                     + f" | {r['total_ms_per_image']:.1f} | {r['fps']:.2f} |" + ratio
                     + f" {r['track_fps']:.2f} | {r['track_detect_every_fps']:.2f} (N={r['detect_every']}) |"
                     + ("".join(f" {r[k]:.3g} |" for k in ("detect_gflop_per_image", "detect_gflops",
                                                            "kpd_gflop_per_image", "kpd_gflops"))
                        if "kpd_gflops" in r else " - | - | - | - |"))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="kpd6d-benchmark pipeline", description=__doc__.strip().splitlines()[0])
    p.add_argument("--configs", default="fast,paper", help=f"comma-separated, of {', '.join(CONFIGS)}")
    p.add_argument("--batch-sizes", default="1,4", help="comma-separated images per batch")
    p.add_argument("--objects", type=int, default=3, help="objects (KPD crops) per image")
    p.add_argument("--keypoints", type=int, default=50)
    p.add_argument("--top-l", type=int, default=10)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--warmup", type=int, default=1)
    p.add_argument("--device", default="auto", help="auto (cuda when available), cpu or cuda")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    p.add_argument("--detect-every", type=int, default=10,
                   help="tracking: the detector runs on every N-th frame (the tracked-fps column with N)")
    p.add_argument("--json", default=None, help="also write the rows as JSON here")
    p.add_argument("--backends", default="torch",
                   help="comma-separated, of torch, onnxruntime, openvino (exported networks, torch-free runtime; "
                        "needs kpd6d[deploy]); the table gains the ratio to eager torch")
    args = p.parse_args(argv)
    unknown = [c for c in args.configs.split(",") if c not in CONFIGS]
    if unknown:
        p.error(f"unknown config(s) {unknown}; known: {', '.join(CONFIGS)}")
    from kpd6d.deploy import BACKENDS

    backends = [b for b in args.backends.split(",") if b]
    bad = [b for b in backends if b not in BACKENDS]
    if bad or not backends:
        p.error(f"unknown backend(s) {bad}; known: {', '.join(BACKENDS)}")
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device("cuda" if args.device == "auto" and torch.cuda.is_available() else
                          ("cpu" if args.device == "auto" else args.device))
    sizes = [int(b) for b in args.batch_sizes.split(",")]
    rows = []
    for c in args.configs.split(","):
        rows += run(c, sizes, args.objects, args.keypoints, args.top_l, args.repeats, args.warmup, device,
                    backends=backends, threads=args.threads, detect_every=args.detect_every)
    dev_name = torch.cuda.get_device_name(device) if device.type == "cuda" else f"{platform.processor() or 'cpu'}, {torch.get_num_threads()} threads"
    print(f"device: {dev_name}; {args.objects} objects/image, {args.keypoints} keypoints, top-{args.top_l}, EPnP; "
          f"median of {args.repeats} runs; untrained weights")
    if device.type == "cpu":
        from kpd6d.benchmarks.flops import matmul_peak_gflops

        print(f"machine peak (float32 1024x1024 matmul, {torch.get_num_threads()} threads): "
              f"{matmul_peak_gflops():.1f} GFLOP/s; GFLOP counts: convolutions and matrix products")
    print(format_table(rows))
    print("paper (KPD, ResNet-101, GTX 1080 Ti): 25 fps")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)
    return 0
