"""``merge_shards``: check the shards of a split generated with ``generate_dataset(..., shard=i,
num_shards=n)`` and write its final scene files.

Image ``k`` of a split belongs to shard ``k % n`` (:func:`kpd6d.synth.generate.shard_of`). Each shard
writes its images' files and its own partial scene files (``scene_gt.shard-i-of-n.json``,
``scene_camera.shard-i-of-n.json``, ``scene_gt_info.shard-i-of-n.json``), then the marker
``<root>/shards/<split>/shard-i-of-n.json`` (its settings). The merge refuses, naming the image
and the shard, anything but a complete and consistent union: every shard finished (marker present),
with the same settings as the others and as ``dataset_info.json``; every image id ``0..N-1``
recorded by exactly one shard, its own; its rgb, mask_visib (and depth) files present. It then
writes ``scene_gt.json``, ``scene_camera.json`` and ``scene_gt_info.json`` of every scene
(atomically), the bytes the unsharded run writes. The shards' partial files and markers stay (they
are small), so rerunning a shard or the merge is harmless.
"""

from __future__ import annotations

import os
from pathlib import Path

from kpd6d.config import to_int
from kpd6d.data.bop_io import (
    BopFormatError,
    load_scene_camera,
    load_scene_gt,
    load_scene_gt_info,
    save_scene_camera,
    save_scene_gt,
    save_scene_gt_info,
)
from kpd6d.io import read_json
from kpd6d.synth.generate import INFO_FILE, _remove_stale_tmp, scene_files, shard_marker, shard_of, shard_tag

__all__ = ["ShardMergeError", "merge_shards"]

MAX_LISTED = 20  # problems listed in one error message


class ShardMergeError(ValueError):
    """The shards of a split do not make a complete, consistent dataset; the message lists each
    problem with the image id and the shard."""


def _where(k: int, scene_size: int) -> str:
    s, i = divmod(k, scene_size)
    return f"image {k} (scene {s:06d}, im_id {i})"


def merge_shards(root: str | os.PathLike, split: str = "train", num_shards: int = 2) -> dict:
    """Check the ``num_shards`` shards of ``split`` under ``root`` and write the final scene files.

    Returns ``{"num_images", "num_shards", "scenes"}``; raises :class:`ShardMergeError` listing the
    problems (an unfinished shard, other settings, a missing, duplicated or misplaced image, a
    missing image file) and writes nothing then.
    """
    root = Path(root)
    num_shards = to_int(num_shards, "num_shards")
    if num_shards < 2:
        raise ValueError(f"merge_shards: num_shards must be >= 2 (the number of shards the split was generated in), "
                         f"got {num_shards}")
    if not (root / INFO_FILE).is_file():
        raise FileNotFoundError(f"merge_shards: {root / INFO_FILE} does not exist; is {root} a generated dataset?")
    info = read_json(root / INFO_FILE, what=INFO_FILE, error=BopFormatError)
    ref_split = (info.get("splits") or {}).get(split)
    if ref_split is None:
        raise ShardMergeError(f"{root / INFO_FILE}: no split {split!r} (splits: {sorted(info.get('splits') or {})})")

    # 1. every shard finished, all with the same settings
    problems: list[str] = []
    markers = {}
    for i in range(num_shards):
        path = shard_marker(root, split, i, num_shards)
        if not path.is_file():
            problems.append(f"shard {i} of {num_shards} has not finished: {path} does not exist (rerun it with "
                            f"shard={i} num_shards={num_shards} and the same settings; it resumes)")
            continue
        markers[i] = read_json(path, what="shard marker", error=BopFormatError)
    for i, m in markers.items():
        diff = [k for k in ("seed", "config") if m.get(k) != ref_split.get(k)]
        diff += ["models"] if m.get("models") != info.get("models") else []
        if diff:
            problems.append(f"shard {i} of {num_shards} was generated with other settings ({', '.join(diff)}) than "
                            f"{root / INFO_FILE} records for split {split!r}")
    counts = {i: m.get("num_images") for i, m in markers.items()}
    if len(set(counts.values())) > 1:
        problems.append("the shards were generated with different num_images: "
                        + ", ".join(f"shard {i}: {n}" for i, n in sorted(counts.items())))
    if problems:
        raise ShardMergeError(_message(root, split, problems))

    cfg = ref_split["config"]
    num_images = int(next(iter(counts.values())))
    scene_size, rgb_ext, depth = int(cfg["scene_size"]), cfg["rgb_format"], bool(cfg["depth"])
    n_scenes = -(-num_images // scene_size)

    # 2. every image recorded by exactly one shard, its own, with its files
    split_dir = root / split
    merged = []
    for scene_id in range(n_scenes):
        sd = split_dir / f"{scene_id:06d}"
        gt, cam, gi, owner = {}, {}, {}, {}
        for i in range(num_shards):
            paths = scene_files(sd, shard_tag(i, num_shards))
            if not any(p.is_file() for p in paths):
                continue
            missing = [p.name for p in paths if not p.is_file()]
            if missing:
                problems.append(f"shard {i}: scene {scene_id:06d} lacks {', '.join(missing)} beside its other "
                                "partial files")
                continue
            sg, sc, si = load_scene_gt(paths[0]), load_scene_camera(paths[1]), load_scene_gt_info(paths[2])
            for im_id in sorted(set(sg) | set(sc) | set(si)):
                k = scene_id * scene_size + im_id
                if not (im_id in sg and im_id in sc and im_id in si) or len(sg[im_id]) != len(si[im_id]):
                    problems.append(f"{_where(k, scene_size)}: shard {i}'s partial scene files disagree about it "
                                    f"(rerun shard {i}; it remakes the image)")
                    continue
                if k >= num_images:
                    problems.append(f"{_where(k, scene_size)} is recorded by shard {i}, but the split has "
                                    f"{num_images} images (0..{num_images - 1})")
                    continue
                if im_id in owner:
                    problems.append(f"{_where(k, scene_size)} is duplicated: recorded by shard {owner[im_id]} and "
                                    f"by shard {i} (it belongs to shard {shard_of(k, num_shards)})")
                    continue
                if shard_of(k, num_shards) != i:
                    problems.append(f"{_where(k, scene_size)} is recorded by shard {i}, but belongs to shard "
                                    f"{shard_of(k, num_shards)} of {num_shards}")
                owner[im_id] = i
                gt[im_id], cam[im_id], gi[im_id] = sg[im_id], sc[im_id], si[im_id]
        for k in range(scene_id * scene_size, min(num_images, (scene_id + 1) * scene_size)):
            im_id = k - scene_id * scene_size
            if im_id not in owner:
                j = shard_of(k, num_shards)
                problems.append(f"{_where(k, scene_size)} is missing: shard {j} of {num_shards} did not record it "
                                f"(rerun shard {j}; it resumes)")
                continue
            files = [sd / "rgb" / f"{im_id:06d}.{rgb_ext}"]
            files += [sd / "mask_visib" / f"{im_id:06d}_{g:06d}.png" for g in range(len(gt[im_id]))]
            if depth:
                files.append(sd / "depth" / f"{im_id:06d}.png")
            for f in files:
                if not f.is_file():
                    problems.append(f"{_where(k, scene_size)} (shard {owner[im_id]}): {f} is missing "
                                    f"(rerun shard {owner[im_id]}; it remakes the image)")
        merged.append((sd, gt, cam, gi))
    designator = (info.get("models") or {}).get("designator")
    if designator is not None and not (root / "models" / "keypoints.json").is_file():
        problems.append(f"{root / 'models' / 'keypoints.json'} is missing (shard 0 designates the keypoints; "
                        "rerun shard 0)")
    if problems:
        raise ShardMergeError(_message(root, split, problems))

    # 3. the final scene files, as the unsharded run writes them
    for sd, gt, cam, gi in merged:
        final = scene_files(sd)
        save_scene_gt(final[0], gt)
        save_scene_camera(final[1], cam)
        save_scene_gt_info(final[2], gi)
    _remove_stale_tmp(root / "models")  # every shard has finished: what is left is debris
    return {"num_images": num_images, "num_shards": num_shards, "scenes": n_scenes}


def _message(root: Path, split: str, problems: list[str]) -> str:
    head = f"merge_shards: {root}/{split} cannot be merged ({len(problems)} problem{'s' * (len(problems) > 1)}):"
    lines = [f"  - {p}" for p in problems[:MAX_LISTED]]
    if len(problems) > MAX_LISTED:
        lines.append(f"  ... and {len(problems) - MAX_LISTED} more")
    return "\n".join([head, *lines])
