"""Box augmentation: jitter ranges, PGPG offsets from fitted detector-error stats, stats file I/O."""

import json

import numpy as np
import pytest

from kpd6d.box_errors import (
    BoxErrorStatsError,
    apply_offsets,
    box_offsets,
    fit_box_error_stats,
    load_box_error_stats,
    save_box_error_stats,
)
from kpd6d.kpd.box_augment import build_box_augment


def test_offsets_by_hand_and_round_trip():
    gt = np.array([[10.0, 20.0, 100.0, 50.0]])
    pred = np.array([[20.0, 15.0, 120.0, 50.0]])  # centre (80, 40) vs (60, 45)
    off = box_offsets(gt, pred)
    np.testing.assert_allclose(off, [[20 / 100, -5 / 50, np.log(1.2), 0.0]])
    np.testing.assert_allclose(apply_offsets(gt[0], off[0]), pred[0])
    with pytest.raises(ValueError, match="positive"):
        box_offsets([[0, 0, 0, 5]], [[0, 0, 1, 1]])


def test_jitter_ranges():
    aug = build_box_augment({"name": "jitter", "shift": 0.1, "scale": 0.2})
    rng = np.random.default_rng(0)
    box = np.array([50.0, 60.0, 80.0, 40.0])
    offs = np.array([box_offsets(box[None], aug(box, rng)[None])[0] for _ in range(2000)])
    assert np.abs(offs[:, :2]).max() <= 0.1 + 1e-9 and np.abs(offs[:, :2]).max() > 0.09
    assert np.abs(offs[:, 2:]).max() <= np.log(1.2) + 1e-9
    assert abs(offs.mean(0)).max() < 0.02
    with pytest.raises(ValueError, match="unknown box augmentation 'wobble'; known: jitter, none, pgpg"):
        build_box_augment({"name": "wobble"})


def test_pgpg_draws_from_fitted_distribution(tmp_path):
    rng = np.random.default_rng(1)
    gt = np.column_stack([rng.uniform(0, 500, (400, 2)), rng.uniform(30, 200, (400, 2))])
    # a biased detector: boxes 10% too wide, shifted right by 5% of the width
    true_off = np.column_stack([0.05 + 0.01 * rng.standard_normal(400), 0.01 * rng.standard_normal(400),
                                np.log(1.1) + 0.01 * rng.standard_normal(400), 0.01 * rng.standard_normal(400)])
    pred = np.array([apply_offsets(g, o) for g, o in zip(gt, true_off)])
    obj_ids = np.where(np.arange(400) < 200, 1, 5)
    stats = fit_box_error_stats(gt, pred, obj_ids=obj_ids)
    assert stats["num_samples"] == 400
    np.testing.assert_allclose(stats["mean"], true_off.mean(0), atol=1e-9)
    path = save_box_error_stats(tmp_path / "det" / "box_error_stats.json", stats)
    assert json.loads(path.read_text())["format"] == "kpd6d-box-error-stats"
    loaded = load_box_error_stats(path)
    np.testing.assert_allclose(loaded["offsets"], true_off, atol=1e-9)
    assert sorted(loaded["per_object"]) == [1, 5]

    aug = build_box_augment({"name": "pgpg", "stats": str(path)})
    box = np.array([100.0, 100.0, 80.0, 60.0])
    draws = np.array([box_offsets(box[None], aug(box, rng, obj_id=5)[None])[0] for _ in range(500)])
    # every draw is one of the object's empirical offsets
    own = true_off[200:]
    assert np.min(np.abs(draws[:, None, :] - own[None]).sum(-1), axis=1).max() < 1e-9
    np.testing.assert_allclose(draws.mean(0), own.mean(0), atol=0.01)


def test_stats_errors_name_file_and_field(tmp_path):
    with pytest.raises(BoxErrorStatsError, match="does not exist"):
        load_box_error_stats(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": "kpd6d-box-error-stats", "offsets": [[0, 0, 0]]}))
    with pytest.raises(BoxErrorStatsError, match=r"bad\.json.*'offsets'"):
        load_box_error_stats(bad)
    bad.write_text(json.dumps({"format": "other"}))
    with pytest.raises(BoxErrorStatsError, match="'format'"):
        load_box_error_stats(bad)
