"""kpd6d.io, the leaf file-I/O module: JSON errors, BOP errors as a kind of them, plain values."""

import numpy as np
import pytest
from omegaconf import OmegaConf

from kpd6d.data import BopFormatError, load_scene_gt
from kpd6d.io import FileFormatError, atomic_write_json, atomic_write_text, read_json, to_plain


def test_read_json_errors_name_the_file(tmp_path):
    with pytest.raises(FileFormatError, match=r"nope.json: settings file does not exist"):
        read_json(tmp_path / "nope.json", what="settings file")
    atomic_write_text(tmp_path / "bad.json", "{1:")
    with pytest.raises(FileFormatError, match=r"bad.json: invalid JSON"):
        read_json(tmp_path / "bad.json")
    with pytest.raises(KeyError, match=r"bad\.json"):
        read_json(tmp_path / "bad.json", error=KeyError)


def test_bop_errors_are_file_format_errors(tmp_path):
    atomic_write_text(tmp_path / "scene_gt.json", "[")
    with pytest.raises(BopFormatError) as info:
        load_scene_gt(tmp_path / "scene_gt.json")
    assert isinstance(info.value, FileFormatError) and isinstance(info.value, ValueError)


def test_json_round_trip_of_plain_values(tmp_path):
    cfg = OmegaConf.create({"a": 1, "b": "${a}", "c": [0.5]})
    data = {"cfg": cfg, "arr": np.arange(3), "n": np.int64(7), "t": (np.float32(0.5),)}
    assert to_plain(data) == {"cfg": {"a": 1, "b": 1, "c": [0.5]}, "arr": [0, 1, 2], "n": 7, "t": [0.5]}
    path = atomic_write_json(tmp_path / "sub" / "x.json", data)
    assert read_json(path) == {"cfg": {"a": 1, "b": 1, "c": [0.5]}, "arr": [0, 1, 2], "n": 7, "t": [0.5]}
    assert not [p for p in path.parent.iterdir() if p.name != "x.json"]  # no temp file left
