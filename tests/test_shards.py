"""Sharded generation (``generate_dataset(..., shard=i, num_shards=n)`` + ``merge_shards``) and sharded
evaluation (``evaluate(..., shard=i, num_shards=n)`` + ``merge=True``): the union is the single job's
result, byte for byte; a killed shard resumes; the merges name a missing or duplicated image / frame."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from kpd6d.synth import ShardMergeError, generate_dataset, merge_shards
from synth_helpers import SMALL, tree_bytes, write_models

# 7 images in scenes of 4: scene 0 (images 0-3) and scene 1 (images 4-6); in 3 shards every shard
# writes into both scenes
_RUN = dict(num_images=7, seed=5, progress=False, distractors=(1, 1), scene_size=4, objects_per_image=(1, 2),
            **{**SMALL, "width": 64, "height": 48, "distance_range": (350.0, 600.0), "designator": {
                "name": "bbox_corners", "num_keypoints": 9}})
N = 3


def _dataset_files(root: Path) -> dict[str, bytes]:
    """The dataset's files, without the shards' own (partial scene files and markers)."""
    return {k: v for k, v in tree_bytes(root).items() if ".shard-" not in k and not k.startswith("shards/")}


@pytest.fixture(scope="module")
def models_dir(tmp_path_factory) -> Path:
    return write_models(tmp_path_factory.mktemp("models"))


@pytest.fixture(scope="module")
def reference(tmp_path_factory, models_dir) -> dict[str, bytes]:
    root = tmp_path_factory.mktemp("one")
    generate_dataset(root, models_dir, **_RUN)
    return tree_bytes(root)


def _shards(root, models_dir, shards=range(N), **kw):
    for i in shards:
        generate_dataset(root, models_dir, shard=i, num_shards=N, **{**_RUN, **kw})


def test_three_shards_merged_are_the_single_run_byte_for_byte(tmp_path, models_dir, reference):
    root = tmp_path / "sharded"
    _shards(root, models_dir)
    # before the merge: no final scene files, only the shards' own
    assert not list(root.glob("train/*/scene_gt.json"))
    assert sorted(p.name for p in (root / "train" / "000000").glob("scene_gt.*.json")) == [
        f"scene_gt.shard-{i}-of-3.json" for i in range(N)]
    assert sorted(p.name for p in (root / "shards" / "train").iterdir()) == [f"shard-{i}-of-3.json" for i in range(N)]
    info = merge_shards(root, "train", N)
    assert info == {"num_images": 7, "num_shards": 3, "scenes": 2}
    got = _dataset_files(root)
    assert set(got) == set(reference)
    for name in reference:  # annotations, rgb, masks, models/, keypoints.json, camera.json, dataset_info.json
        assert got[name] == reference[name], name
    assert any(n.endswith("scene_gt_info.json") for n in got) and any("mask_visib" in n for n in got)
    assert "models/keypoints.json" in got
    assert not list(root.rglob("*.tmp"))
    merge_shards(root, "train", N)  # merging again changes nothing
    assert _dataset_files(root) == got


def test_a_killed_shard_resumes(tmp_path, models_dir, reference, monkeypatch):
    import kpd6d.synth.generate as gen

    root = tmp_path / "k"
    _shards(root, models_dir, shards=[0, 2])
    real = gen._make_image
    calls = {"n": 0}

    def killed(index):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt  # shard 1 (images 1, 4) dies after its first image
        return real(index)

    monkeypatch.setattr(gen, "_make_image", killed)
    with pytest.raises(KeyboardInterrupt):
        _shards(root, models_dir, shards=[1])
    monkeypatch.setattr(gen, "_make_image", real)
    assert json.loads((root / "train/000000/scene_gt.shard-1-of-3.json").read_text()).keys() == {"1"}
    assert not (root / "shards/train/shard-1-of-3.json").exists()  # not finished
    with pytest.raises(ShardMergeError, match=r"shard 1 of 3 has not finished"):
        merge_shards(root, "train", N)
    # debris of the killed writer of shard 1; a temporary file of shard 0 (still running elsewhere) stays
    (root / "train/000001/rgb/.000000.jpg.abc.tmp").write_bytes(b"half-written")  # image 4: shard 1
    (root / "train/000001/rgb/.000001.jpg.def.tmp").write_bytes(b"in flight")  # image 5: shard 2
    made = []
    monkeypatch.setattr(gen, "_make_image", lambda i: made.append(i) or real(i))
    _shards(root, models_dir, shards=[1])
    assert made == [4]  # only the image it had not finished
    assert not (root / "train/000001/rgb/.000000.jpg.abc.tmp").exists()
    assert (root / "train/000001/rgb/.000001.jpg.def.tmp").exists()
    (root / "train/000001/rgb/.000001.jpg.def.tmp").unlink()
    # a lost image file of shard 2 is remade by rerunning shard 2
    (root / "train/000000/rgb/000002.jpg").unlink()
    with pytest.raises(ShardMergeError, match=r"image 2 \(scene 000000, im_id 2\) \(shard 2\).*000002.jpg is missing"):
        merge_shards(root, "train", N)
    made.clear()
    _shards(root, models_dir, shards=[2])
    assert made == [2]
    merge_shards(root, "train", N)
    got = _dataset_files(root)
    assert all(got[name] == reference[name] for name in reference) and set(got) == set(reference)


def test_merge_names_a_missing_and_a_duplicated_image(tmp_path, models_dir):
    root = tmp_path / "m"
    _shards(root, models_dir)
    sd = root / "train" / "000001"
    p1, p2 = sd / "scene_gt.shard-1-of-3.json", sd / "scene_gt.shard-2-of-3.json"
    gt1, gt2 = json.loads(p1.read_text()), json.loads(p2.read_text())
    assert sorted(gt1) == ["0"] and sorted(gt2) == ["1"]  # images 4 (shard 1) and 5 (shard 2)
    # image 4 lost from shard 1's records
    for name in ("scene_gt", "scene_camera", "scene_gt_info"):
        f = sd / f"{name}.shard-1-of-3.json"
        d = json.loads(f.read_text())
        keep = d.pop("0")
        f.write_text(json.dumps(d))
        # ... and image 5 recorded by shard 1 as well (a copy of shard 2's)
        g = json.loads((sd / f"{name}.shard-2-of-3.json").read_text())
        f.write_text(json.dumps({**d, "1": g["1"]}))
        assert keep
    with pytest.raises(ShardMergeError) as err:
        merge_shards(root, "train", N)
    msg = str(err.value)
    assert "image 4 (scene 000001, im_id 0) is missing: shard 1 of 3 did not record it" in msg
    assert "image 5 (scene 000001, im_id 1) is duplicated: recorded by shard 1 and by shard 2" in msg
    assert "image 5 (scene 000001, im_id 1) is recorded by shard 1, but belongs to shard 2 of 3" in msg
    assert not list(root.glob("train/*/scene_gt.json"))  # nothing written


def test_merge_refuses_shards_with_other_settings_or_counts(tmp_path, models_dir):
    root = tmp_path / "s"
    _shards(root, models_dir)
    m = root / "shards/train/shard-2-of-3.json"
    d = json.loads(m.read_text())
    m.write_text(json.dumps({**d, "seed": 99}))
    with pytest.raises(ShardMergeError, match=r"shard 2 of 3 was generated with other settings \(seed\)"):
        merge_shards(root, "train", N)
    m.write_text(json.dumps({**d, "num_images": 8}))
    with pytest.raises(ShardMergeError, match=r"different num_images: shard 0: 7, shard 1: 7, shard 2: 8"):
        merge_shards(root, "train", N)
    with pytest.raises(ValueError, match=r"shard must be in 0\.\.num_shards-1"):
        generate_dataset(root, models_dir, shard=3, num_shards=3, **_RUN)
    # a different shard count does not see these shards
    with pytest.raises(ShardMergeError, match="shard 0 of 2 has not finished"):
        merge_shards(root, "train", 2)


def _tiny_cli_options(models_dir) -> list[str]:
    """_RUN as kpd6d-generate overrides."""
    return [f"models_dir={models_dir}", "num_images=7", "seed=5", "workers=1", "progress=false",
            "options.width=64", "options.height=48", "options.distance_range=[350,600]", "options.distractors=[1,1]",
            "options.objects_per_image=[1,2]", "options.scene_size=4", "options.designator.name=bbox_corners",
            "options.designator.num_keypoints=9",
            "options.flush_interval_s=0"]


def test_the_documented_multirun_makes_the_shards_and_merge_true_merges_them(tmp_path, models_dir, reference,
                                                                             monkeypatch, capsys):
    """docs/scale-out.md's ``kpd6d-generate -m ... shard=0,1,2 num_shards=3``, run through Hydra's multirun
    in this process (basic launcher; the docs add hydra/launcher=local_parallel, whose composition is
    checked below), then ``kpd6d-generate ... num_shards=3 merge=true``."""
    import sys

    from hydra import compose, initialize_config_dir

    from kpd6d.cli.generate import main
    from kpd6d.config import config_dir

    root = tmp_path / "data"
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["kpd6d-generate", "-m", f"out_dir={root}", *_tiny_cli_options(models_dir),
                                      "shard=0,1,2", "num_shards=3", f"hydra.sweep.dir={tmp_path / 'sweep'}"])
    main()
    assert sorted(p.name for p in (root / "shards" / "train").iterdir()) == [f"shard-{i}-of-3.json" for i in range(N)]
    assert sorted(p.name for p in (tmp_path / "sweep").iterdir() if p.is_dir()) == ["0", "1", "2"]
    monkeypatch.setattr(sys, "argv", ["kpd6d-generate", f"out_dir={root}", "num_shards=3", "merge=true",
                                      f"hydra.run.dir={tmp_path / 'merge'}"])
    main()
    assert "3 shards of" in capsys.readouterr().out
    got = _dataset_files(root)
    assert set(got) == set(reference)
    # the same bytes as the single API run, dataset_info.json included (the API and the YAML record the
    # photometric defaults alike)
    assert [n for n in reference if got[n] != reference[n]] == []
    # the documented parallel launchers compose with the sweep (joblib here; SLURM through submitit)
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        cfg = compose("generate", overrides=[f"out_dir={root}", "shard=2", "num_shards=3",
                                             "hydra/launcher=local_parallel", "hydra.launcher.n_jobs=3"],
                      return_hydra_config=True)
    assert cfg.hydra.launcher._target_ == "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher"
    assert cfg.hydra.launcher.n_jobs == 3 and (cfg.shard, cfg.num_shards) == (2, 3)
    slurm = (config_dir() / "hydra" / "launcher" / "slurm_cpu.yaml").read_text()
    assert "submitit_slurm" in slurm and "array_parallelism" in slurm

@pytest.mark.slow
def test_the_documented_multirun_runs_with_the_joblib_launcher(tmp_path, models_dir, reference):
    """docs/scale-out.md's command as written: ``-m ... shard=0,1,2 num_shards=3
    hydra/launcher=local_parallel hydra.launcher.n_jobs=3`` (three joblib processes), then the merge;
    the merged annotations and images are the single job's bytes (but dataset_info.json, as above)."""
    import os
    import subprocess
    import sys

    root = tmp_path / "data"
    exe = [sys.executable, "-m", "kpd6d.cli.generate"]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    res = subprocess.run([*exe, "-m", f"out_dir={root}", *_tiny_cli_options(models_dir), "shard=0,1,2", "num_shards=3",
                          "hydra/launcher=local_parallel", "hydra.launcher.n_jobs=3",
                          f"hydra.sweep.dir={tmp_path / 'sweep'}"],
                         cwd=tmp_path, capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "Joblib.Parallel(n_jobs=3" in res.stdout + res.stderr  # the joblib launcher ran the shards
    res = subprocess.run([*exe, f"out_dir={root}", "num_shards=3", "merge=true", f"hydra.run.dir={tmp_path / 'merge'}"],
                         cwd=tmp_path, capture_output=True, text=True, env=env, timeout=120)
    assert res.returncode == 0, res.stderr[-3000:]
    got = _dataset_files(root)
    assert set(got) == set(reference)
    assert [n for n in reference if got[n] != reference[n]] == []  # dataset_info.json too: the API and the YAML record the same settings


# ---------------------------------------------------------------------------------------------
# sharded evaluation
# ---------------------------------------------------------------------------------------------
def _evaluate_cli(monkeypatch, *args):
    import sys

    from kpd6d.cli.evaluate import main

    monkeypatch.setattr(sys, "argv", ["kpd6d-evaluate", *args])
    main()


def _rows(path: Path) -> list[str]:
    """results.csv rows without the measured time column, sorted as the single job sorts them."""
    lines = path.read_text().splitlines()
    assert lines[0] == "scene_id,im_id,obj_id,score,R,t,time"
    return sorted(line.rsplit(",", 1)[0] for line in lines[1:])


_TIMES = ("fps", "stage_seconds_per_frame")  # measured, never equal between two runs


def _tiny_kpd_checkpoint(path: Path) -> Path:
    """An untrained KPD on the few-layer ``tiny`` backbone for test_evaluate's objects 1 and 2."""
    import torch

    from kpd6d.kpd.module import KPDModule
    from test_evaluate import _keypoints

    torch.manual_seed(0)
    m = KPDModule(obj_ids=[1, 2], keypoints_3d=[_keypoints(1), _keypoints(2)], diameters=[103.9, 94.3],
                  backbone={"name": "tiny", "width": 8}, head={"name": "deconv", "deconv_channels": 16},
                  input_size=64, out_stride=4)
    torch.save({"hyper_parameters": dict(m.hparams), "state_dict": m.state_dict()}, path)
    return path


def _evaluation_setup(tmp_path: Path, overlays: int):
    """test_evaluate's 5-frame dataset, an untrained tiny KPD and the evaluate overrides for both;
    returns ``(overrides, run)`` where ``run(out, **settings)`` is the single (or sharded) job."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from kpd6d.config import config_dir
    from kpd6d.workflow import run_evaluation
    from test_evaluate import make_dataset

    root, _, _ = make_dataset(tmp_path / "ds", n_frames=5, hidden=(3, 2))
    ckpt = _tiny_kpd_checkpoint(tmp_path / "kpd.ckpt")
    common = [f"data.root={root}", f"kpd_ckpt={ckpt}", "detector_ckpt=oracle", "device=cpu", "progress=false",
              f"overlays={overlays}", "pnp=epnp_ransac", "select.top_l=8", "batch_size=2"]
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        cfg = compose("evaluate", overrides=common)

    def run(out, **kw):
        return run_evaluation(OmegaConf.merge(cfg, {"out_dir": str(out), **kw}), out)

    return common, run


def test_two_evaluation_shards_merged_are_the_single_job(tmp_path, monkeypatch, capsys, one_torch_thread):
    common, run = _evaluation_setup(tmp_path, overlays=1)

    one, many = tmp_path / "one", tmp_path / "many"
    run(one)
    assert run(many, shard=0, num_shards=2)["frames"] == 3
    # shard 1 through the command line, as a multirun job runs it
    _evaluate_cli(monkeypatch, *common, f"out_dir={many}", "shard=1", "num_shards=2", f"hydra.run.dir={tmp_path / 'h'}")
    assert "shard 1 of 2: predictions of 2 frames" in capsys.readouterr().out
    assert not (many / "metrics.json").exists()
    # batches of 2 dealt round robin: frames 0, 1, 4 to shard 0, frames 2, 3 to shard 1
    marker = json.loads((many / "shards/shard-1-of-2/shard.json").read_text())
    assert marker["frames"] == [[1, 2], [1, 3]]
    run(many, num_shards=2, merge=True)
    rows = _rows(one / "results.csv")
    assert rows and _rows(many / "results.csv") == rows
    a, b = (json.loads((d / "metrics.json").read_text()) for d in (one, many))
    assert {k: v for k, v in a.items() if k not in _TIMES} == {k: v for k, v in b.items() if k not in _TIMES}
    assert a["mean"]["n"] == 10
    for name in ("test_targets_bop19.json", "overlays/000001_000000.png"):
        assert (one / name).read_bytes() == (many / name).read_bytes(), name
    strip = [{k: v for k, v in json.loads(line).items() if k not in ("time", "stages")}
             for line in (one / "predictions.jsonl").read_text().splitlines()]
    assert strip == [{k: v for k, v in json.loads(line).items() if k not in ("time", "stages")}
                     for line in (many / "predictions.jsonl").read_text().splitlines()]
    # a shard without out_dir is refused (each Hydra job would get its own folder)
    with pytest.raises(SystemExit, match="needs out_dir"):
        _evaluate_cli(monkeypatch, *common, "shard=1", "num_shards=2", f"hydra.run.dir={tmp_path / 'h2'}")


@pytest.mark.slow
def test_the_documented_evaluation_multirun_runs_with_the_joblib_launcher(tmp_path, one_torch_thread):
    """docs/scale-out.md's ``kpd6d-evaluate -m ... out_dir=... shard=0,1 num_shards=2
    hydra/launcher=local_parallel`` and the merge, as written (subprocesses), = the single job."""
    import os
    import subprocess
    import sys

    common, run = _evaluation_setup(tmp_path, overlays=0)
    one, many = tmp_path / "one", tmp_path / "many"
    run(one)
    exe = [sys.executable, "-m", "kpd6d.cli.evaluate"]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    res = subprocess.run([*exe, "-m", *common, f"out_dir={many}", "shard=0,1", "num_shards=2",
                          "hydra/launcher=local_parallel", f"hydra.sweep.dir={tmp_path / 'sweep'}"],
                         cwd=tmp_path, capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "Joblib.Parallel(n_jobs=" in res.stdout + res.stderr
    res = subprocess.run([*exe, *common, f"out_dir={many}", "num_shards=2", "merge=true",
                          f"hydra.run.dir={tmp_path / 'merge'}"], cwd=tmp_path, capture_output=True, text=True,
                         env=env, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    rows = _rows(one / "results.csv")
    assert rows and _rows(many / "results.csv") == rows
    a, b = (json.loads((d / "metrics.json").read_text()) for d in (one, many))
    assert {k: v for k, v in a.items() if k not in _TIMES} == {k: v for k, v in b.items() if k not in _TIMES}


def test_evaluation_merge_names_unfinished_shards_missing_and_duplicated_frames(tmp_path):
    from kpd6d.data import BopDataset
    from kpd6d.evaluation.runner import ShardMergeError, evaluate
    from test_evaluate import BoxKeyedKPD, _pipeline, make_dataset

    root, poses, K = make_dataset(tmp_path / "ds", n_frames=4)
    out = tmp_path / "run"

    def run(**kw):
        return evaluate(_pipeline(BoxKeyedKPD(root, poses, K)), BopDataset(root), out, oracle=True, n_overlays=0,
                        progress=False, run_info={"pnp": "epnp"}, num_shards=2, **kw)

    assert run(shard=0) == {"shard": 0, "num_shards": 2, "frames": 2, "out_dir": str(out / "shards/shard-0-of-2")}
    with pytest.raises(ShardMergeError, match=r"shard 1 of 2 has not finished"):
        run(merge=True)
    run(shard=1)
    p0, p1 = out / "shards/shard-0-of-2/predictions.jsonl", out / "shards/shard-1-of-2/predictions.jsonl"
    l0, l1 = p0.read_text().splitlines(), p1.read_text().splitlines()
    assert [json.loads(x)["im_id"] for x in l0] == [0, 2] and [json.loads(x)["im_id"] for x in l1] == [1, 3]
    p0.write_text(l0[0] + "\n" + l1[0] + "\n")  # frame 2 lost, frame 1 predicted by both shards
    with pytest.raises(ShardMergeError) as err:
        run(merge=True)
    msg = str(err.value)
    assert "frame (scene 1, im_id 2) is missing: shard 0 of 2 has no prediction for it" in msg
    assert "frame (scene 1, im_id 1) is duplicated: predicted by shards 0, 1 (it belongs to shard 1)" in msg
    assert not (out / "metrics.json").exists()
    # without the duplicate, rerunning shard 0 redoes only its lost frame
    p0.write_text(l0[0] + "\n")
    kpd = BoxKeyedKPD(root, poses, K)
    evaluate(_pipeline(kpd), BopDataset(root), out, oracle=True, n_overlays=0, progress=False,
             run_info={"pnp": "epnp"}, num_shards=2, shard=0)
    assert kpd.calls == 1
    m = run(merge=True)
    assert m["mean"]["add_s_01d"] == 1.0 and m["mean"]["n"] == 8
    # a shard with other settings is named
    with pytest.raises(ValueError, match=r"other settings \(pnp"):
        evaluate(_pipeline(BoxKeyedKPD(root, poses, K)), BopDataset(root), out, oracle=True, n_overlays=0,
                 progress=False, run_info={"pnp": "sqpnp"}, num_shards=2, shard=1)
    with pytest.raises(ValueError, match="merge=true needs num_shards"):
        evaluate(_pipeline(BoxKeyedKPD(root, poses, K)), BopDataset(root), out, merge=True, progress=False)


def test_refreshed_distractor_pools_are_the_same_whichever_process_makes_an_image(tmp_path, models_dir, reference):
    """``distractor_refresh``: image k uses pool k // n, so three shards (each meeting the blocks in its
    own order) merge into the single run byte for byte; the first block is the unrefreshed run's pool."""
    kw = dict(distractor_refresh=2, palette="natural")
    one = tmp_path / "one"
    generate_dataset(one, models_dir, **{**_RUN, **kw})
    single = tree_bytes(one)
    _shards(tmp_path / "sharded", models_dir, **kw)
    merge_shards(tmp_path / "sharded", "train", N)
    got = _dataset_files(tmp_path / "sharded")
    assert set(got) == set(single)
    for name in single:
        assert got[name] == single[name], name
    # against the natural palette without refresh: images 0-1 (block 0) equal, later ones differ
    plain = tmp_path / "plain"
    generate_dataset(plain, models_dir, **{**_RUN, "palette": "natural"})
    plain_files = tree_bytes(plain)
    rgb = sorted(n for n in single if "/rgb/" in n)
    assert len(rgb) == 7
    assert [single[n] == plain_files[n] for n in rgb[:2]] == [True, True]
    assert sum(single[n] != plain_files[n] for n in rgb[2:]) >= 3
    assert sum(single[n] != reference[n] for n in rgb) >= 5  # natural vs uniform palette
