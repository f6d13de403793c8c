"""The PnP benchmark runs end to end on a tiny problem set and reports sensible figures."""

from __future__ import annotations

import pytest

from kpd6d.benchmarks import pnp as bench


def test_pnp_benchmark_small_run(capsys):
    assert bench.main(["--batch", "16", "--single", "2", "--solvers", "epnp,weighted_lm", "--noise", "0.5"]) == 0
    out = capsys.readouterr().out
    lines = {ln.split()[0]: ln.split() for ln in out.splitlines() if ln.split() and ln.split()[0] in ("epnp", "weighted_lm")}
    assert set(lines) == {"epnp", "weighted_lm"}
    for cols in lines.values():
        ok_pct, add_acc = float(cols[4]), float(cols[5])
        assert ok_pct == 100.0 and add_acc >= 90.0  # 0.5 px noise at LineMod distances


def test_pnp_benchmark_problems_are_projections_of_the_poses():
    from kpd6d.geometry import LINEMOD_K, project_points

    kp, pts, diameter, R, t, uv = bench.make_problems(20, 5, noise=0.0, outliers=0.0, seed=3)
    assert kp.shape == (20, 3) and pts.shape == (1000, 3) and diameter > 50
    assert abs(project_points(kp, LINEMOD_K, R, t) - uv).max() < 1e-9
    assert ((t[:, 2] >= 400) & (t[:, 2] <= 1200)).all()


def test_pnp_benchmark_rejects_unknown_solver(capsys):
    with pytest.raises(SystemExit):
        bench.main(["--solvers", "nope"])
    assert "known: dlt, epnp" in capsys.readouterr().err
