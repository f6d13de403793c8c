"""kpd6d.benchmarks.flops: FLOP counts against hand-computed ones, the matmul peak, the pipeline table."""

from __future__ import annotations

import math

import pytest
import torch

from kpd6d.benchmarks.flops import count_flops, matmul_peak_gflops

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_count_flops_matches_the_formulas():
    lin = torch.nn.Linear(64, 32)
    assert count_flops(lin, torch.zeros(4, 64)) == 2 * 4 * 64 * 32
    conv = torch.nn.Conv2d(3, 8, 3, padding=1)
    assert count_flops(conv, torch.zeros(2, 3, 16, 16)) == 2 * 2 * 8 * 16 * 16 * 3 * 9
    dw = torch.nn.Conv2d(8, 8, 3, stride=2, padding=1, groups=8)  # depthwise, stride 2: 8 x 8 outputs
    assert count_flops(dw, torch.zeros(1, 8, 16, 16)) == 2 * 8 * 8 * 8 * 9
    assert count_flops(torch.relu, torch.zeros(10)) == 0  # element-wise work is not counted


def test_matmul_peak_is_a_positive_rate():
    g = matmul_peak_gflops(n=128, repeats=2)
    assert math.isfinite(g) and g > 0.01


def test_pipeline_benchmark_reports_network_arithmetic(capsys):
    from kpd6d.benchmarks.pipeline import build, main, network_flops

    det, kpd = build("tiny", 8, 2, torch.device("cpu"))
    images = torch.rand(1, 3, 480, 640)
    one = network_flops(det, kpd, images, torch.tensor([[10.0, 10, 80, 60]]), torch.tensor([0]), torch.tensor([1]))
    two = network_flops(det, kpd, images, torch.tensor([[10.0, 10, 80, 60], [200, 100, 60, 90]]),
                        torch.tensor([0, 0]), torch.tensor([1, 2]))
    assert one[0] == two[0] > 0  # the detector's work does not depend on the boxes
    assert two[1] == 2 * one[1] > 0  # the KPD's grows with the number of crops
    assert main(["--configs", "tiny", "--batch-sizes", "1", "--repeats", "1", "--warmup", "0", "--objects", "2",
                 "--keypoints", "8", "--top-l", "6", "--device", "cpu", "--threads", "1"]) == 0
    out = capsys.readouterr().out
    assert "machine peak (float32 1024x1024 matmul, 1 threads):" in out
    head = next(ln for ln in out.splitlines() if ln.startswith("| config |"))
    cols = [c.strip() for c in head.split("|")]
    row = [c.strip() for c in next(ln for ln in out.splitlines() if ln.startswith("| tiny |")).split("|")]
    assert float(row[cols.index("KPD GFLOP/img")]) == pytest.approx(two[1] / 1e9, rel=0.01)
    assert float(row[cols.index("det GFLOP/s")]) > 0
    assert "lmo" in __import__("kpd6d.benchmarks.pipeline", fromlist=["CONFIGS"]).CONFIGS


def test_tracking_fps_formula_and_table():
    """Tracked fps = batch / (crop + kpd + decode + pnp + projection); with the detector every N-th
    frame the per-frame time is the weighted mean of tracked and detected frames."""
    from kpd6d.benchmarks.pipeline import format_table, projection_seconds, tracking_fps

    st = {"detect": 0.030, "crop": 0.005, "kpd": 0.020, "decode": 0.003, "pnp": 0.002}
    track, mixed = tracking_fps(st, 0.001, 1, 10)
    assert track == pytest.approx(1 / 0.031)
    assert mixed == pytest.approx(1 / (0.9 * 0.031 + 0.1 * 0.061))
    assert tracking_fps(st, 0.001, 1, 1)[1] == pytest.approx(1 / 0.061)  # N=1: detect every frame
    assert 0 < projection_seconds(8, repeats=2) < 1.0
    row = {"config": "x", "batch": 1, "objects_per_image": 8, "device": "cpu",
           **{f"{s}_ms_per_image": 1000 * v for s, v in st.items()}, "total_ms_per_image": 60.0,
           "fps": 1 / 0.06, "track_fps": track, "track_detect_every_fps": mixed, "detect_every": 10}
    out = format_table([row])
    assert "tracked fps" in out and f"{track:.2f} | {mixed:.2f} (N=10) |" in out
