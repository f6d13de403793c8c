"""``kpd6d-benchmark generate``: it measures the scenes it says it measures."""

from __future__ import annotations

import json
import re

import pytest

from kpd6d.benchmarks.generate import experiment_options, main


def _scene_gt(root):
    (scene,) = sorted((root / "train").iterdir())
    return json.loads((scene / "scene_gt.json").read_text())


def test_default_scenes_hold_one_object(tmp_path, capsys):
    out = tmp_path / "gen"
    assert main(["--num-images", "2", "--workers", "1", "--width", "160", "--height", "120", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "2 images 160x120, 1 object + 1 occluder(s)" in printed and "images/s" in printed
    gt = _scene_gt(out)
    assert len(gt) == 2 and all(len(v) == 1 for v in gt.values())


def test_profile_breaks_the_render_time_into_passes(tmp_path, capsys):
    assert main(["--num-images", "1", "--workers", "1", "--width", "160", "--height", "120", "--profile", "3"]) == 0
    printed = capsys.readouterr().out
    assert "profile, one process, 3 images" in printed
    # one target + one occluder: a colour pass of both and a segmentation pass of the target per image
    assert re.search(r"colour passes +[0-9.]+ ms +\(1\.00 per image", printed), printed
    assert re.search(r"segmentation passes +[0-9.]+ ms +\([1-9][0-9.]* per image", printed), printed


def test_experiment_options_are_the_recipes():
    opts, ids = experiment_options("lmo", "/any/models")  # composing does not read the models
    assert ids == [1, 5, 6, 8, 9, 10, 11, 12]
    assert opts["layout"] == "tabletop" and list(opts["objects_per_image"]) == [3, 8]
    with pytest.raises(Exception, match="nonexistent"):
        experiment_options("nonexistent", None)


@pytest.mark.lmo
@pytest.mark.slow
def test_experiment_lmo_measures_table_top_scenes_of_the_recipes_objects(tmp_path, capsys, lmo_dir):
    out = tmp_path / "gen"
    assert main(["--experiment", "lmo", "--models-dir", str(lmo_dir / "models"), "--num-images", "2",
                 "--workers", "1", "--width", "160", "--height", "120", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "experiment=lmo (tabletop layout" in printed and "8 object models" in printed
    info = json.loads((out / "dataset_info.json").read_text())
    assert info["splits"]["train"]["config"]["layout"] == "tabletop"
    gt = _scene_gt(out)
    # 3-8 of the recipe's objects per image (objects_per_image [3, 8]), each at most once
    for insts in gt.values():
        ids = [g["obj_id"] for g in insts]
        assert 3 <= len(ids) <= 8 and len(set(ids)) == len(ids) and set(ids) <= {1, 5, 6, 8, 9, 10, 11, 12}
