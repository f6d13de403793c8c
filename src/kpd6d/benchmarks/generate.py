"""``kpd6d-benchmark generate``: synthetic-data throughput (images/s, writing included).

Generates ``--num-images`` 640x480 images (one target object, one occluder by default) with
:func:`kpd6d.synth.generate_dataset` into a temporary folder and prints

* ``total``: images / wall time of the whole call (worker start-up, model loading, writing);
* ``steady``: images / time between the first and the last image written (rgb file times), i.e.
  the rate once the workers run;
* ``CPU``: CPU time per image over all processes and threads (start-up included), and the rate
  that many idle cores would reach (an upper bound; use it when other jobs load the machine);
* a per-stage profile of one process (``--profile``): where the time of one image goes.

``--experiment lmo --models-dir <BOP lmo>/models`` measures the scenes of a recipe instead: that
experiment's ``data.options`` (table-top layout, objects per image, distractors, lighting) and
``objects.obj_ids``, exactly as ``kpd6d-run experiment=lmo`` generates them.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path


def _steady_rate(root: Path, split: str) -> tuple[float, int]:
    times = sorted(p.stat().st_mtime for p in root.glob(f"{split}/*/rgb/*") if not p.name.startswith("."))
    if len(times) < 2 or times[-1] <= times[0]:
        return float("nan"), len(times)
    return (len(times) - 1) / (times[-1] - times[0]), len(times)


def _profile(args) -> None:
    """Time the stages of one process making images (no pool, no JSON)."""
    import numpy as np

    from kpd6d.synth import SynthConfig
    from kpd6d.synth.generate import image_rng

    root = Path(tempfile.mkdtemp(prefix="kpd6d-bench-prof-"))
    try:
        from kpd6d.synth import generate_dataset

        opts, obj_ids = _options(args)
        generate_dataset(root, args.models_dir, obj_ids=obj_ids, num_images=1, workers=1, progress=False, **opts)
        import kpd6d.synth.generate as gen

        spec = {"root": str(root), "split_dir": str(root / "prof"), "obj_ids": obj_ids, "seed": 1,
                "config": SynthConfig.from_options(opts).to_dict()}
        gen._init_worker(spec)
        comp = gen._STATE["composer"]
        stages = {"background": 0.0, "render (scene + extra silhouette passes)": 0.0, "compose (paste, photometric)": 0.0,
                  "encode + write": 0.0}
        renderer = comp.renderer
        real_render = renderer.render

        def timed_render(*a, **k):
            t = time.perf_counter()
            out = real_render(*a, **k)
            stages["render (scene + extra silhouette passes)"] += time.perf_counter() - t
            return out

        renderer.render = timed_render
        real_bg = comp.backgrounds.sample

        def timed_bg(*a, **k):
            t = time.perf_counter()
            out = real_bg(*a, **k)
            stages["background"] += time.perf_counter() - t
            return out

        comp.backgrounds.sample = timed_bg
        n = args.profile
        renderer.pass_stats.clear()
        t_all = time.perf_counter()
        for i in range(n):
            t0 = time.perf_counter()
            before = stages["background"] + stages["render (scene + extra silhouette passes)"]
            sample = comp.compose(image_rng(1, i))
            t1 = time.perf_counter()
            stages["compose (paste, photometric)"] += (t1 - t0) - (
                stages["background"] + stages["render (scene + extra silhouette passes)"] - before)
            from kpd6d.io import atomic_write_image

            cfg = gen._STATE["cfg"]
            sd = root / "prof" / "000000"
            for j, inst in enumerate(sample.instances):
                atomic_write_image(sd / "mask_visib" / f"{i:06d}_{j:06d}.png", inst.mask_visib.astype(np.uint8) * 255,
                                   png_compression=cfg.png_compression)
            atomic_write_image(sd / "rgb" / f"{i:06d}.{cfg.rgb_format}", sample.rgb, png_compression=cfg.png_compression,
                               jpg_quality=cfg.jpg_quality)
            stages["encode + write"] += time.perf_counter() - t1
        wall = time.perf_counter() - t_all
        print(f"\nprofile, one process, {n} images: {1000 * wall / n:.1f} ms/image")
        for k, v in stages.items():
            print(f"  {k:42s} {1000 * v / n:7.1f} ms")
        for kind, (count, secs) in sorted(renderer.pass_stats.items()):
            print(f"    {kind + ' passes':40s} {1000 * secs / n:7.1f} ms  ({count / n:.2f} per image, "
                  f"{1000 * secs / max(count, 1):.1f} ms each)")
        gen._STATE["renderer"].close()
        gen._STATE.clear()
    finally:
        shutil.rmtree(root, ignore_errors=True)


def experiment_options(name: str, models_dir: str | None) -> tuple[dict, list[int] | None]:
    """(generator options, object ids) of ``conf/experiment/<name>.yaml``: its ``data.options`` and
    ``objects.obj_ids``, as ``kpd6d-run experiment=<name>`` composes them."""
    from hydra import compose, initialize_config_dir

    from kpd6d.config import config_dir
    from kpd6d.io import to_plain

    overrides = [f"experiment={name}"] + ([f"objects.models_dir={models_dir}"] if models_dir else [])
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("run", overrides=overrides)
    ids = to_plain(cfg.objects.obj_ids)
    return dict(to_plain(cfg.data.options) or {}), (None if ids is None else [int(i) for i in ids])


def _options(args) -> tuple[dict, list[int] | None]:
    """Generator options and object ids of the benchmark: one object + occluders, or an experiment's."""
    if args.experiment:
        opts, obj_ids = experiment_options(args.experiment, args.models_dir)
    else:
        opts = dict(objects_per_image=(1, 1), distractors=(args.occluders, args.occluders))
        obj_ids = None
    opts.update(width=args.width, height=args.height, rgb_format=args.rgb_format, depth=args.depth,
                antialias=args.antialias, designator=None)
    return opts, obj_ids


def _describe(args, opts: dict, obj_ids) -> str:
    if args.experiment:
        return (f"experiment={args.experiment} ({opts.get('layout', 'free')} layout, objects per image "
                f"{opts.get('objects_per_image')}, distractors {opts.get('distractors')}, "
                f"{len(obj_ids) if obj_ids else 'all'} object models)")
    return f"1 object + {args.occluders} occluder(s)"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="kpd6d-benchmark generate", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--num-images", type=int, default=300)
    ap.add_argument("--workers", type=int, default=0, help="0: all cores")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--occluders", type=int, default=1)
    ap.add_argument("--rgb-format", default="jpg", choices=["jpg", "png"])
    ap.add_argument("--depth", action="store_true")
    ap.add_argument("--antialias", action="store_true", help="4x multisampled colour pass")
    ap.add_argument("--models-dir", default=None, help="BOP models folder (default: procedural objects)")
    ap.add_argument("--experiment", default=None,
                    help="measure this conf/experiment's scenes (its data.options and obj_ids), e.g. lmo")
    ap.add_argument("--out", default=None, help="keep the dataset here (default: a temporary folder, deleted)")
    ap.add_argument("--profile", type=int, default=0, metavar="N", help="also profile N images in one process")
    args = ap.parse_args(argv)

    from kpd6d.synth import generate_dataset
    from kpd6d.synth.generate import resolve_workers

    workers = resolve_workers(args.workers)
    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="kpd6d-bench-gen-"))
    if args.out and root.exists() and any(root.iterdir()):
        print(f"kpd6d-benchmark generate: --out {root} is not empty", file=sys.stderr)
        return 2
    try:
        import resource

        def cpu() -> float:  # this process + finished children (the pool's workers), all threads
            a, b = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
            return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime

        opts, obj_ids = _options(args)
        c0, t0 = cpu(), time.perf_counter()
        generate_dataset(root, args.models_dir, obj_ids=obj_ids, num_images=args.num_images, workers=workers,
                         progress=False, **opts)
        wall, cpu_s = time.perf_counter() - t0, cpu() - c0
        steady, n = _steady_rate(root, "train")
        print(f"kpd6d-benchmark generate: {args.num_images} images {args.width}x{args.height}, "
              f"{_describe(args, opts, obj_ids)}, rgb {args.rgb_format}{', depth' if args.depth else ''}"
              f"{', antialias' if args.antialias else ''}, "
              f"{workers} worker(s), {os.cpu_count()} cores")
        print(f"  total : {args.num_images / wall:6.1f} images/s  ({wall:.1f} s incl. start-up and models)")
        print(f"  steady: {steady:6.1f} images/s  (first to last image written, {n} images)")
        ncpu = os.cpu_count() or 1
        print(f"  CPU   : {1000 * cpu_s / args.num_images:6.1f} ms CPU time/image (all processes and threads); "
              f"{ncpu} idle cores would give at most {ncpu * args.num_images / cpu_s:.1f} images/s")
        if os.getloadavg()[0] > ncpu:
            print(f"  note  : load average {os.getloadavg()[0]:.1f} on {ncpu} cores -- other jobs share the CPU; "
                  "wall-clock rates are low")
    finally:
        if not args.out:
            shutil.rmtree(root, ignore_errors=True)
    if args.profile:
        _profile(args)
    return 0
