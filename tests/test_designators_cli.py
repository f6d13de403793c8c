"""kpd6d-designate and the cached batch designation behind it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from kpd6d.keypoints import load_keypoints, read_keypoint_file
from kpd6d.keypoints.designate import designate_objects, render_overview
from kpd6d.objects import procedural_objects


def test_cache_reuse_and_invalidation(tmp_path, monkeypatch):
    models = procedural_objects(obj_ids=[1, 3])
    cache = tmp_path / "kp.json"
    params = {"num_keypoints": 6, "num_surface_samples": 800}
    pts, reused = designate_objects(models, "fps", params, cache, progress=False)
    assert reused == [] and sorted(pts) == [1, 3] and pts[1].shape == (6, 3)
    f = read_keypoint_file(cache)
    assert f.designator == "fps" and f.params["num_keypoints"] == 6 and f.params["num_surface_samples"] == 800
    # same designator and parameters: everything from the cache, nothing recomputed
    from kpd6d.keypoints import designators

    calls = []
    real = designators.FpsDesignator.__call__
    monkeypatch.setattr(designators.FpsDesignator, "__call__", lambda self, m: calls.append(m.obj_id) or real(self, m))
    pts2, reused = designate_objects(models, "fps", dict(params), cache, progress=False)
    assert reused == [1, 3] and calls == []
    assert all(np.array_equal(pts[k], pts2[k]) for k in pts)
    # a changed mesh (fingerprint) recomputes only that object
    models[1].mesh.apply_translation([1.0, 0.0, 0.0])
    _, reused = designate_objects(models, "fps", dict(params), cache, progress=False)
    assert reused == [1] and calls == [3]
    # other parameters: all recomputed and the file now says so
    _, reused = designate_objects(models, "fps", {**params, "num_keypoints": 4}, cache, progress=False)
    assert reused == [] and load_keypoints(cache)[1].shape == (4, 3)


def test_resume_after_interruption(tmp_path, monkeypatch):
    models = procedural_objects(obj_ids=[1, 2, 3])
    cache = tmp_path / "kp.json"
    from kpd6d.keypoints import designators

    real = designators.FpsDesignator.__call__

    def flaky(self, m):
        if m.obj_id == 3:
            raise KeyboardInterrupt
        return real(self, m)

    monkeypatch.setattr(designators.FpsDesignator, "__call__", flaky)
    with pytest.raises(KeyboardInterrupt):
        designate_objects(models, "fps", {"num_keypoints": 5}, cache, progress=False)
    assert sorted(load_keypoints(cache)) == [1, 2]  # written as they were done
    monkeypatch.setattr(designators.FpsDesignator, "__call__", real)
    _, reused = designate_objects(models, "fps", {"num_keypoints": 5}, cache, progress=False)
    assert reused == [1, 2]
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_per_object_overrides_and_reuse_by_id_without_fingerprints(tmp_path):
    models = procedural_objects(obj_ids=[1, 3])
    cache = tmp_path / "kp.json"
    pts, _ = designate_objects(models, "fps", {"num_keypoints": 6}, cache, per_object={3: {"num_keypoints": 4}},
                               fingerprints=False, progress=False)
    assert pts[1].shape == (6, 3) and pts[3].shape == (4, 3)
    f = read_keypoint_file(cache)
    assert f.params == {"num_keypoints": 6, "per_object": {"3": {"num_keypoints": 4}}} and f.fingerprints == {}
    # without fingerprints a changed mesh does not invalidate its cached keypoints
    models[1].mesh.apply_translation([1.0, 0.0, 0.0])
    _, reused = designate_objects(models, "fps", {"num_keypoints": 6}, cache, per_object={3: {"num_keypoints": 4}},
                                  fingerprints=False, progress=False)
    assert reused == [1, 3]
    # other overrides are other parameters: all recomputed
    _, reused = designate_objects(models, "fps", {"num_keypoints": 6}, cache, per_object={3: {"num_keypoints": 5}},
                                  fingerprints=False, progress=False)
    assert reused == [] and load_keypoints(cache)[3].shape == (5, 3)


def test_unknown_designator_and_parameter(tmp_path):
    from kpd6d.registry import UnknownNameError

    with pytest.raises(UnknownNameError, match="known designators"):
        designate_objects(procedural_objects(obj_ids=[1]), "surf", {}, tmp_path / "kp.json", progress=False)
    with pytest.raises(TypeError, match="unknown parameter"):
        designate_objects(procedural_objects(obj_ids=[1]), "fps", {"k": 3}, tmp_path / "kp.json", progress=False)


def test_overview_marks_visible_and_far_side():
    m = procedural_objects(obj_ids=[3])[0]
    lo, hi = m.mesh.bounds
    # two points at opposite ends along x: from views around the object one of them is hidden at times
    pts = np.array([[lo[0] + 1e-3, 0.0, 0.0], [hi[0] - 1e-3, -15.0, 0.0]])
    pts = m.mesh.nearest.on_surface(pts)[0]
    img = render_overview(m, pts, num_views=4, image_size=160)
    assert img.shape == (320, 320, 3)
    green = (img[..., 1] == 255) & (img[..., 0] == 40)
    red = (img[..., 0] == 255) & (img[..., 1] == 60)
    assert green.sum() > 0 and red.sum() > 0


def test_console_script_end_to_end(tmp_path):
    exe = Path(sys.executable).with_name("kpd6d-designate")
    cmd = [str(exe), f"out_dir={tmp_path}", "designator=fps", "designator.num_keypoints=7", "obj_ids=[2,6]",
           "overview.num_views=2", "overview.image_size=128", "progress=false", f"hydra.run.dir={tmp_path / 'hydra'}"]
    env = {**os.environ, "PYOPENGL_PLATFORM": "egl"}
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "2 object(s) (0 from the cache)" in out.stdout
    doc = json.loads((tmp_path / "keypoints.json").read_text())
    assert doc["designator"] == "fps" and sorted(doc["objects"]) == ["2", "6"]
    for oid in (2, 6):
        png = cv2.imread(str(tmp_path / f"obj_{oid:06d}.png"))
        assert png is not None and png.shape == (128, 256, 3)
    again = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert again.returncode == 0 and "2 object(s) (2 from the cache)" in again.stdout
    bad = subprocess.run([str(exe), f"out_dir={tmp_path}", "designator=nope", f"hydra.run.dir={tmp_path / 'h2'}"],
                         capture_output=True, text=True, env=env, timeout=300)
    assert bad.returncode != 0 and "nope" in bad.stderr
