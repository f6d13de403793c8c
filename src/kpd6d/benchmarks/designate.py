"""``kpd6d-benchmark designate``: time keypoint designation per object and check the results.

By default it designates ``--num-keypoints`` (50) SIFT keypoints with the designator's default
settings (conf/designator/sift.yaml: 60 views at 256 px) for every procedural object; with
``--models-dir`` (a BOP models folder, e.g. LM-O's) it uses those meshes, ``--obj-ids`` picks some.
For each object it prints the wall time (the first object also pays for the OpenGL context), the
number of SIFT detections and clusters, how many keypoints came from SIFT (the rest: farthest-point
fill), the largest distance of a keypoint to the surface (mm) and the smallest distance between two
keypoints relative to the diameter. ``--auto-symmetry`` also times ``SYMMETRIES.build("auto")``.
The target (issue 3): 50 SIFT keypoints for one LM-O object in under 60 s on a 2-core CPU.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="kpd6d-benchmark designate", description=__doc__.split("\n\n")[0])
    p.add_argument("--models-dir", default=None, help="BOP models folder (default: the procedural objects)")
    p.add_argument("--obj-ids", type=int, nargs="*", default=None, help="object ids (default: all)")
    p.add_argument("--designator", default="sift", help="sift | fps | bbox_corners (default: sift)")
    p.add_argument("--num-keypoints", type=int, default=50)
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                   help="extra designator parameter (e.g. num_views=40), repeatable")
    p.add_argument("--auto-symmetry", action="store_true", help="also time the automatic symmetry detection")
    p.add_argument("--target-s", type=float, default=60.0, help="time per object to report against (s)")
    return p


def _value(text: str):
    import yaml

    return yaml.safe_load(text)


def main(argv: list[str] | None = None) -> int:
    import trimesh

    from kpd6d.objects import load_bop_models, procedural_objects
    from kpd6d.registry import DESIGNATORS, SYMMETRIES

    args = _parser().parse_args(argv)
    params = {"num_keypoints": args.num_keypoints}
    for kv in args.param:
        if "=" not in kv:
            raise SystemExit(f"--param expects KEY=VALUE, got {kv!r}")
        k, v = kv.split("=", 1)
        params[k] = _value(v)
    if args.designator == "bbox_corners":
        params["num_keypoints"] = 9
    models = (load_bop_models(args.models_dir, obj_ids=args.obj_ids) if args.models_dir
              else procedural_objects(obj_ids=args.obj_ids))
    source = args.models_dir or "procedural objects"
    print(f"designate benchmark: {args.designator} {params} on {source}")
    print(f"{'obj':>4} {'faces':>7} {'time_s':>7} {'detect':>7} {'clusters':>8} {'from_sift':>9} "
          f"{'max_surf_mm':>11} {'min_dist/diam':>13}" + ("  auto_sym_s  auto_found" if args.auto_symmetry else ""))
    times = []
    for m in models:
        d = DESIGNATORS.build(args.designator, **params)
        t0 = time.perf_counter()
        kp = d(m)
        dt = time.perf_counter() - t0
        times.append(dt)
        surf = float(trimesh.proximity.closest_point(m.mesh, kp)[1].max())
        diff = kp[:, None] - kp[None]
        dist = np.linalg.norm(diff, axis=-1) + np.eye(len(kp)) * 1e9
        st = getattr(d, "last_stats", {}) or {}
        line = (f"{m.obj_id:>4} {len(m.faces):>7} {dt:>7.2f} {st.get('detections', '-'):>7} {st.get('clusters', '-'):>8} "
                f"{st.get('sift_keypoints', '-'):>9} {surf:>11.4f} {dist.min() / m.diameter:>13.4f}")
        if args.auto_symmetry:
            t1 = time.perf_counter()
            found = SYMMETRIES.build("auto")(m)
            line += f"  {time.perf_counter() - t1:>10.2f}  {len(found['symmetries_discrete'])}d/{len(found['symmetries_continuous'])}c"
        print(line, flush=True)
    print(f"time per object: mean {np.mean(times):.2f} s, max {np.max(times):.2f} s "
          f"(target < {args.target_s:.0f} s: {'met' if max(times) < args.target_s else 'NOT met'})")
    return 0
