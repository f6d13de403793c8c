"""BOP19 scoring: official reference numbers on LM-O, matching rules on hand-made datasets."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import trimesh

from kpd6d.cli.score import main as score_main
from kpd6d.evaluation.bop19 import bop_symmetry_transforms, greedy_match, mspd_batch, mssd_batch, score_bop19
from kpd6d.evaluation.results_io import PoseResult, write_bop_results
from kpd6d.geometry import LINEMOD_K, random_rotation, rotation_about_axis

# ---------------------------------------------------------------------------------------------
# official toolkit numbers (bop_toolkit_lib/tests/eval_bop19_pose_test.py)
# ---------------------------------------------------------------------------------------------
MEGAPOSE_AR_MSSD = 0.49411764705882344
MEGAPOSE_AR_MSPD = 0.6067128027681661


def test_megapose_lmo_reproduces_official_toolkit(shared_data, tmp_path, capsys):
    ref = shared_data / "bop_reference"
    csv = next(ref.glob("cnos-fastsammegapose_lmo-test_*.csv"))
    out = tmp_path / "scores.json"
    assert score_main([str(csv), str(ref / "lmo_full"), "--json", str(out)]) == 0
    scores = json.loads(out.read_text())
    assert abs(scores["ar_mssd"] - MEGAPOSE_AR_MSSD) < 1e-3
    assert abs(scores["ar_mspd"] - MEGAPOSE_AR_MSPD) < 1e-3
    assert scores["n_targets"] == 1445
    assert set(scores["per_object"]) == {"1", "5", "6", "8", "9", "10", "11", "12"}
    printed = capsys.readouterr().out
    assert "AR_MSSD 0.4941" in printed and "VSD: skipped" in printed


def test_ground_truth_csv_scores_one(shared_data):
    from kpd6d.evaluation.bop19 import score_bop19_file

    ref = shared_data / "bop_reference"
    scores = score_bop19_file(ref / "gt-pbrreal-rgb-mmodel_lmo-test_lmo.csv", ref / "lmo_full")
    assert scores["ar_mssd"] == 1.0 and scores["ar_mspd"] == 1.0
    assert all(s["ar_mssd"] == 1.0 and s["ar_mspd"] == 1.0 for s in scores["per_object"].values())


# ---------------------------------------------------------------------------------------------
# greedy matching
# ---------------------------------------------------------------------------------------------
def test_greedy_match_duplicates_take_one_gt_each():
    # two estimates (score order) both closest to GT 0; the second falls back to GT 1
    errs = np.array([[0.1, 0.3], [0.05, 0.2]])
    np.testing.assert_array_equal(greedy_match(errs, [True, True], 0.25), [0, 1])
    # with a tighter threshold the duplicate gets nothing
    np.testing.assert_array_equal(greedy_match(errs, [True, True], 0.15), [0, -1])


def test_greedy_match_strict_threshold_invalid_gts_and_ties():
    errs = np.array([[0.2, 0.2, 0.01]])
    np.testing.assert_array_equal(greedy_match(errs, [True, True, True], 0.2), [2])
    np.testing.assert_array_equal(greedy_match(errs, [True, True, False], 0.2), [-1])  # 0.2 is not < 0.2
    np.testing.assert_array_equal(greedy_match(errs, [True, True, False], 0.21), [0])  # tie -> lower index
    assert greedy_match(np.zeros((0, 2)), [True, True], 1.0).shape == (0,)


# ---------------------------------------------------------------------------------------------
# errors against independent computations
# ---------------------------------------------------------------------------------------------
def test_mssd_mspd_against_independent_computations():
    rng = np.random.default_rng(1)
    pts = rng.uniform(-50, 50, (200, 3))
    R_g = random_rotation(rng, 5)
    t_g = np.array([0, 0, 800.0]) + rng.normal(size=(5, 3)) * 30
    # pure translation offset: MSSD is the offset's length for every point
    off = rng.normal(size=(5, 3)) * 7
    d = mssd_batch(R_g, t_g + off, R_g, t_g, pts, np.eye(4)[None])
    np.testing.assert_allclose(d, np.linalg.norm(off, axis=1), rtol=1e-12)
    # a 180-degree symmetry about z makes the flipped pose error-free
    S = np.eye(4)
    S[:3, :3] = rotation_about_axis([0, 0, 1], np.pi)
    R_flip = R_g @ S[:3, :3]
    assert np.all(mssd_batch(R_flip, t_g, R_g, t_g, pts, np.eye(4)[None]) > 1)
    np.testing.assert_allclose(mssd_batch(R_flip, t_g, R_g, t_g, pts, np.stack([np.eye(4), S])), 0, atol=1e-9)
    # against the per-pair reference errors of kpd6d.evaluation.errors (with a continuous symmetry)
    from kpd6d.evaluation.errors import mspd_error, mssd_error

    syms = bop_symmetry_transforms({"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]})
    assert len(syms) == 315  # ceil(pi / 0.01), as bop_toolkit
    R_e = R_g @ rotation_about_axis([0, 0, 1], 0.3) @ rotation_about_axis([1, 0, 0], 0.02)
    got_s = mssd_batch(R_e, t_g + off, R_g, t_g, pts, syms)
    got_p = mspd_batch(R_e, t_g + off, R_g, t_g, LINEMOD_K, pts, syms)
    for i in range(5):
        assert got_s[i] == pytest.approx(mssd_error(R_e[i], t_g[i] + off[i], R_g[i], t_g[i], pts, syms), rel=1e-9)
        assert got_p[i] == pytest.approx(mspd_error(R_e[i], t_g[i] + off[i], R_g[i], t_g[i], pts, LINEMOD_K, syms),
                                         rel=1e-9)
    # MSPD against OpenCV's projection
    R_e = R_g @ rotation_about_axis([1, 0, 0], 0.05)
    got = mspd_batch(R_e, t_g + off, R_g, t_g, LINEMOD_K, pts, np.eye(4)[None])
    for i in range(5):
        ue = cv2.projectPoints(pts, cv2.Rodrigues(R_e[i])[0], t_g[i] + off[i], LINEMOD_K, None)[0][:, 0]
        ug = cv2.projectPoints(pts, cv2.Rodrigues(R_g[i])[0], t_g[i], LINEMOD_K, None)[0][:, 0]
        assert got[i] == pytest.approx(np.linalg.norm(ue - ug, axis=1).max(), rel=1e-9)


# ---------------------------------------------------------------------------------------------
# hand-made BOP dataset
# ---------------------------------------------------------------------------------------------
def _make_dataset(root, instances, targets, width=640):
    """One scene (1), images with GT ``instances[im] = [(obj_id, R, t, visib_fract), ...]``; a 100 mm cube per object."""
    mdir = root / "models_eval"
    mdir.mkdir(parents=True)
    info = {}
    for oid in sorted({o for insts in instances.values() for o, *_ in insts}):
        box = trimesh.creation.box(extents=(100, 100, 100))
        box.export(mdir / f"obj_{oid:06d}.ply")
        info[str(oid)] = {"diameter": float(np.sqrt(3) * 100)}
    (mdir / "models_info.json").write_text(json.dumps(info))
    sdir = root / "test" / "000001"
    sdir.mkdir(parents=True)
    gt = {str(im): [{"obj_id": o, "cam_R_m2c": R.reshape(-1).tolist(), "cam_t_m2c": list(t)} for o, R, t, _ in insts]
          for im, insts in instances.items()}
    gi = {str(im): [{"visib_fract": v, "bbox_obj": [0, 0, 10, 10], "bbox_visib": [0, 0, 10, 10], "px_count_all": 100,
                     "px_count_valid": 100, "px_count_visib": int(100 * v)} for *_, v in insts]
          for im, insts in instances.items()}
    cam = {str(im): {"cam_K": LINEMOD_K.reshape(-1).tolist(), "depth_scale": 1.0} for im in instances}
    (sdir / "scene_gt.json").write_text(json.dumps(gt))
    (sdir / "scene_gt_info.json").write_text(json.dumps(gi))
    (sdir / "scene_camera.json").write_text(json.dumps(cam))
    (root / "camera.json").write_text(json.dumps({"width": width, "height": 480, "fx": 572.4114, "fy": 573.57043,
                                                  "cx": 325.2611, "cy": 242.04899, "depth_scale": 1.0}))
    (root / "test_targets_bop19.json").write_text(json.dumps(
        [{"scene_id": 1, "im_id": im, "obj_id": o, "inst_count": n} for (im, o), n in targets.items()]))
    return root


def _pose(x=0.0, y=0.0, z=1000.0):
    return np.eye(3), np.array([x, y, z])


def test_inst_count_missing_estimates_and_non_targets(tmp_path):
    # image 1: two instances of object 1 (inst_count 2) and one of object 2; image 2: object 1 only
    g = {1: [(1, *_pose(-150), 0.9), (1, *_pose(150), 0.8), (2, *_pose(0, 150), 0.7)], 2: [(1, *_pose(), 1.0)]}
    root = _make_dataset(tmp_path / "ds", g, {(1, 1): 2, (1, 2): 1, (2, 1): 1})
    exact = lambda im, i: PoseResult(1, im, g[im][i][0], 0.5, g[im][i][1], g[im][i][2])  # noqa: E731
    far = lambda im, oid, s: PoseResult(1, im, oid, s, np.eye(3), np.array([0, -400, 900.0]))  # noqa: E731
    # a perfect estimate for each instance: recall 1
    all_ok = [exact(1, 0), exact(1, 1), exact(1, 2), exact(2, 0)]
    s = score_bop19(all_ok, root)
    assert (s["ar_mssd"], s["ar_mspd"], s["n_targets"]) == (1.0, 1.0, 4)
    # a wrong estimate with the highest score pushes a correct one out of the top inst_count (2)
    s = score_bop19([*all_ok, far(1, 1, 0.9)], root)
    assert s["ar_mssd"] == pytest.approx(3 / 4) and s["per_object"]["1"]["ar_mssd"] == pytest.approx(2 / 3)
    assert s["n_estimates_considered"] == 4
    # missing estimates count as failures; estimates of non-target objects / images are ignored
    s = score_bop19([exact(1, 0), PoseResult(1, 1, 7, 1.0, np.eye(3), np.zeros(3)), PoseResult(1, 9, 1, 1.0, *_pose())],
                    root)
    assert s["ar_mssd"] == pytest.approx(1 / 4) and s["per_object"]["2"]["ar_mssd"] == 0.0
    assert s["n_estimates_considered"] == 1


def test_duplicate_estimates_match_one_instance(tmp_path):
    g = {1: [(1, *_pose(-150), 0.9), (1, *_pose(150), 0.8)]}
    root = _make_dataset(tmp_path / "ds", g, {(1, 1): 2})
    dup = [PoseResult(1, 1, 1, s, g[1][0][1], g[1][0][2]) for s in (0.9, 0.8)]
    s = score_bop19(dup, root)
    assert s["ar_mssd"] == pytest.approx(0.5) and s["ar_mspd"] == pytest.approx(0.5)


def test_low_visibility_instances_not_counted(tmp_path):
    g = {1: [(1, *_pose(-150), 0.05), (1, *_pose(150), 0.8)]}
    root = _make_dataset(tmp_path / "ds", g, {(1, 1): 1})
    # the estimate of the hidden instance is not a success: only the visible one counts
    hidden = [PoseResult(1, 1, 1, 1.0, g[1][0][1], g[1][0][2])]
    for v in (-1.0, 0.1):
        s = score_bop19(hidden, root, visib_gt_min=v)
        assert s["n_targets"] == 1 and s["ar_mssd"] == 0.0
    visible = [PoseResult(1, 1, 1, 1.0, g[1][1][1], g[1][1][2])]
    assert score_bop19(visible, root, visib_gt_min=0.1)["ar_mssd"] == 1.0


def test_error_thresholds_mssd_relative_and_mspd_scaled_by_width(tmp_path):
    # a translation error of 0.12 d along x: MSSD correct for thresholds 0.15..0.5 (8 of 10)
    d = np.sqrt(3) * 100
    g = {1: [(1, *_pose(), 1.0)]}
    root = _make_dataset(tmp_path / "a", g, {(1, 1): 1})
    est = [PoseResult(1, 1, 1, 1.0, np.eye(3), np.array([0.12 * d, 0, 1000]))]
    s = score_bop19(est, root)
    assert s["recalls_mssd"] == [0.0, 0.0] + [1.0] * 8
    # MSPD: the shift is 0.12 d * fx / z_min-ish px; compute it independently and check the count
    pts = trimesh.creation.box(extents=(100, 100, 100)).vertices
    err = np.abs(LINEMOD_K[0, 0] * (0.12 * d) / (1000 + pts[:, 2])).max()
    assert s["recalls_mspd"] == [float(err < th) for th in range(5, 51, 5)]
    # at image width 1280 the same pixel error counts as half as large
    root2 = _make_dataset(tmp_path / "b", g, {(1, 1): 1}, width=1280)
    s2 = score_bop19(est, root2)
    assert s2["recalls_mspd"] == [float(err / 2 < th) for th in range(5, 51, 5)]


def test_cli_errors_are_clear(tmp_path, capsys):
    g = {1: [(1, *_pose(), 1.0)]}
    root = _make_dataset(tmp_path / "ds", g, {(1, 1): 1})
    bad = tmp_path / "bad.csv"
    bad.write_text("scene_id,im_id,obj_id,score,R,t,time\n1,1,1,x,1 0 0 0 1 0 0 0 1,0 0 0,1\n")
    assert score_main([str(bad), str(root)]) == 2
    assert "field 'score'" in capsys.readouterr().err
    ok = write_bop_results(tmp_path / "ok.csv", [PoseResult(1, 1, 1, 1.0, *_pose())])
    assert score_main([str(ok), str(tmp_path / "nowhere")]) == 2
    assert "test_targets_bop19.json: file does not exist" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# error decomposition (oracle substitution)
# ---------------------------------------------------------------------------------------------
def test_substitute_takes_each_part_from_the_nearest_gt_instance(tmp_path):
    from kpd6d.evaluation.bop19 import load_bop_gt
    from kpd6d.evaluation.decompose import substitute

    R1, R2 = rotation_about_axis([0, 0, 1], 0.3), rotation_about_axis([1, 0, 0], -0.4)
    g = {1: [(1, R1, np.array([-150.0, 0, 1000]), 1.0), (1, R2, np.array([150.0, 20, 900]), 1.0)]}
    root = _make_dataset(tmp_path / "ds", g, {(1, 1): 2})
    gt = load_bop_gt(root)
    t_e = np.array([160.0, 10, 990])  # nearest to the second instance
    est = [PoseResult(1, 1, 1, 0.7, np.eye(3), t_e, 0.5), PoseResult(1, 1, 3, 0.2, np.eye(3), t_e)]  # obj 3: no GT
    d, tr, ro = (substitute(est, gt, p) for p in ("depth", "translation", "rotation"))
    assert d[0].t[2] == pytest.approx(900) and np.allclose(d[0].R, np.eye(3))
    uv = lambda t: (LINEMOD_K @ t)[:2] / t[2]  # noqa: E731
    assert np.allclose(uv(d[0].t), uv(t_e))  # moved along its own ray: the projected centre stays
    assert np.allclose(tr[0].t, [150, 20, 900]) and np.allclose(tr[0].R, np.eye(3))
    assert np.allclose(ro[0].R, R2) and np.allclose(ro[0].t, t_e)
    assert (d[0].score, d[0].time) == (0.7, 0.5)
    for s in (d, tr, ro):  # no GT instance of the object: copied unchanged
        assert np.allclose(s[1].t, t_e) and np.allclose(s[1].R, np.eye(3))
    assert np.allclose(est[0].t, t_e)  # the input is not modified
    with pytest.raises(ValueError, match="known: depth, translation, rotation"):
        substitute(est, gt, "scale")


def test_error_decomposition_against_hand_substituted_scores(tmp_path, capsys):
    from kpd6d.evaluation.decompose import error_decomposition

    R2 = rotation_about_axis([0, 1, 0], 0.5)
    t1, t2 = np.array([-100.0, 30, 1000]), np.array([120.0, -40, 900])
    g = {1: [(1, np.eye(3), t1, 1.0), (2, R2, t2, 1.0)]}
    root = _make_dataset(tmp_path / "ds", g, {(1, 1): 1, (1, 2): 1})
    wrong_depth = PoseResult(1, 1, 1, 1.0, np.eye(3), t1 * 1.1)  # object 1: 100 mm too far, along its ray
    wrong_rot = PoseResult(1, 1, 2, 1.0, rotation_about_axis([0, 1, 0], 0.9), t2 + np.array([3.0, 0, 0]))  # object 2: 23 deg off
    exact1 = PoseResult(1, 1, 1, 1.0, np.eye(3), t1)
    rot_fixed = PoseResult(1, 1, 2, 1.0, R2, t2 + np.array([3.0, 0, 0]))
    trans_fixed = PoseResult(1, 1, 2, 1.0, wrong_rot.R, t2)
    dec = error_decomposition([wrong_depth, wrong_rot], root)

    def ar(results):
        s = score_bop19(results, root)
        return {"ar_mssd": s["ar_mssd"], "ar_mspd": s["ar_mspd"]}

    assert dec == {"estimated": ar([wrong_depth, wrong_rot]), "depth": ar([exact1, wrong_rot]),
                   "translation": ar([exact1, trans_fixed]), "rotation": ar([wrong_depth, rot_fixed])}
    assert dec["depth"]["ar_mssd"] > dec["estimated"]["ar_mssd"] and dec["rotation"]["ar_mspd"] > dec["estimated"]["ar_mspd"]
    # the same from the command line, in its JSON and its printed table
    csv = write_bop_results(tmp_path / "r.csv", [wrong_depth, wrong_rot])
    assert score_main([str(csv), str(root), "--decompose", "--json", str(tmp_path / "s.json")]) == 0
    assert json.loads((tmp_path / "s.json").read_text())["decomposition"] == dec
    assert f"rotation from the GT{' ' * 27}{100 * dec['rotation']['ar_mssd']:7.1f}" in capsys.readouterr().out
