"""``kpd6d-benchmark pnp``: speed and accuracy of every PnP solver on LM-O-like problems.

Keypoints are ``--num-keypoints`` points sampled on the surface of procedural object 1 (the
library's embedded default, no data needed); poses are uniform random rotations at LineMod
distances (z in 400..1200 mm, object inside the 640x480 LineMod view), projected with LINEMOD_K
plus Gaussian noise of ``--noise`` px (and optionally a fraction ``--outliers`` of points moved by
30..150 px). For each solver it prints the time per solve called one problem at a time
(``--single`` problems), the time of one ``solve_batch`` over ``--batch`` problems (total and per
problem), the fraction of problems solved (ok), the ADD accuracy (ADD < 0.1 diameter, over 1000
surface points; failures count as wrong) and the median ADD of the batch results.
``--device cuda`` passes torch tensors on the GPU (the torch solvers solve there; OpenCV ones
copy to the CPU and loop).
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from kpd6d.evaluation import add_error, add_s_accuracy
from kpd6d.geometry import LINEMOD_K, project_points, random_rotation
from kpd6d.registry import PNP_SOLVERS

DEFAULT_SOLVERS = ("epnp", "iterative", "sqpnp", "epnp_ransac", "sqpnp_ransac", "dlt", "weighted_lm")


def make_problems(num_keypoints: int, batch: int, noise: float, outliers: float, seed: int):
    """(keypoints (n,3), eval points (1000,3), diameter, R (B,3,3), t (B,3), uv (B,n,2))."""
    from kpd6d.objects import procedural_objects

    model = procedural_objects(seed=0, obj_ids=[1])[0]
    kp = model.sample_points(num_keypoints, seed=seed)
    pts = model.sample_points(1000, seed=seed + 1)
    rng = np.random.default_rng(seed)
    R = random_rotation(rng, batch)
    z = rng.uniform(400.0, 1200.0, batch)
    t = np.stack([rng.uniform(-0.15, 0.15, batch) * z, rng.uniform(-0.1, 0.1, batch) * z, z], axis=-1)
    uv = project_points(kp, LINEMOD_K, R, t) + rng.normal(0.0, noise, (batch, num_keypoints, 2))
    n_out = round(outliers * num_keypoints)
    if n_out:
        for b in range(batch):
            idx = rng.choice(num_keypoints, n_out, replace=False)
            ang = rng.uniform(0, 2 * math.pi, n_out)
            uv[b, idx] += rng.uniform(30, 150, (n_out, 1)) * np.stack([np.cos(ang), np.sin(ang)], -1)
    return kp, pts, float(model.diameter), R, t, uv


def _sync(device: str) -> None:
    if device == "cuda":
        import torch

        torch.cuda.synchronize()


def run(args) -> list[dict]:
    from tqdm import tqdm

    kp, pts, diameter, R_gt, t_gt, uv = make_problems(args.num_keypoints, args.batch, args.noise,
                                                      args.outliers, args.seed)
    B = args.batch
    X = np.broadcast_to(kp, (B, *kp.shape)).copy()
    K = LINEMOD_K
    if args.device == "cuda":
        import torch

        X_in, uv_in, K_in = (torch.as_tensor(a, device="cuda") for a in (X, uv, K))
    else:
        X_in, uv_in, K_in = X, uv, K
    print(f"object: procedural #1, diameter {diameter:.1f} mm; {args.num_keypoints} keypoints; noise {args.noise} px; "
          f"outliers {args.outliers:.0%}; device {args.device}; {args.single} single solves, batch of {B}")
    rows = []
    for name in tqdm(args.solvers, desc="solvers", unit="solver"):
        solver = PNP_SOLVERS.build(name)
        n1 = min(args.single, B)
        solver.solve_batch(X_in[:4], uv_in[:4], K_in)  # warm-up (imports, CUDA kernels)
        solver(X_in[0], uv_in[0], K_in)
        _sync(args.device)
        t0 = time.perf_counter()
        for i in range(n1):
            solver(X_in[i], uv_in[i], K_in)
        _sync(args.device)
        single = (time.perf_counter() - t0) / max(n1, 1)
        t0 = time.perf_counter()
        res = solver.solve_batch(X_in, uv_in, K_in)
        _sync(args.device)
        total = time.perf_counter() - t0
        R = res.R.cpu().numpy() if hasattr(res.R, "cpu") else res.R
        t = res.t.cpu().numpy() if hasattr(res.t, "cpu") else res.t
        ok = np.asarray(res.ok.cpu() if hasattr(res.ok, "cpu") else res.ok, dtype=bool)
        add = np.array([add_error(R[b], t[b], R_gt[b], t_gt[b], pts) for b in range(B)])
        rows.append({
            "solver": name, "single_ms": 1e3 * single, "batch_s": total, "batch_ms": 1e3 * total / B,
            "ok": ok.mean(), "add_acc": add_s_accuracy(add, diameter), "median_add": float(np.median(add)),
        })
    return rows


def format_table(rows: list[dict]) -> str:
    head = f"{'solver':<12} {'single ms/solve':>15} {'batch total s':>13} {'batch ms/problem':>16} {'ok %':>6} " \
           f"{'ADD<0.1d %':>10} {'median ADD mm':>13}"
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(f"{r['solver']:<12} {r['single_ms']:>15.3f} {r['batch_s']:>13.2f} {r['batch_ms']:>16.4f} "
                     f"{100 * r['ok']:>6.1f} {100 * r['add_acc']:>10.2f} {r['median_add']:>13.2f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="kpd6d-benchmark pnp", description=__doc__.split("\n\n")[0])
    p.add_argument("--num-keypoints", type=int, default=50)
    p.add_argument("--batch", type=int, default=10000, help="problems in the batched solve (default 10000)")
    p.add_argument("--single", type=int, default=1000, help="problems solved one at a time for timing (default 1000)")
    p.add_argument("--noise", type=float, default=1.0, help="Gaussian pixel noise, px (default 1.0)")
    p.add_argument("--outliers", type=float, default=0.0, help="fraction of keypoints made gross outliers (default 0)")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    p.add_argument("--solvers", default=",".join(DEFAULT_SOLVERS),
                   help=f"comma-separated PnP solver names (default {','.join(DEFAULT_SOLVERS)})")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    args.solvers = [s.strip() for s in args.solvers.split(",") if s.strip()]
    unknown = [s for s in args.solvers if s not in PNP_SOLVERS]
    if unknown:
        p.error(f"unknown solver(s) {', '.join(unknown)}; known: {', '.join(PNP_SOLVERS.names())}")
    if args.num_keypoints < 6 or args.batch < 4 or args.single < 1 or args.noise < 0 or not 0 <= args.outliers < 1:
        p.error("need --num-keypoints >= 6, --batch >= 4, --single >= 1, --noise >= 0, 0 <= --outliers < 1")
    if args.device == "cuda":
        import torch

        if not torch.cuda.is_available():
            p.error("--device cuda: no CUDA device available")
    print(format_table(run(args)))
    return 0
