"""Model configs: the shipped YAML files, loading by name or path, and clear errors."""

from __future__ import annotations

import dataclasses

import pytest

from vlocnetpp_core.errors import DataError
from vlocnetpp_core.model import ModelConfig, load_model_config
from vlocnetpp_core.model.config import config_dir


def test_paper_yaml_is_the_paper_topology():
    cfg = load_model_config("paper")
    assert cfg == ModelConfig()  # the dataclass defaults are the paper's values
    assert cfg.depths == (3, 4, 6, 3)
    assert cfg.stage_channels == (256, 512, 1024, 2048)
    assert cfg.stem_width == 64 and cfg.fc_width == 1024 and cfg.dropout == 0.2
    assert cfg.input_size == (448, 256)
    assert cfg.temporal_fusion and cfg.semantic_fusion and cfg.warping


def test_lite_keeps_every_stream_and_fusion_and_is_smaller():
    lite, paper = load_model_config("lite"), load_model_config("paper")
    assert (lite.temporal_fusion, lite.semantic_fusion, lite.warping) == (True, True, True)
    assert all(a <= b for a, b in zip(lite.widths, paper.widths, strict=True))
    assert sum(lite.depths) < sum(paper.depths)
    w, h = lite.input_size
    assert w % 16 == 0 and h % 16 == 0


def test_config_dir_is_found_from_the_module(tmp_path):
    folder = config_dir()
    assert folder is not None and (folder / "paper.yaml").is_file() and (folder / "lite.yaml").is_file()


def test_yaml_file_by_path_round_trips(tmp_path):
    import yaml

    cfg = dataclasses.replace(load_model_config("lite"), name="mine", input_size=(160, 96), warping=False)
    path = tmp_path / "mine.yaml"
    path.write_text(yaml.safe_dump(cfg.to_dict()))
    assert load_model_config(path) == cfg
    partial = tmp_path / "partial.yaml"
    partial.write_text("depths: [1, 1, 1, 1]\nres4_fusion_block: 1\n")
    loaded = load_model_config(str(partial))
    assert loaded.depths == (1, 1, 1, 1) and loaded.widths == ModelConfig().widths


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("input_size: [100, 64]\n", "multiples of 16"),
        ("widths: [16, 32]\n", "expected 4 values"),
        ("bogus: 3\n", "unknown model config key"),
        ("warping: yes please\n", "expected true/false"),
        ("depths: [1, 1, 2, 1]\n", "res4_fusion_block"),
        ("input_size: [64\n", "not valid YAML"),
        ("global_pose_pooling: max\n", "global_pose_pooling must be one of"),
        ("global_downsample: 0\n", "global_downsample must be >= 1"),
        ("global_pose_anchors: -1\n", "global_pose_anchors must be >= 0"),
        ("global_rotation_anchors: -2\n", "global_rotation_anchors must be >= 0"),
    ],
)
def test_bad_config_files_name_the_file(tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(DataError, match=message) as err:
        load_model_config(path)
    assert str(path) in str(err.value)


def test_missing_config_file_is_a_clear_error(tmp_path):
    with pytest.raises(DataError, match="no such model config"):
        load_model_config(tmp_path / "absent.yaml")


def test_base_takes_every_key_of_the_named_config_and_the_file_overrides_them(tmp_path):
    (tmp_path / "narrow.yaml").write_text("base: lite\nname: narrow\nfc_width: 128\n")
    (tmp_path / "narrower.yaml").write_text(
        "base: narrow.yaml\nname: narrower\ndropout: 0.0\n"
    )  # relative to this file
    assert load_model_config(tmp_path / "narrow.yaml") == dataclasses.replace(
        load_model_config("lite"), name="narrow", fc_width=128
    )
    assert load_model_config(tmp_path / "narrower.yaml") == dataclasses.replace(
        load_model_config("lite"), name="narrower", fc_width=128, dropout=0.0
    )


@pytest.mark.parametrize(
    ("files", "message"),
    [
        ({"a.yaml": "base: b.yaml\n", "b.yaml": "base: a.yaml\n"}, "'base' loops back"),
        ({"a.yaml": "base: absent.yaml\n"}, "no such model config file"),
        ({"a.yaml": "base: [lite]\n"}, "'base' must name a model config"),
        ({"a.yaml": "base: b.yaml\n", "b.yaml": "bogus: 1\n"}, "unknown model config key"),
        ({"a.yaml": "base: b.yaml\n", "b.yaml": "- 1\n"}, "expected a mapping of model config keys"),
    ],
)
def test_a_bad_base_is_a_clear_error(tmp_path, files, message):
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    with pytest.raises(DataError, match=message):
        load_model_config(tmp_path / "a.yaml")
