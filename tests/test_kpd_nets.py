"""BACKBONES (timm features_only, local weights only) and the heatmap heads / KeypointNet."""

import pytest
import torch

from kpd6d.kpd.backbones import BackboneWeightsError
from kpd6d.kpd.heads import KeypointNet
from kpd6d.registry import BACKBONES, UnknownNameError

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_registered_backbones():
    want = {"resnet18", "resnet34", "resnet50", "resnet101", "hrnet_w18", "hrnet_w32", "convnext_tiny"}
    assert want <= set(BACKBONES.names())
    with pytest.raises(UnknownNameError, match="resnet101"):
        BACKBONES.build("resnet9000")


@pytest.mark.parametrize("name", ["resnet18", "hrnet_w18", "convnext_tiny", "tiny"])
@pytest.mark.parametrize("head", [{"name": "deconv", "deconv_channels": 32}, {"name": "fpn", "fpn_channels": 32}])
def test_keypoint_net_output_stride_4(name, head):
    net = KeypointNet({"name": name}, head, num_keypoints=5, num_groups=3, out_stride=4).eval()
    with torch.no_grad():
        out = net(torch.rand(2, 3, 64, 64))
    assert out.shape == (2, 15, 16, 16)
    sel = net.select(out, torch.tensor([2, 0]))
    assert torch.equal(sel[0], out[0, 10:15]) and torch.equal(sel[1], out[1, 0:5])


def test_resnet101_deconv_head_is_simple_baselines():
    net = KeypointNet({"name": "resnet101"}, {"name": "deconv"}, num_keypoints=8)
    deconvs = [m for m in net.head.modules() if isinstance(m, torch.nn.ConvTranspose2d)]
    assert len(deconvs) == 3
    assert all(d.kernel_size == (4, 4) and d.stride == (2, 2) and d.out_channels == 256 for d in deconvs)
    assert deconvs[0].in_channels == 2048


def test_head_errors():
    with pytest.raises(ValueError, match="unknown head 'mlp'; known heads: deconv, fpn"):
        KeypointNet({"name": "resnet18"}, {"name": "mlp"}, 4)
    with pytest.raises(ValueError, match="output stride 3"):
        KeypointNet({"name": "resnet18"}, {"name": "deconv"}, 4, out_stride=3)
    net = KeypointNet({"name": "resnet18"}, {"name": "deconv", "deconv_channels": 8}, 4, num_groups=2)
    with pytest.raises(ValueError, match="object index"):
        net.select(torch.zeros(1, 8, 4, 4), None)
    with pytest.raises(TypeError, match="deconv_channels"):  # a setting of the other head kind is an error ...
        KeypointNet({"name": "resnet18"}, {"name": "fpn", "fpn_channels": 8, "deconv_channels": 8}, 4)
    # ... unless null: how a preset inheriting the deconv head switches to the FPN head (conf/kpd/cpu_small.yaml)
    net = KeypointNet({"name": "resnet18"}, {"name": "fpn", "fpn_channels": 8, "deconv_channels": None}, 4)
    assert type(net.head).__name__ == "FPNHead"


def test_local_pretrained_weights(tmp_path):
    import timm

    full = timm.create_model("resnet18", pretrained=False, num_classes=10)
    path = tmp_path / "resnet18.pth"
    torch.save({"state_dict": full.state_dict()}, path)
    bb = BACKBONES.build("resnet18", pretrained=str(path))
    assert torch.equal(bb.body.conv1.weight, full.conv1.weight)
    assert torch.equal(bb.body.layer4[1].bn2.running_var, full.layer4[1].bn2.running_var)

    with pytest.raises(BackboneWeightsError, match=r"missing\.pth.*does not exist.*never downloads"):
        BACKBONES.build("resnet18", pretrained=str(tmp_path / "missing.pth"))
    other = tmp_path / "resnet50.pth"
    torch.save(timm.create_model("resnet50", pretrained=False).state_dict(), other)
    with pytest.raises(BackboneWeightsError, match=r"resnet50\.pth.*does not match"):
        BACKBONES.build("resnet18", pretrained=str(other))
    junk = tmp_path / "junk.pth"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(BackboneWeightsError, match="cannot read"):
        BACKBONES.build("resnet18", pretrained=str(junk))
