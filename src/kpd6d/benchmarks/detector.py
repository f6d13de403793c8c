"""``kpd6d-benchmark detector``: detector latency and accuracy.

Latency (default): per-image time of ``detector.predict`` on 640x480 images, batch 1 and batched,
for each detector config (``conf/detector/<name>.yaml``, built as configured; untrained weights:
timing only), on CPU and on CUDA when available.

Accuracy (``--checkpoint PATH --data ROOT [--split test]``): AP@0.5 and AP@0.5:0.95 of a trained
detector (``detector.pt`` from ``kpd6d-train stage=detector``) on a BOP split.
"""

from __future__ import annotations

import argparse
import json
import time


def detector_config(choice: str) -> dict:
    """The parameters of config choice ``conf/detector/<choice>.yaml`` (``name`` = registry name)."""
    from omegaconf import OmegaConf

    from kpd6d.config import config_dir

    path = config_dir() / "detector" / f"{choice}.yaml"
    if not path.is_file():
        known = sorted(q.stem for q in path.parent.glob("*.yaml"))
        raise ValueError(f"unknown detector config {choice!r} (no {path}); known: {', '.join(known)}")
    return OmegaConf.to_container(OmegaConf.load(path), resolve=True)


def _latency(config: dict, device: str, batch: int, iters: int, width: int, height: int,
             input_size) -> tuple[float, str]:
    """Seconds per image of ``predict`` of the detector ``config`` describes, and the input size used."""
    import torch

    from kpd6d.detection import build_detector

    params = dict(config)
    name = params.pop("name")
    params["obj_ids"] = [1, 2, 3, 4, 5, 6]
    if input_size is not None and "input_size" in params:
        params["input_size"] = input_size
    det = build_detector(name, **params).to(device).eval()
    images = torch.rand(batch, 3, height, width, device=device)
    targets = [{"boxes": torch.tensor([[100.0, 100, 80, 60]] * 6), "obj_ids": torch.arange(1, 7)}] * batch
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    for _ in range(2):
        det.predict(images, targets if name == "oracle" else None)
    sync()
    t0 = time.perf_counter()
    for _ in range(iters):
        det.predict(images, targets if name == "oracle" else None)
    sync()
    seconds = (time.perf_counter() - t0) / (iters * batch)
    return seconds, "x".join(str(v) for v in det.input_size) if det.input_size else "full"


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="kpd6d-benchmark detector", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--detectors", default="centernet,centernet_tiny,centernet_lite0,fcos,faster_rcnn,oracle",
                   help="comma list of detector configs (conf/detector/<name>.yaml), built as configured")
    p.add_argument("--batch-sizes", default="1,8")
    p.add_argument("--iters", type=int, default=5)
    p.add_argument("--devices", default="auto", help="comma list (cpu, cuda); auto: cpu and cuda if available")
    p.add_argument("--size", default="640x480", help="image size WxH")
    p.add_argument("--input-size", default="config",
                   help="network input WxH (images are resized to it); config: each detector's configured size")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    p.add_argument("--checkpoint", help="accuracy mode: a trained detector (detector.pt)")
    p.add_argument("--data", help="accuracy mode: BOP dataset root")
    p.add_argument("--split", default="test")
    p.add_argument("--json", help="also write the figures to this JSON file")
    a = p.parse_args(argv)
    import torch

    if a.threads:
        torch.set_num_threads(a.threads)
    if a.checkpoint or a.data:
        if not (a.checkpoint and a.data):
            p.error("accuracy mode needs both --checkpoint and --data")
        from kpd6d.detection import load_detector
        from kpd6d.detection.dataset import DetectionDataset
        from kpd6d.detection.metrics import evaluate_detector

        det = load_detector(a.checkpoint)
        ds = DetectionDataset(a.data, a.split, obj_ids=det.obj_ids, input_size=det.input_size)
        t0 = time.perf_counter()
        res = evaluate_detector(det, ds, per_object=True)
        res.pop("box_stats", None)
        res.update(images=len(ds), eval_s=round(time.perf_counter() - t0, 1), checkpoint=a.checkpoint,
                   split=a.split)
        print(f"detector accuracy on {a.data} [{a.split}], {len(ds)} images, {res['num_gt']} objects:")
        print(f"  AP@0.5 = {res['map_50']:.4f}   AP@0.5:0.95 = {res['map']:.4f}   "
              f"recall@IoU0.5 (score >= {det.score_threshold}) = {res['recall_at_iou']:.4f}")
        print("  AP@0.5 per object: " + ", ".join(f"{o}: {v:.3f}" for o, v in sorted(res["ap50_per_object"].items())))
        rows = [res]
    else:
        W, H = (int(v) for v in a.size.lower().split("x"))
        insz = [int(v) for v in a.input_size.lower().split("x")] if a.input_size not in ("", "none", "config") else None
        devices = (["cpu"] + (["cuda"] if torch.cuda.is_available() else [])) if a.devices == "auto" \
            else a.devices.split(",")
        try:
            configs = {name: detector_config(name) for name in a.detectors.split(",")}
        except ValueError as e:
            p.error(str(e))
        rows = []
        print(f"detector latency per image, {W}x{H} images, torch threads {torch.get_num_threads()}")
        print(f"{'detector':<15} {'input':<8} {'device':<6} {'batch':>5} {'ms/image':>10}")
        for dev in devices:
            for name, config in configs.items():
                for b in (int(x) for x in a.batch_sizes.split(",")):
                    s, used = _latency(config, dev, b, a.iters, W, H, insz)
                    rows.append({"detector": name, "input": used, "device": dev, "batch": b,
                                 "ms_per_image": round(s * 1e3, 2)})
                    print(f"{name:<15} {used:<8} {dev:<6} {b:>5} {s * 1e3:>10.2f}", flush=True)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=2)
    return 0
