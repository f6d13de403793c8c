"""The detector latency benchmark builds each detector as its config (conf/detector/) describes."""

from __future__ import annotations

import json

import pytest

from kpd6d.benchmarks import detector as bench
from kpd6d.config import config_dir


def test_detector_config_is_the_yaml_file():
    from omegaconf import OmegaConf

    cfg = bench.detector_config("centernet_tiny")
    assert cfg == OmegaConf.to_container(OmegaConf.load(config_dir() / "detector" / "centernet_tiny.yaml"))
    assert cfg["name"] == "centernet"


def test_detector_latency_uses_the_configured_input_size(tmp_path, capsys):
    out = tmp_path / "rows.json"
    argv = ["--detectors", "centernet_tiny,oracle", "--batch-sizes", "1,2", "--iters", "1", "--size", "160x120",
            "--devices", "cpu", "--json", str(out)]
    assert bench.main(argv) == 0
    rows = json.loads(out.read_text())
    tiny_size = "x".join(str(v) for v in bench.detector_config("centernet_tiny")["input_size"])
    assert [(r["detector"], r["batch"], r["input"]) for r in rows] == [
        ("centernet_tiny", 1, tiny_size), ("centernet_tiny", 2, tiny_size), ("oracle", 1, "full"), ("oracle", 2, "full")]
    assert all(r["ms_per_image"] > 0 for r in rows)
    assert "centernet_tiny" in capsys.readouterr().out
    # an explicit --input-size overrides the configured one
    assert bench.main([*argv[:-2], "--detectors", "centernet_tiny", "--batch-sizes", "1", "--input-size", "96x64",
                       "--json", str(out)]) == 0
    assert json.loads(out.read_text())[0]["input"] == "96x64"


def test_detector_benchmark_rejects_unknown_config(capsys):
    with pytest.raises(SystemExit):
        bench.main(["--detectors", "centernet,nope"])
    err = capsys.readouterr().err
    assert "nope" in err and "known: centernet, centernet_lite0, centernet_tiny" in err
