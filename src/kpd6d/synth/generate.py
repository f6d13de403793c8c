"""``generate_dataset``: write a synthetic BOP dataset (render-and-paste), in parallel, resumably.

Image ``i`` lands in scene ``i // scene_size`` as image ``i % scene_size`` and is made with its own
random generator seeded from ``(seed, i)``, so the result does not depend on scheduling or on the
number of workers. Workers write each image's files (rgb, mask_visib, depth) atomically and return
its annotations; the main process keeps the scene JSON files and rewrites them atomically every few
seconds and at the end. An image is complete when all three scene JSON files list it and its files
exist; a rerun skips complete images and makes the rest (after an interruption, the same bytes).

Shards (``shard=i, num_shards=n``, n > 1): image ``k`` of the split belongs to shard ``k % n`` and is
made exactly as in the unsharded run (same random generator, same files). Several shards write into
one root at the same time without clobbering each other: a shard writes the image files it owns, and
its own partial scene files ``scene_gt.shard-i-of-n.json`` (``scene_camera`` / ``scene_gt_info``
alike) instead of the final ones, and, once all its images are done, the marker
``<root>/shards/<split>/shard-i-of-n.json``. Dataset-level files (models/, camera.json,
dataset_info.json) are identical whichever shard writes them; keypoints.json is designated by shard 0
only. :func:`kpd6d.synth.shards.merge_shards` checks the union and writes the final scene files.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from kpd6d.config import to_int
from kpd6d.data.bop_io import (
    BopFormatError,
    load_scene_camera,
    load_scene_gt,
    load_scene_gt_info,
    save_camera,
    save_scene_camera,
    save_scene_gt,
    save_scene_gt_info,
)
from kpd6d.io import atomic_write_bytes, atomic_write_image, atomic_write_json, read_json
from kpd6d.synth.config import SynthConfig

__all__ = ["generate_dataset", "image_rng", "resolve_workers", "shard_of", "shard_tag"]

INFO_FILE = "dataset_info.json"


def image_rng(seed: int, index: int) -> np.random.Generator:
    """The random generator of image ``index`` (independent of scheduling)."""
    return np.random.default_rng([int(seed), int(index)])


def shard_tag(shard: int, num_shards: int) -> str:
    """``"shard-<i>-of-<n>"``: the name part of a shard's files."""
    return f"shard-{int(shard)}-of-{int(num_shards)}"


def shard_of(index: int, num_shards: int) -> int:
    """The shard that makes image ``index`` of a split generated in ``num_shards`` shards (round robin)."""
    return int(index) % int(num_shards)


def check_shard(shard: int, num_shards: int) -> tuple[int, int]:
    """``(shard, num_shards)`` as ints, or a ValueError naming the bad value."""
    shard, num_shards = to_int(shard, "shard"), to_int(num_shards, "num_shards")
    if num_shards < 1:
        raise ValueError(f"num_shards must be >= 1, got {num_shards}")
    if not 0 <= shard < num_shards:
        raise ValueError(f"shard must be in 0..num_shards-1 = 0..{num_shards - 1}, got {shard}")
    return shard, num_shards


def resolve_workers(workers: int | None) -> int:
    """``workers`` <= 0 or None -> all cores (``os.cpu_count()``)."""
    if workers is None or int(workers) <= 0:
        return max(1, os.cpu_count() or 1)
    return int(workers)


# ---------------------------------------------------------------------------------------------
# models folder
# ---------------------------------------------------------------------------------------------
def _write_models(root: Path, models_dir: Path | None, obj_ids: list[int] | None, cfg: SynthConfig,
                  *, sharded: bool = False, designate: bool = True) -> list[int]:
    """Fill ``<root>/models`` (meshes, models_info.json, keypoints.json unless ``designate`` is false)
    unless already there. ``sharded``: other shards may be writing here now, so their temporary files
    are left alone (every file here is written identically by whichever shard gets there first)."""
    from kpd6d.objects import load_bop_models

    out = root / "models"
    out.mkdir(parents=True, exist_ok=True)
    if not sharded:
        _remove_stale_tmp(out)
    info_path = out / "models_info.json"
    if models_dir is None:
        from kpd6d.objects import procedural_objects

        models = procedural_objects(seed=cfg.procedural_seed, obj_ids=obj_ids)
        for m in models:
            p = out / f"obj_{m.obj_id:06d}.ply"
            if not p.is_file():
                atomic_write_bytes(p, m.mesh.export(file_type="ply"))
    else:
        models = load_bop_models(models_dir, obj_ids)
        for m in models:
            src = Path(m.source)
            for f in sorted(src.parent.glob(src.stem + ".*")):  # the mesh and its texture image(s)
                dst = out / f.name
                if not dst.is_file():
                    tmp = out / f".{f.name}.{uuid.uuid4().hex}.tmp"  # unique: shards may copy at once
                    shutil.copyfile(f, tmp)
                    os.replace(tmp, dst)
    ids = [m.obj_id for m in models]
    if not info_path.is_file():
        atomic_write_json(info_path, {str(m.obj_id): m.info() for m in models})
    if designate and cfg.designator is not None and not (out / "keypoints.json").is_file():
        from kpd6d.keypoints.designate import designate_objects, designator_name_params

        name, params = designator_name_params(cfg.designator)
        shipped = load_bop_models(out, ids)  # designate on the meshes the dataset ships
        # keypoints.json appears complete or not at all; the partial file lets an interrupted run resume
        partial = out / ".keypoints.partial.json"
        designate_objects(shipped, name, params, partial, progress=False)
        os.replace(partial, out / "keypoints.json")
    return ids


def _remove_stale_tmp(folder: Path, owned: Callable[[str], bool] | None = None) -> None:
    """Delete temporary files an interrupted run left behind (``.<name>.*.tmp``); with ``owned``,
    only those whose final file name ``<name>`` it accepts (a shard's own files)."""
    if folder.is_dir():
        for p in folder.glob(".*.tmp"):
            if owned is not None and not owned(p.name[1:].rsplit(".", 2)[0]):
                continue
            try:
                p.unlink()
            except OSError:
                pass


# ---------------------------------------------------------------------------------------------
# worker side
# ---------------------------------------------------------------------------------------------
_STATE: dict[str, Any] = {}


def _init_worker(spec: dict) -> None:
    """Build this process's renderer, models, backgrounds and occluders (once per worker)."""
    if spec.get("single_thread_gl"):
        os.environ.setdefault("LP_NUM_THREADS", "1")
    from kpd6d.objects import load_bop_models
    from kpd6d.render import Renderer
    from kpd6d.synth.backgrounds import make_background_source
    from kpd6d.synth.scene import SceneComposer

    cfg = SynthConfig.from_options(spec["config"])
    models = load_bop_models(Path(spec["root"]) / "models", spec["obj_ids"])
    handlers = None
    if cfg.canonicalize_symmetric:
        from kpd6d.symmetry import handler_for_model

        handlers = [handler_for_model(m) for m in models]
    renderer = Renderer(cfg.width, cfg.height, cfg.camera_K(), antialias=cfg.antialias, smooth_models=cfg.smooth_objects)
    sources = _color_sources(models, cfg)
    pool = _distractors(spec["seed"], cfg, 0, sources)
    backgrounds = make_background_source(cfg.backgrounds_dir, cfg.palette, cfg.printed_matter)
    _STATE.clear()
    _STATE.update(
        spec=spec, cfg=cfg, renderer=renderer, pool_block=0, color_sources=sources,
        composer=SceneComposer(renderer, models, cfg, backgrounds, pool, handlers),
    )


def _color_sources(models: list, cfg: SynthConfig) -> list | None:
    """The target objects' colour layouts, when occluders wear them (``distractor_object_colors``)."""
    if not cfg.distractor_object_colors or cfg.distractors[1] <= 0:
        return None
    from kpd6d.synth.distractors import color_source

    return [color_source(m.mesh) for m in models]


def _distractors(seed: int, cfg: SynthConfig, block: int, color_sources: list | None = None) -> list:
    """Distractor pool number ``block`` of a run (block 0 only, unless ``distractor_refresh``)."""
    from kpd6d.synth.distractors import distractor_pool

    if cfg.distractors[1] <= 0:
        return []
    return distractor_pool(seed, cfg.distractor_pool_size, palette=cfg.palette, block=block,
                           object_colors=cfg.distractor_object_colors, color_sources=color_sources,
                           printed=cfg.printed_matter)


def _make_images(indices: list[int]) -> list[dict]:
    return [_make_image(i) for i in indices]


def _run_pool(ctx, n_workers: int, spec: dict, todo: list[int], chunk: int, consume) -> None:
    """Images ``todo`` in ``n_workers`` processes, results to ``consume`` as they come. A worker that
    dies (it cannot start, or crashes) ends the run with an error instead of being replaced
    (multiprocessing.Pool respawns dead workers forever); on any error or Ctrl-C the pending work is
    cancelled and the caller records what was finished."""
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool

    ex = ProcessPoolExecutor(n_workers, mp_context=ctx, initializer=_init_worker, initargs=(spec,))
    try:
        chunks = [todo[i:i + chunk] for i in range(0, len(todo), chunk)]
        pending, nxt = set(), 0
        while nxt < len(chunks) or pending:
            while nxt < len(chunks) and len(pending) < 4 * n_workers:  # bounded queue: errors surface early
                pending.add(ex.submit(_make_images, chunks[nxt]))
                nxt += 1
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for fut in done:
                consume(fut.result())
    except BrokenProcessPool as exc:
        how = ("each spawned worker re-imports the main module, so run generate_dataset from a script file whose "
               "top level is guarded by `if __name__ == '__main__':` (not from standard input or a notebook cell "
               "that cannot be re-imported), or use workers=1" if ctx.get_start_method() == "spawn" else
               "see the worker's error above, or use workers=1")
        raise RuntimeError(f"generate_dataset: a worker process died before finishing its images ({exc}); "
                           f"{how}") from exc
    finally:
        ex.shutdown(wait=True, cancel_futures=True)


@contextlib.contextmanager
def _standard_default_start_method(method: str):
    """Inside a process whose default start method is not one of multiprocessing's own (a joblib /
    loky worker, e.g. a job of Hydra's joblib launcher: "loky"), a spawned child fails while it starts
    (it sets its parent's default method, which it does not know). Make ``method`` the default while
    the pool starts its workers, then put the old one back."""
    import multiprocessing as mp

    prev = mp.get_start_method(allow_none=True)
    if prev is None or prev in mp.get_all_start_methods():
        yield
        return
    mp.set_start_method(method, force=True)
    try:
        yield
    finally:
        try:
            mp.set_start_method(prev, force=True)
        except ValueError:
            pass


def _make_image(index: int) -> dict:
    """Compose image ``index``, write its files, return its annotations."""
    spec, cfg, composer = _STATE["spec"], _STATE["cfg"], _STATE["composer"]
    if cfg.distractor_refresh > 0:  # image ``index`` uses pool ``index // refresh``, whichever worker makes it
        block = index // cfg.distractor_refresh
        if block != _STATE["pool_block"]:
            composer.set_distractors(_distractors(spec["seed"], cfg, block, _STATE["color_sources"]))
            _STATE["pool_block"] = block
    scene_id, im_id = divmod(index, cfg.scene_size)
    sd = Path(spec["split_dir"]) / f"{scene_id:06d}"
    sample = composer.compose(image_rng(spec["seed"], index))
    for j, inst in enumerate(sample.instances):
        atomic_write_image(sd / "mask_visib" / f"{im_id:06d}_{j:06d}.png", inst.mask_visib.astype(np.uint8) * 255,
                           png_compression=cfg.png_compression)
    if cfg.depth:
        d = np.clip(np.round(sample.depth / cfg.depth_scale), 0, 65535).astype(np.uint16)
        atomic_write_image(sd / "depth" / f"{im_id:06d}.png", d, png_compression=cfg.png_compression)
    atomic_write_image(sd / "rgb" / f"{im_id:06d}.{cfg.rgb_format}", sample.rgb,
                       png_compression=cfg.png_compression, jpg_quality=cfg.jpg_quality)
    return {
        "index": index, "scene_id": scene_id, "im_id": im_id,
        "gt": [inst.gt() for inst in sample.instances],
        "camera": {"K": sample.K, "depth_scale": cfg.depth_scale},
        "info": [inst.info() for inst in sample.instances],
        "attempts": sample.attempts,
    }


# ---------------------------------------------------------------------------------------------
# main side: scene bookkeeping
# ---------------------------------------------------------------------------------------------
class _SceneRecords:
    """The three scene JSON dicts of one scene folder, loaded from disk on resume."""

    def __init__(self, sd: Path, tag: str | None = None) -> None:
        self.dir = sd
        self.gt: dict[int, list] = {}
        self.cam: dict[int, dict] = {}
        self.info: dict[int, list] = {}
        self.paths = scene_files(sd, tag)
        paths = self.paths
        if all(p.is_file() for p in paths):
            try:
                self.gt = load_scene_gt(paths[0])
                self.cam = load_scene_camera(paths[1])
                self.info = load_scene_gt_info(paths[2])
            except BopFormatError as exc:
                raise BopFormatError(f"cannot resume: {exc} (delete the scene folder {sd} to regenerate it)") from exc
        self.dirty = False

    def complete(self, im_id: int, rgb_ext: str, depth: bool) -> bool:
        if im_id not in self.gt or im_id not in self.cam or im_id not in self.info:
            return False
        if len(self.info[im_id]) != len(self.gt[im_id]):
            return False
        files = [self.dir / "rgb" / f"{im_id:06d}.{rgb_ext}"]
        files += [self.dir / "mask_visib" / f"{im_id:06d}_{j:06d}.png" for j in range(len(self.gt[im_id]))]
        if depth:
            files.append(self.dir / "depth" / f"{im_id:06d}.png")
        return all(f.is_file() for f in files)

    def add(self, rec: dict) -> None:
        im = rec["im_id"]
        self.gt[im] = rec["gt"]
        self.cam[im] = rec["camera"]
        self.info[im] = rec["info"]
        self.dirty = True

    def drop(self, im_id: int) -> None:
        for d in (self.gt, self.cam, self.info):
            d.pop(im_id, None)

    def flush(self) -> None:
        if not self.dirty:
            return
        self.dir.mkdir(parents=True, exist_ok=True)
        save_scene_gt(self.paths[0], self.gt)
        save_scene_camera(self.paths[1], self.cam)
        save_scene_gt_info(self.paths[2], self.info)
        self.dirty = False


def scene_files(sd: Path, tag: str | None = None) -> list[Path]:
    """A scene folder's scene_gt / scene_camera / scene_gt_info files; with a shard ``tag``, that
    shard's partial files (``scene_gt.<tag>.json``, ...)."""
    suffix = f".{tag}.json" if tag else ".json"
    return [sd / f"scene_gt{suffix}", sd / f"scene_camera{suffix}", sd / f"scene_gt_info{suffix}"]


def shard_marker(root: Path, split: str, shard: int, num_shards: int) -> Path:
    """The file a shard writes once all its images are done."""
    return Path(root) / "shards" / split / f"{shard_tag(shard, num_shards)}.json"


def _check_info(root: Path, split: str, models_part: dict, split_part: dict) -> dict:
    """Merge this run's settings into dataset_info.json; refuse to mix different settings."""
    path = root / INFO_FILE
    info = read_json(path, what=INFO_FILE, error=BopFormatError) if path.is_file() else {}
    if info.get("models") not in (None, models_part):
        diff = sorted(k for k in set(models_part) | set(info["models"]) if info["models"].get(k) != models_part.get(k))
        raise ValueError(
            f"{path}: this dataset was generated with different model settings ({', '.join(diff)}: "
            f"{ {k: info['models'].get(k) for k in diff} } vs now { {k: models_part.get(k) for k in diff} }); "
            "use another out_dir or delete it"
        )
    old = info.get("splits", {}).get(split)
    if old is not None and isinstance(old.get("config"), dict) and "photometric" in old["config"]:
        # datasets started from Python before session 9 recorded the photometric defaults as {}
        from kpd6d.synth.config import photometric_settings

        old = {**old, "config": {**old["config"], "photometric": photometric_settings(old["config"]["photometric"])}}
    if old is not None:
        keys = sorted(k for k in set(old) | set(split_part) if k != "num_images" and old.get(k) != split_part.get(k))
        if keys:
            raise ValueError(
                f"{path}: split {split!r} was generated with different settings ({', '.join(keys)}); "
                "resuming would mix them. Use another out_dir or split, or delete the split folder and its entry"
            )
        split_part = dict(split_part, num_images=max(int(old.get("num_images", 0)), split_part["num_images"]))
    import kpd6d

    info = {
        "generator": "kpd6d.synth.generate_dataset",
        "kpd6d_version": kpd6d.__version__,
        "models": models_part,
        "splits": {**info.get("splits", {}), split: split_part},
    }
    atomic_write_json(path, info)
    return info


# ---------------------------------------------------------------------------------------------
# API
# ---------------------------------------------------------------------------------------------
def generate_dataset(out_dir: str | os.PathLike, models_dir: str | os.PathLike | None = None,
                     obj_ids: Sequence[int] | None = None, num_images: int = 1000, split: str = "train",
                     seed: int = 0, workers: int = 1, *, progress: bool = True, shard: int = 0,
                     num_shards: int = 1, **options: Any) -> Path:
    """Write ``num_images`` render-and-paste images of the objects as a BOP dataset under ``out_dir``.

    ``models_dir`` is a BOP models folder (``obj_XXXXXX.ply`` + ``models_info.json``); ``None`` uses
    the procedural objects. ``workers`` processes render in parallel (0 or -1: all cores).
    ``options`` are the fields of :class:`~kpd6d.synth.config.SynthConfig` (conf/generate.yaml).
    Returns the dataset root. Rerunning with the same arguments resumes an interrupted run.

    ``shard`` / ``num_shards``: make only the images ``k`` with ``k % num_shards == shard``, into
    partial scene files, so that ``num_shards`` jobs (any machines sharing the folder) can write the
    split at once; :func:`kpd6d.synth.shards.merge_shards` then writes the final scene files. The
    union is the unsharded dataset byte for byte, whatever ``num_shards``.
    """
    shard, num_shards = check_shard(shard, num_shards)
    cfg = SynthConfig.from_options(options)
    num_images, seed = to_int(num_images, "num_images"), to_int(seed, "seed")
    workers = None if workers is None else to_int(workers, "workers")
    if num_images < 0:
        raise ValueError(f"num_images must be >= 0, got {num_images}")
    if not split or "/" in split or split in (".", ".."):
        raise ValueError(f"split must be a plain folder name, got {split!r}")
    root = Path(out_dir)
    root.mkdir(parents=True, exist_ok=True)
    if models_dir is not None and not Path(models_dir).is_dir():
        raise FileNotFoundError(f"models_dir {models_dir}: folder does not exist")
    ids = None if obj_ids is None else sorted(int(o) for o in obj_ids)
    models_part = {
        "source": "procedural" if models_dir is None else str(Path(models_dir).resolve()),
        "obj_ids": ids,
        "procedural_seed": cfg.procedural_seed if models_dir is None else None,
        "designator": cfg.designator,
    }
    split_part = {"seed": int(seed), "num_images": num_images, "config": cfg.to_dict()}
    split_part["config"].pop("mp_start_method")
    split_part["config"].pop("flush_interval_s")
    _check_info(root, split, models_part, split_part)
    sharded = num_shards > 1
    ids = _write_models(root, None if models_dir is None else Path(models_dir), ids, cfg, sharded=sharded,
                        designate=shard == 0)
    K = cfg.camera_K()
    if not (root / "camera.json").is_file():
        save_camera(root / "camera.json", K, cfg.width, cfg.height, cfg.depth_scale)

    split_dir = root / split
    tag = shard_tag(shard, num_shards) if sharded else None
    marker = shard_marker(root, split, shard, num_shards) if sharded else None
    mine = [k for k in range(num_images) if shard_of(k, num_shards) == shard]
    scenes: dict[int, _SceneRecords] = {}
    todo: list[int] = []
    for index in mine:
        scene_id, im_id = divmod(index, cfg.scene_size)
        if scene_id not in scenes:
            sd = split_dir / f"{scene_id:06d}"
            for sub in ("", "rgb", "mask_visib", "depth"):
                _remove_stale_tmp(sd / sub, _owned_by(scene_id, cfg.scene_size, shard, num_shards, tag, sub == ""))
            scenes[scene_id] = _SceneRecords(sd, tag)
        rec = scenes[scene_id]
        if not rec.complete(im_id, cfg.rgb_format, cfg.depth):
            rec.drop(im_id)
            todo.append(index)
    if not todo:
        if marker is not None:
            _write_marker(marker, shard, num_shards, split, models_part, split_part, len(mine))
        return root
    if marker is not None and marker.is_file():
        marker.unlink()  # this shard is not finished until the marker is written again

    spec = {
        "root": str(root), "split_dir": str(split_dir), "obj_ids": ids, "seed": int(seed),
        "config": {k: v for k, v in cfg.to_dict().items()},
    }
    n_workers = min(resolve_workers(workers), len(todo))
    bar = None
    if progress:
        from tqdm.auto import tqdm

        desc = f"generate {split}" + (f" ({tag})" if tag else "")
        bar = tqdm(total=len(mine), initial=len(mine) - len(todo), desc=desc, unit="img")
    last_flush = time.monotonic()

    def consume(results):
        nonlocal last_flush
        for rec in results:
            scenes[rec["scene_id"]].add(rec)
            if bar is not None:
                bar.update(1)
            if time.monotonic() - last_flush > cfg.flush_interval_s:
                for s in scenes.values():
                    s.flush()
                last_flush = time.monotonic()

    try:
        if n_workers == 1:
            _init_worker(spec)
            try:
                consume(_make_image(i) for i in todo)
            finally:
                _STATE["renderer"].close()
                _STATE.clear()
        else:
            import multiprocessing as mp

            ctx = mp.get_context(cfg.mp_start_method)
            spec["single_thread_gl"] = True
            chunk = max(1, min(8, len(todo) // (4 * n_workers)))
            with _standard_default_start_method(ctx.get_start_method()):
                _run_pool(ctx, n_workers, spec, todo, chunk, consume)
    finally:  # also on errors / Ctrl-C: record every image finished so far, so a rerun resumes
        for s in scenes.values():
            s.flush()
        if bar is not None:
            bar.close()
    if marker is not None:
        _write_marker(marker, shard, num_shards, split, models_part, split_part, len(mine))
    return root


def _owned_by(scene_id: int, scene_size: int, shard: int, num_shards: int, tag: str | None,
              scene_dir: bool) -> Callable[[str], bool] | None:
    """Which temporary files in a scene (sub)folder are the shard's own (None: unsharded, all)."""
    if tag is None:
        return None
    if scene_dir:  # the scene JSON files: the shard's partial files only
        return lambda name: f".{tag}." in name

    def owned(name: str) -> bool:  # rgb/000007.jpg, mask_visib/000007_000001.png, depth/000007.png
        head = name[:6]
        return head.isdigit() and shard_of(scene_id * scene_size + int(head), num_shards) == shard

    return owned


def _write_marker(path: Path, shard: int, num_shards: int, split: str, models_part: dict, split_part: dict,
                  n_images: int) -> None:
    atomic_write_json(path, {"shard": shard, "num_shards": num_shards, "split": split, "images": n_images,
                             "num_images": split_part["num_images"], "seed": split_part["seed"],
                             "config": split_part["config"], "models": models_part})
