"""Sharded generation (``generate_dataset(..., shard=i, num_shards=n)`` + ``merge_shards``) and sharded
evaluation (``evaluate(..., shard=i, num_shards=n)`` + ``merge=True``): the union is the single job's
result, byte for byte; a killed shard resumes; the merges name a missing or duplicated image / frame."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from kpd6d.synth import ShardMergeError, generate_dataset, merge_shards
from synth_helpers import SMALL, tree_bytes, write_models

# 7 images in scenes of 4: scene 0 (images 0-3) and scene 1 (images 4-6); in 3 shards every shard
# writes into both scenes
_RUN = dict(num_images=7, seed=5, progress=False, distractors=(1, 1), scene_size=4, objects_per_image=(1, 2),
            **{**SMALL, "width": 64, "height": 48, "distance_range": (350.0, 600.0), "designator": {
                "name": "bbox_corners"}})
N = 3


def _dataset_files(root: Path) -> dict[str, bytes]:
    """The dataset's files, without the shards' own (partial scene files and markers)."""
    return {k: v for k, v in tree_bytes(root).items() if ".shard-" not in k and not k.startswith("shards/")}


@pytest.fixture(scope="module")
def models_dir(tmp_path_factory) -> Path:
    return write_models(tmp_path_factory.mktemp("models"))


@pytest.fixture(scope="module")
def reference(tmp_path_factory, models_dir) -> dict[str, bytes]:
    root = tmp_path_factory.mktemp("one")
    generate_dataset(root, models_dir, **_RUN)
    return tree_bytes(root)


def _shards(root, models_dir, shards=range(N), **kw):
    for i in shards:
        generate_dataset(root, models_dir, shard=i, num_shards=N, **{**_RUN, **kw})


def test_three_shards_merged_are_the_single_run_byte_for_byte(tmp_path, models_dir, reference):
    root = tmp_path / "sharded"
    _shards(root, models_dir)
    # before the merge: no final scene files, only the shards' own
    assert not list(root.glob("train/*/scene_gt.json"))
    assert sorted(p.name for p in (root / "train" / "000000").glob("scene_gt.*.json")) == [
        f"scene_gt.shard-{i}-of-3.json" for i in range(N)]
    assert sorted(p.name for p in (root / "shards" / "train").iterdir()) == [f"shard-{i}-of-3.json" for i in range(N)]
    info = merge_shards(root, "train", N)
    assert info == {"num_images": 7, "num_shards": 3, "scenes": 2}
    got = _dataset_files(root)
    assert set(got) == set(reference)
    for name in reference:  # annotations, rgb, masks, models/, keypoints.json, camera.json, dataset_info.json
        assert got[name] == reference[name], name
    assert any(n.endswith("scene_gt_info.json") for n in got) and any("mask_visib" in n for n in got)
    assert "models/keypoints.json" in got
    assert not list(root.rglob("*.tmp"))
    merge_shards(root, "train", N)  # merging again changes nothing
    assert _dataset_files(root) == got


def test_a_killed_shard_resumes(tmp_path, models_dir, reference, monkeypatch):
    import kpd6d.synth.generate as gen

    root = tmp_path / "k"
    _shards(root, models_dir, shards=[0, 2])
    real = gen._make_image
    calls = {"n": 0}

    def killed(index):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt  # shard 1 (images 1, 4) dies after its first image
        return real(index)

    monkeypatch.setattr(gen, "_make_image", killed)
    with pytest.raises(KeyboardInterrupt):
        _shards(root, models_dir, shards=[1])
    monkeypatch.setattr(gen, "_make_image", real)
    assert json.loads((root / "train/000000/scene_gt.shard-1-of-3.json").read_text()).keys() == {"1"}
    assert not (root / "shards/train/shard-1-of-3.json").exists()  # not finished
    with pytest.raises(ShardMergeError, match=r"shard 1 of 3 has not finished"):
        merge_shards(root, "train", N)
    # debris of the killed writer of shard 1; a temporary file of shard 0 (still running elsewhere) stays
    (root / "train/000001/rgb/.000000.jpg.abc.tmp").write_bytes(b"half-written")  # image 4: shard 1
    (root / "train/000001/rgb/.000001.jpg.def.tmp").write_bytes(b"in flight")  # image 5: shard 2
    made = []
    monkeypatch.setattr(gen, "_make_image", lambda i: made.append(i) or real(i))
    _shards(root, models_dir, shards=[1])
    assert made == [4]  # only the image it had not finished
    assert not (root / "train/000001/rgb/.000000.jpg.abc.tmp").exists()
    assert (root / "train/000001/rgb/.000001.jpg.def.tmp").exists()
    (root / "train/000001/rgb/.000001.jpg.def.tmp").unlink()
    # a lost image file of shard 2 is remade by rerunning shard 2
    (root / "train/000000/rgb/000002.jpg").unlink()
    with pytest.raises(ShardMergeError, match=r"image 2 \(scene 000000, im_id 2\) \(shard 2\).*000002.jpg is missing"):
        merge_shards(root, "train", N)
    made.clear()
    _shards(root, models_dir, shards=[2])
    assert made == [2]
    merge_shards(root, "train", N)
    got = _dataset_files(root)
    assert all(got[name] == reference[name] for name in reference) and set(got) == set(reference)


def test_merge_names_a_missing_and_a_duplicated_image(tmp_path, models_dir):
    root = tmp_path / "m"
    _shards(root, models_dir)
    sd = root / "train" / "000001"
    p1, p2 = sd / "scene_gt.shard-1-of-3.json", sd / "scene_gt.shard-2-of-3.json"
    gt1, gt2 = json.loads(p1.read_text()), json.loads(p2.read_text())
    assert sorted(gt1) == ["0"] and sorted(gt2) == ["1"]  # images 4 (shard 1) and 5 (shard 2)
    # image 4 lost from shard 1's records
    for name in ("scene_gt", "scene_camera", "scene_gt_info"):
        f = sd / f"{name}.shard-1-of-3.json"
        d = json.loads(f.read_text())
        keep = d.pop("0")
        f.write_text(json.dumps(d))
        # ... and image 5 recorded by shard 1 as well (a copy of shard 2's)
        g = json.loads((sd / f"{name}.shard-2-of-3.json").read_text())
        f.write_text(json.dumps({**d, "1": g["1"]}))
        assert keep
    with pytest.raises(ShardMergeError) as err:
        merge_shards(root, "train", N)
    msg = str(err.value)
    assert "image 4 (scene 000001, im_id 0) is missing: shard 1 of 3 did not record it" in msg
    assert "image 5 (scene 000001, im_id 1) is duplicated: recorded by shard 1 and by shard 2" in msg
    assert "image 5 (scene 000001, im_id 1) is recorded by shard 1, but belongs to shard 2 of 3" in msg
    assert not list(root.glob("train/*/scene_gt.json"))  # nothing written


def test_merge_refuses_shards_with_other_settings_or_counts(tmp_path, models_dir):
    root = tmp_path / "s"
    _shards(root, models_dir)
    m = root / "shards/train/shard-2-of-3.json"
    d = json.loads(m.read_text())
    m.write_text(json.dumps({**d, "seed": 99}))
    with pytest.raises(ShardMergeError, match=r"shard 2 of 3 was generated with other settings \(seed\)"):
        merge_shards(root, "train", N)
    m.write_text(json.dumps({**d, "num_images": 8}))
    with pytest.raises(ShardMergeError, match=r"different num_images: shard 0: 7, shard 1: 7, shard 2: 8"):
        merge_shards(root, "train", N)
    with pytest.raises(ValueError, match="shard must be in 0..num_shards-1"):
        generate_dataset(root, models_dir, shard=3, num_shards=3, **_RUN)
    # a different shard count does not see these shards
    with pytest.raises(ShardMergeError, match="shard 0 of 2 has not finished"):
        merge_shards(root, "train", 2)
