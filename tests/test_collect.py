import csv
import json

import pytest

from kpd6d.cli.collect import main
from kpd6d.evaluation.collect import collect


def _run(root, i, overrides, mean, per_object):
    d = root / str(i)
    (d / ".hydra").mkdir(parents=True)
    (d / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    (d / "metrics.json").write_text(json.dumps({"mean": mean, "per_object": per_object}))


def test_collect_top_l_sweep_and_designator_table(tmp_path):
    for i, top_l in enumerate([4, 10, 50]):
        _run(tmp_path, i, [f"select.top_l={top_l}", "designator=sift"],
             {"add_0.1d": top_l / 100, "proj2d_5px": 0.5}, {"1": {"add_0.1d": top_l / 100}, "5": {"add_0.1d": 0.2}})
    res = collect(tmp_path)
    assert res["varied"] == ["select.top_l"]
    rows = list(csv.DictReader(open(res["csv"])))
    # natural order of run folders and the values written, independently recomputed
    assert [r["select.top_l"] for r in rows] == ["4", "10", "50"]
    assert [float(r["add_0.1d"]) for r in rows] == pytest.approx([0.04, 0.10, 0.50])
    assert [float(r["obj5.add_0.1d"]) for r in rows] == pytest.approx([0.2] * 3)
    md = open(res["markdown"]).read()
    assert "| 2 | 50 | 0.5000 | 0.5000 |" in md
    assert any(p.endswith("accuracy_vs_top_l.png") for p in res["plots"])


def test_collect_designator_ablation_plot(tmp_path):
    _run(tmp_path, 0, ["designator=sift"], {"add_0.1d": 0.7}, {"1": {"add_0.1d": 0.8}, "5": {"add_0.1d": 0.6}})
    _run(tmp_path, 1, ["designator=bbox_corners"], {"add_0.1d": 0.5}, {"1": {"add_0.1d": 0.6}, "5": {"add_0.1d": 0.4}})
    res = collect(tmp_path, tmp_path / "out")
    assert [p.split("/")[-1] for p in res["plots"]] == ["per_object_by_designator.png"]
    assert (tmp_path / "out" / "per_object_by_designator.png").stat().st_size > 1000


def test_collect_errors_name_the_problem(tmp_path, capsys):
    assert main([str(tmp_path / "missing")]) == 2
    assert "is not a folder" in capsys.readouterr().err
    assert main([str(tmp_path)]) == 2
    assert "no metrics.json" in capsys.readouterr().err
    (tmp_path / "0").mkdir()
    (tmp_path / "0" / "metrics.json").write_text("{oops")
    assert main([str(tmp_path)]) == 2
    assert "0/metrics.json is not valid JSON" in capsys.readouterr().err


def test_collect_skips_a_jobs_own_subfolders(tmp_path):
    # kpd6d-run writes metrics.json in the job folder and in its eval/ and kpd/ sub-folders
    for i, name in enumerate(["sift", "bbox_corners"]):
        _run(tmp_path, i, [f"designator={name}"], {"add_0.1d": 0.1 * (i + 1)}, {"1": {"add_0.1d": 0.1}})
        (tmp_path / str(i) / "eval").mkdir()
        (tmp_path / str(i) / "eval" / "metrics.json").write_text(json.dumps({"mean": {"add_0.1d": 0.9}}))
    res = collect(tmp_path)
    assert [r["run"] for r in res["rows"]] == ["0", "1"] and res["varied"] == ["designator"]
