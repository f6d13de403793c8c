"""BOP results CSV reading / writing."""

from __future__ import annotations

import numpy as np
import pytest

from kpd6d.evaluation.results_io import PoseResult, ResultsFormatError, read_bop_results, write_bop_results
from kpd6d.geometry import random_rotation


def test_roundtrip_exact(tmp_path):
    rng = np.random.default_rng(0)
    res = [PoseResult(2, i, 5 + i, float(rng.random()), random_rotation(rng), rng.normal(size=3) * 500, 0.25)
           for i in range(4)]
    path = write_bop_results(tmp_path / "sub" / "r.csv", res)
    back = read_bop_results(path)
    assert len(back) == 4
    for a, b in zip(res, back):
        assert (a.scene_id, a.im_id, a.obj_id, a.score, a.time) == (b.scene_id, b.im_id, b.obj_id, b.score, b.time)
        np.testing.assert_array_equal(a.R, b.R)  # repr() round-trips floats exactly
        np.testing.assert_array_equal(a.t, b.t)
    assert path.read_text().splitlines()[0] == "scene_id,im_id,obj_id,score,R,t,time"
    assert not list((tmp_path / "sub").glob("*.tmp"))


def test_reads_official_format_without_time(tmp_path):
    p = tmp_path / "r.csv"
    p.write_text("scene_id,im_id,obj_id,score,R,t\n1,3,8,0.5,1 0 0 0 1 0 0 0 1,10 20 30\n")
    (r,) = read_bop_results(p)
    assert (r.scene_id, r.im_id, r.obj_id, r.score, r.time) == (1, 3, 8, 0.5, -1.0)
    np.testing.assert_array_equal(r.R, np.eye(3))
    np.testing.assert_array_equal(r.t, [10, 20, 30])


@pytest.mark.parametrize(
    ("body", "needle"),
    [
        ("1,3,8,0.5,1 0 0 0 1 0 0 0,10 20 30,1\n", "field 'R' has 8 values"),
        ("1,3,x,0.5,1 0 0 0 1 0 0 0 1,10 20 30,1\n", "field 'obj_id' is not an integer"),
        ("1,3,8,0.5,1 0 0 0 1 0 0 0 1,10 nan 30,1\n", "field 't' has non-finite"),
        ("1,3,8,0.5,1 0 0 0 1 0 0 0 1\n", "fields, expected 7"),
    ],
)
def test_bad_lines_name_file_line_and_field(tmp_path, body, needle):
    p = tmp_path / "bad.csv"
    p.write_text("scene_id,im_id,obj_id,score,R,t,time\n" + body)
    with pytest.raises(ResultsFormatError, match=needle) as ei:
        read_bop_results(p)
    assert f"{p}:2" in str(ei.value)


def test_bad_header_and_missing_file(tmp_path):
    p = tmp_path / "h.csv"
    p.write_text("a,b,c\n")
    with pytest.raises(ResultsFormatError, match="unexpected header"):
        read_bop_results(p)
    with pytest.raises(ResultsFormatError, match="does not exist"):
        read_bop_results(tmp_path / "nope.csv")


def test_reads_official_megapose_file(shared_data):
    path = next((shared_data / "bop_reference").glob("cnos-fastsammegapose_lmo-test_*.csv"))
    res = read_bop_results(path)
    assert len(res) == sum(1 for _ in path.open()) - 1
    R = np.stack([r.R for r in res])
    # official rotations are orthonormal to float32 precision
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-5)
