"""``--init-backbone``: a standard ResNet-50 state dict (torchvision names) onto the paper backbones."""

from __future__ import annotations

import pytest
import torch
from model_fixtures import one_thread  # noqa: F401  (autouse: one thread per test)
from safetensors.torch import save_file

from vlocnetpp_core.errors import DataError
from vlocnetpp_core.model import VLocNetPP, load_backbone_weights, load_model_config


def resnet50_state_dict(dtype=torch.float16) -> dict[str, torch.Tensor]:
    """Random tensors with exactly the names and shapes of torchvision's ``resnet50().state_dict()``."""
    g = torch.Generator().manual_seed(0)
    sd: dict[str, torch.Tensor] = {}

    def rand(*shape):
        return torch.randn(*shape, generator=g).to(dtype)

    def bn(prefix: str, c: int) -> None:
        sd[f"{prefix}.weight"], sd[f"{prefix}.bias"] = rand(c), rand(c)
        sd[f"{prefix}.running_mean"], sd[f"{prefix}.running_var"] = rand(c), rand(c).abs() + 0.5
        sd[f"{prefix}.num_batches_tracked"] = torch.tensor(7)

    sd["conv1.weight"] = rand(64, 3, 7, 7)
    bn("bn1", 64)
    inplanes = 64
    for layer, (planes, blocks) in enumerate([(64, 3), (128, 4), (256, 6), (512, 3)], start=1):
        for b in range(blocks):
            p = f"layer{layer}.{b}"
            sd[f"{p}.conv1.weight"] = rand(planes, inplanes, 1, 1)
            bn(f"{p}.bn1", planes)
            sd[f"{p}.conv2.weight"] = rand(planes, planes, 3, 3)
            bn(f"{p}.bn2", planes)
            sd[f"{p}.conv3.weight"] = rand(planes * 4, planes, 1, 1)
            bn(f"{p}.bn3", planes * 4)
            if b == 0:
                sd[f"{p}.downsample.0.weight"] = rand(planes * 4, inplanes, 1, 1)
                bn(f"{p}.downsample.1", planes * 4)
            inplanes = planes * 4
    sd["fc.weight"], sd["fc.bias"] = rand(1000, 2048), rand(1000)
    return sd


@pytest.fixture(scope="module")
def resnet_file(tmp_path_factory):
    sd = resnet50_state_dict()
    path = tmp_path_factory.mktemp("rn50") / "resnet50.safetensors"
    save_file(sd, str(path))
    return path, sd


def _conv_keys(sd):
    return {k for k in sd if k.endswith(".weight") and sd[k].dim() == 4}


def test_resnet50_loads_into_every_paper_backbone(resnet_file):
    path, sd = resnet_file
    model = VLocNetPP(load_model_config("paper"))
    report = load_backbone_weights(model, path)

    assert report.unexpected == []
    loaded = {copy: {src for c, src, _ in report.loaded if c == copy} for copy in ("global", "odometry", "semantic")}
    missing = {copy: [name for c, name in report.missing if c == copy] for copy in ("global", "odometry", "semantic")}
    # The global backbone takes every convolution of the file and has none left over.
    assert _conv_keys(sd) <= loaded["global"]
    assert missing["global"] == []
    # The semantic encoder too (multiscale blocks split conv2 by output channel).
    assert _conv_keys(sd) <= loaded["semantic"] and missing["semantic"] == []
    # The odometry Res5a sees two concatenated Res4 outputs: twice the input channels, skipped and reported.
    assert sorted(missing["odometry"]) == ["odometry.res5.0.conv1.weight", "odometry.res5.0.shortcut.weight"]
    odo_skips = {src: why for c, src, why in report.skipped if c == "odometry"}
    assert "does not fit" in odo_skips["layer4.0.conv1.weight"] and "no res3" in odo_skips["layer2.0.conv1.weight"]
    assert not any(src.startswith("fc.") for _, src, _ in report.loaded)
    assert "loaded into global, odometry, semantic" in str(report)

    f32 = {k: v.float() for k, v in sd.items()}
    torch.testing.assert_close(model.trunk.stem.conv.weight, f32["conv1.weight"])
    torch.testing.assert_close(model.trunk.stem.bn.running_var, f32["bn1.running_var"])
    torch.testing.assert_close(model.global_stream.res4[5].conv3.weight, f32["layer3.5.conv3.weight"])
    torch.testing.assert_close(model.global_stream.res5[0].shortcut.weight, f32["layer4.0.downsample.0.weight"])
    torch.testing.assert_close(model.odometry.res4[2].conv2.weight, f32["layer3.2.conv2.weight"])
    # Post-activation bn1/bn2 normalise conv1/conv2 outputs: our pre-activation bn2/bn3 do the same.
    torch.testing.assert_close(model.trunk.res2[0].bn2.weight, f32["layer1.0.bn1.weight"])
    torch.testing.assert_close(model.global_stream.res4[1].bn3.running_mean, f32["layer3.1.bn2.running_mean"])
    assert (model.trunk.res2[0].bn1.weight == 1).all()  # block-input BN has no counterpart: left at init
    ms = model.semantic.res4[1]
    half = ms.conv2.out_channels
    torch.testing.assert_close(torch.cat((ms.conv2.weight, ms.conv2_dilated.weight)), f32["layer3.1.conv2.weight"])
    assert half == 128


def test_weights_only_torch_file_and_lite_mismatch(tmp_path):
    sd = {k: v for k, v in resnet50_state_dict().items() if k.startswith(("conv1", "bn1", "layer1.0."))}
    path = tmp_path / "partial.pth"
    torch.save({"state_dict": {f"module.{k}": v for k, v in sd.items()}}, path)
    model = VLocNetPP(load_model_config("paper"))
    report = load_backbone_weights(model, path)
    torch.testing.assert_close(model.semantic.res2[0].conv1.weight, sd["layer1.0.conv1.weight"].float())
    assert {c for c, _, _ in report.loaded} == {"global", "semantic"}
    with pytest.raises(DataError, match="no tensor fits"):
        load_backbone_weights(VLocNetPP(load_model_config("lite")), path)


def test_bad_backbone_files_name_the_file(tmp_path):
    model = VLocNetPP(load_model_config("lite"))
    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(b"not a weights file at all")
    with pytest.raises(DataError, match="cannot read a state dict") as err:
        load_backbone_weights(model, junk)
    assert str(junk) in str(err.value)
    pickled = tmp_path / "object.pth"
    torch.save({"weights": object()}, pickled)  # needs full unpickling: refused
    with pytest.raises(DataError, match="cannot read a state dict"):
        load_backbone_weights(model, pickled)
    with pytest.raises(DataError, match="no such file"):
        load_backbone_weights(model, tmp_path / "absent.pth")
