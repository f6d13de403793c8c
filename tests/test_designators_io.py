"""Keypoint JSON I/O: round trip, provenance, atomic writes and clear errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from kpd6d.keypoints import (
    KeypointFileError,
    load_keypoints,
    model_fingerprint,
    read_keypoint_file,
    save_keypoints,
)
from kpd6d.objects import procedural_objects


def test_round_trip_with_provenance(tmp_path):
    rng = np.random.default_rng(0)
    kps = {3: rng.normal(size=(9, 3)) * 50, 1: rng.normal(size=(50, 3)) * 80}
    m = procedural_objects(obj_ids=[1])[0]
    path = save_keypoints(tmp_path / "sub" / "keypoints.json", kps, designator="sift",
                          params={"num_keypoints": 50, "views": np.int64(60), "size": (256, 256)},
                          fingerprints={1: model_fingerprint(m)})
    assert path.is_file() and [p.name for p in path.parent.iterdir()] == ["keypoints.json"]  # no temp left
    loaded = load_keypoints(path)
    assert sorted(loaded) == [1, 3]
    for k in kps:
        assert np.array_equal(loaded[k], kps[k])  # JSON floats round-trip exactly
    f = read_keypoint_file(path)
    assert f.designator == "sift" and f.params == {"num_keypoints": 50, "views": 60, "size": [256, 256]}
    assert f.fingerprints == {1: model_fingerprint(m)}
    doc = json.loads(path.read_text())
    assert doc["format"] == "kpd6d-keypoints" and doc["objects"]["3"]["points"][0] == kps[3][0].tolist()


def test_fingerprint_changes_with_mesh():
    a, b = procedural_objects(obj_ids=[1, 2])
    assert model_fingerprint(a) == model_fingerprint(procedural_objects(obj_ids=[1])[0])
    assert model_fingerprint(a) != model_fingerprint(b)
    a.mesh.apply_translation([0.01, 0, 0])
    assert model_fingerprint(a) != model_fingerprint(procedural_objects(obj_ids=[1])[0])


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("{not json", "invalid JSON"),
        ('{"designator": "fps"}', "missing field 'objects'"),
        ('{"format": "other", "objects": {}}', "field 'format' is 'other'"),
        ('{"objects": {"a": {"points": [[0, 0, 0]]}}}', "object id 'a'"),
        ('{"objects": {"1": {"pts": [[0, 0, 0]]}}}', "objects.1 has no field 'points'"),
        ('{"objects": {"1": {"points": [[0, 0]]}}}', r"objects.1.points must have shape \(k, 3\), got \(1, 2\)"),
        ('{"objects": {"2": {"points": [["x", 0, 0]]}}}', "objects.2.points is not a list of numbers"),
        ('{"objects": {"1": {"points": [[0, 0, 0]]}}, "params": [1]}', "field 'params' must be an object"),
    ],
)
def test_read_errors_name_file_and_field(tmp_path, content, message):
    p = tmp_path / "kp.json"
    p.write_text(content)
    with pytest.raises(KeypointFileError, match=message) as ei:
        load_keypoints(p)
    assert str(p) in str(ei.value)


def test_missing_file_and_bad_save(tmp_path):
    with pytest.raises(KeypointFileError, match="does not exist"):
        load_keypoints(tmp_path / "nope.json")
    with pytest.raises(KeypointFileError, match=r"object 4 must have shape \(k, 3\)"):
        save_keypoints(tmp_path / "kp.json", {4: np.zeros((5, 2))})
    with pytest.raises(KeypointFileError, match="NaN"):
        save_keypoints(tmp_path / "kp.json", {4: np.full((5, 3), np.nan)})
    with pytest.raises(TypeError, match="params must be JSON values"):
        save_keypoints(tmp_path / "kp.json", {4: np.zeros((5, 3))}, params={"x": object()})
    assert not any(tmp_path.iterdir())  # nothing half-written
