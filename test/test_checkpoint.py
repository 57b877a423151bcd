"""Checkpoints: safetensors + JSON sidecar round trip, atomic writes, clear errors, never unpickled."""

from __future__ import annotations

import json
import os
import pickle
from pathlib import Path

import pytest
import torch

from vlocnetpp_core.camera.intrinsics import Intrinsics
from vlocnetpp_core.classes import CLASS_NAMES
from vlocnetpp_core.errors import DataError
from vlocnetpp_core.inference.checkpoint import (
    DEFAULT_ODOMETRY_VARIANCE,
    DEFAULT_POSE_VARIANCE,
    calibration_variances,
    checkpoint_paths,
    init_checkpoint,
    load_checkpoint,
    read_checkpoint_tensors,
    save_checkpoint,
)
from vlocnetpp_core.model import VLocNetPP, load_model_config


@pytest.fixture(scope="module")
def lite_checkpoint(tmp_path_factory) -> Path:
    return init_checkpoint("lite", tmp_path_factory.mktemp("ckpt") / "lite", seed=3)


def _same_weights(a: torch.nn.Module, b: torch.nn.Module, atol: float = 0.0) -> bool:
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.allclose(sa[k].float(), sb[k].float(), atol=atol, rtol=0) for k in sa)


def test_round_trip_restores_every_weight_and_writes_the_sidecar(lite_checkpoint: Path):
    model, meta = load_checkpoint(lite_checkpoint)
    torch.manual_seed(3)
    fresh = VLocNetPP(load_model_config("lite"))
    assert _same_weights(model, fresh)  # init_checkpoint is the seeded fresh model, stored exactly
    assert not model.training
    weights, sidecar = checkpoint_paths(lite_checkpoint)
    assert weights.suffix == ".safetensors" and sidecar.suffix == ".json" and sidecar.is_file()
    assert meta["input_size"] == [224, 128] == list(model.config.input_size)
    assert meta["model_config"]["name"] == "lite"
    assert meta["normalization"] == {"mean": list(model.config.mean), "std": list(model.config.std)}
    assert meta["class_names"] == list(CLASS_NAMES) and len(meta["class_colors"]) == 10
    K = Intrinsics.from_dict(meta["intrinsics"])
    assert (K.width, K.height) == (224, 128)  # default intrinsics live at the network input size
    assert meta["training"]["stage"] == "init"
    assert meta["calibration"]["source"] == "default"
    pose, odo = calibration_variances(meta)
    assert pose.tolist() == list(DEFAULT_POSE_VARIANCE) and odo.tolist() == list(DEFAULT_ODOMETRY_VARIANCE)
    # the same checkpoint is reachable as NAME, NAME.safetensors and NAME.json
    for name in (weights.with_suffix(""), weights, sidecar):
        assert checkpoint_paths(name) == (weights, sidecar)


def test_meta_overrides_and_fp16_storage(lite_checkpoint: Path, tmp_path: Path):
    model, _ = load_checkpoint(lite_checkpoint)
    calib = {"pose_variance": [0.04, 0.04, 0.09, 1e-4, 1e-4, 2e-4], "odometry_variance": None, "frames": 12}
    K = Intrinsics(200.0, 190.0, 111.5, 63.5, 224, 128)
    out = save_checkpoint(
        tmp_path / "half", model, {"calibration": calib, "intrinsics": K, "training": {"step": 7}}, dtype=torch.float16
    )
    assert out == tmp_path / "half.safetensors"
    assert out.stat().st_size < 0.6 * checkpoint_paths(lite_checkpoint)[0].stat().st_size
    loaded, meta = load_checkpoint(tmp_path / "half.json")
    assert meta["dtype"] == "float16"
    assert all(p.dtype == torch.float32 for p in loaded.parameters())
    assert _same_weights(model, loaded, atol=2e-3) and not _same_weights(model, loaded)
    assert Intrinsics.from_dict(meta["intrinsics"]) == K
    pose, odo = calibration_variances(meta)
    assert pose.tolist() == calib["pose_variance"]
    assert odo.tolist() == list(DEFAULT_ODOMETRY_VARIANCE)  # null entry -> documented default
    assert meta["calibration"]["frames"] == 12 and meta["training"] == {"step": 7}


def test_save_is_atomic_and_leaves_no_temporary_files(lite_checkpoint: Path, tmp_path: Path):
    model, _ = load_checkpoint(lite_checkpoint)
    target = tmp_path / "run" / "best"
    save_checkpoint(target, model, {"training": {"step": 1}})
    before = {p.name: p.read_bytes() for p in target.parent.iterdir()}
    with pytest.raises(TypeError):  # an object JSON cannot hold: nothing is replaced
        save_checkpoint(target, model, {"training": {"step": 2, "bad": object()}})
    assert {p.name: p.read_bytes() for p in target.parent.iterdir()} == before
    save_checkpoint(target, model, {"training": {"step": 3}})
    assert sorted(p.name for p in target.parent.iterdir()) == ["best.json", "best.safetensors"]
    assert json.loads((target.parent / "best.json").read_text())["training"]["step"] == 3
    assert (target.parent / "best.safetensors").stat().st_mode & 0o044  # readable like any file the user writes


def test_weights_and_sidecar_of_different_saves_are_detected(lite_checkpoint: Path, tmp_path: Path):
    model, _ = load_checkpoint(lite_checkpoint)
    a = save_checkpoint(tmp_path / "a", model, {})
    b = save_checkpoint(tmp_path / "b", model, {})
    os.replace(b, a)  # as if a save died between its two renames
    with pytest.raises(DataError, match="does not belong"):
        load_checkpoint(a)


def test_read_checkpoint_tensors_gives_the_stored_tensors(lite_checkpoint: Path):
    tensors, meta = read_checkpoint_tensors(lite_checkpoint)
    model, _ = load_checkpoint(lite_checkpoint)
    assert tensors.keys() == model.state_dict().keys()
    assert meta["format"] == "vlocnetpp-checkpoint"


def _broken_copy(src: Path, dst: Path) -> tuple[Path, Path]:
    w, s = checkpoint_paths(src)
    dw, ds = checkpoint_paths(dst)
    dw.write_bytes(w.read_bytes())
    ds.write_text(s.read_text())
    return dw, ds


def test_missing_corrupt_and_mismatched_files_raise_one_clear_error(lite_checkpoint: Path, tmp_path: Path):
    with pytest.raises(DataError, match=r"nothing\.safetensors: no such checkpoint"):
        load_checkpoint(tmp_path / "nothing")

    w, s = _broken_copy(lite_checkpoint, tmp_path / "no_sidecar")
    s.unlink()
    with pytest.raises(DataError, match=r"no_sidecar\.json: missing checkpoint sidecar"):
        load_checkpoint(w)

    w, s = _broken_copy(lite_checkpoint, tmp_path / "truncated")
    w.write_bytes(w.read_bytes()[: w.stat().st_size // 2])
    with pytest.raises(DataError, match=r"truncated\.safetensors: not a readable safetensors file"):
        load_checkpoint(w)

    w, s = _broken_copy(lite_checkpoint, tmp_path / "badjson")
    s.write_text(s.read_text()[:100])
    with pytest.raises(DataError, match=r"badjson\.json: not valid JSON"):
        load_checkpoint(w)

    w, s = _broken_copy(lite_checkpoint, tmp_path / "otherconfig")
    meta = json.loads(s.read_text())
    meta["model_config"]["fc_width"] = 128
    s.write_text(json.dumps(meta))
    with pytest.raises(
        DataError, match=r"otherconfig\.safetensors: weights do not fit the model config.*of another shape"
    ):
        load_checkpoint(w)

    w, s = _broken_copy(lite_checkpoint, tmp_path / "badcalib")
    meta = json.loads(s.read_text())
    meta["calibration"]["pose_variance"] = [1.0, 2.0]
    s.write_text(json.dumps(meta))
    with pytest.raises(DataError, match=r"badcalib\.json: calibration\.pose_variance must be 6"):
        load_checkpoint(w)


def test_non_finite_weights_are_refused(lite_checkpoint: Path, tmp_path: Path):
    model, _ = load_checkpoint(lite_checkpoint)
    with torch.no_grad():
        first = next(model.parameters())
        first[(0,) * first.dim()] = float("nan")
    save_checkpoint(tmp_path / "nan", model, {})
    with pytest.raises(DataError, match="NaN or infinite"):
        load_checkpoint(tmp_path / "nan")


class _Trap:
    """Unpickling this writes a marker file: a loader that unpickles would trip it."""

    marker = ""

    def __reduce__(self):
        return (Path(self.marker).write_text, ("unpickled",))


def test_a_pickle_is_never_unpickled(lite_checkpoint: Path, tmp_path: Path):
    marker = tmp_path / "marker"
    trap = _Trap()
    trap.marker = str(marker)
    w, _ = _broken_copy(lite_checkpoint, tmp_path / "evil")
    w.write_bytes(pickle.dumps({"weights": trap}))
    with pytest.raises(DataError, match="not a readable safetensors file"):
        load_checkpoint(w)
    assert not marker.exists()
