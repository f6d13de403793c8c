"""Bad input and faults (issue 20, first part): clear errors that name the file, nothing an input holds
is overwritten, a dead worker ends a run instead of hanging it."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _tiny_kpd(tmp_path):
    import pytorch_lightning as pl

    from kpd6d.kpd.module import KPDModule

    rng = np.random.default_rng(0)
    module = KPDModule(obj_ids=[1], keypoints_3d=[rng.uniform(-30, 30, (5, 3))], diameters=[80.0],
                       backbone={"name": "tiny", "width": 4}, head={"name": "fpn", "fpn_channels": 8},
                       input_size=32, out_stride=4)
    trainer = pl.Trainer(max_steps=0, accelerator="cpu", logger=False, enable_checkpointing=False,
                         enable_progress_bar=False, enable_model_summary=False, default_root_dir=tmp_path)
    trainer.strategy.connect(module)
    path = tmp_path / "kpd.ckpt"
    trainer.save_checkpoint(path)
    return path


def test_broken_kpd_checkpoints_name_the_file(tmp_path):
    from kpd6d.detection import build_detector, save_detector
    from kpd6d.kpd.module import KPDModule

    good = _tiny_kpd(tmp_path)
    data = good.read_bytes()
    cases = {
        "empty.ckpt": (b"", r"empty\.ckpt.* is empty \(0 bytes\)"),
        "truncated.ckpt": (data[: len(data) // 2], r"truncated\.ckpt.* cannot be read"),
        "text.ckpt": (b"hello, not a checkpoint\n", r"text\.ckpt.* cannot be read"),
    }
    for name, (content, match) in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ValueError, match=match):
            KPDModule.load_checkpoint(tmp_path / name)
    det = save_detector(build_detector("centernet", obj_ids=[1], backbone="resnet10t", input_size=None),
                        tmp_path / "detector.pt")
    with pytest.raises(ValueError, match=r"detector\.pt.* is a detector checkpoint.*detector_ckpt"):
        KPDModule.load_checkpoint(det)
    torch.save({"state_dict": {}}, tmp_path / "other.ckpt")
    with pytest.raises(ValueError, match=r"other\.ckpt.* is not a kpd6d KPD checkpoint.*found \['state_dict'\]"):
        KPDModule.load_checkpoint(tmp_path / "other.ckpt")
    assert KPDModule.load_checkpoint(good).obj_ids == [1]  # the good one still loads
    assert good.read_bytes() == data


def test_evaluation_never_writes_into_the_dataset(tmp_path):
    """kpd6d-evaluate with its output folder inside the dataset used to overwrite the dataset's own
    test_targets_bop19.json."""
    from kpd6d.data import BopDataset
    from kpd6d.evaluation.runner import evaluate
    from kpd6d.synth import generate_dataset

    root = tmp_path / "ds"
    generate_dataset(root, obj_ids=[1], num_images=2, split="test", seed=3, workers=1, width=96, height=72)
    targets = root / "test_targets_bop19.json"
    targets.write_text('[{"scene_id": 0, "im_id": 0, "obj_id": 1, "inst_count": 1}]')
    before = {p: p.read_bytes() for p in root.rglob("*") if p.is_file()}
    for out in (root, root / "test", root / "eval"):
        with pytest.raises(ValueError, match=r"is inside the dataset .*; outputs never go into an input dataset"):
            evaluate(None, BopDataset(root, "test"), out, oracle=True, progress=False)
    assert {p: p.read_bytes() for p in root.rglob("*") if p.is_file()} == before
    assert not (root / "eval").exists()


@pytest.mark.slow
def test_generation_whose_workers_cannot_start_fails_instead_of_hanging(tmp_path):
    """A script read from standard input cannot be re-imported by spawned workers: the run must end
    with an error that says what to do (multiprocessing.Pool respawned the dead workers forever)."""
    script = textwrap.dedent(f"""
        from kpd6d.synth import generate_dataset
        generate_dataset({str(tmp_path / 'ds')!r}, obj_ids=[1], num_images=6, workers=2, width=64, height=48)
    """)
    r = subprocess.run([sys.executable, "-"], input=script, capture_output=True, text=True, timeout=300)
    assert r.returncode != 0, r.stdout[-2000:]
    assert "a worker process died" in r.stderr and "__main__" in r.stderr, r.stderr[-3000:]
