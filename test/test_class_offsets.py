"""Per-class segmentation offsets: fitted for mean IoU, written into the sidecar by ``vlocnetpp calibrate-classes``
(weights untouched), applied by the localizer before the argmax."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from vlocnetpp_core.errors import DataError
from vlocnetpp_core.inference.class_offsets import fit_class_offsets
from vlocnetpp_core.inference.localizer import Localizer

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "models" / "vlocnetpp_lite"


def test_the_fit_undoes_a_bias_against_a_class():
    g = torch.Generator().manual_seed(0)
    labels = torch.randint(0, 3, (4, 16, 16), generator=g)
    scores = torch.nn.functional.one_hot(labels, 3).permute(0, 3, 1, 2).float() * 2.0
    scores = scores + torch.randn(scores.shape, generator=g)
    scores[:, 2] -= 1.5  # class 2 under-predicted
    offsets, before, after = fit_class_offsets(scores.half(), labels)
    assert after > before + 0.05
    assert offsets[2] > offsets[0] and offsets[2] > offsets[1]
    assert abs(float(offsets.sum())) < 1e-5


def _copy_shipped(tmp_path: Path) -> Path:
    for suffix in (".safetensors", ".json"):
        shutil.copy(SHIPPED.with_suffix(suffix), tmp_path / f"m{suffix}")
    return tmp_path / "m.safetensors"


def test_calibrate_classes_writes_offsets_that_the_localizer_applies(tmp_path):
    data = tmp_path / "visits"
    synth = [sys.executable, "-m", "vlocnetpp_core.cli", "synth", str(data), "--seed", "5", "--loops", "0"]
    subprocess.run([*synth, "--test-loops", "1", "--frames-per-loop", "8", "--no-progress"], check=True, cwd=ROOT)
    ckpt = _copy_shipped(tmp_path)
    weights = ckpt.read_bytes()
    run = subprocess.run(
        [sys.executable, "-m", "vlocnetpp_core.cli", "calibrate-classes", str(ckpt), "--data", str(data)],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert run.returncode == 0, run.stderr
    before, after = (float(v) for v in run.stdout.strip().rsplit(" ", 3)[1::2])
    assert after >= before
    calibration = json.loads(ckpt.with_suffix(".json").read_text())["calibration"]
    assert len(calibration["class_logit_offsets"]) == 10 and "pose_variance" in calibration
    assert ckpt.read_bytes() == weights  # the weights stay as they were

    image = np.full((180, 320, 3), 120, np.uint8)
    plain = Localizer.from_checkpoint(SHIPPED.with_suffix(".safetensors")).step(image, "rgb8", 0.0).mask
    offsets = [0.0] * 10
    offsets[7] = 1000.0  # one class's offset beyond any score: every pixel is that class
    sidecar = json.loads(ckpt.with_suffix(".json").read_text())
    sidecar["calibration"]["class_logit_offsets"] = offsets
    ckpt.with_suffix(".json").write_text(json.dumps(sidecar))
    forced = Localizer.from_checkpoint(ckpt).step(image, "rgb8", 0.0)
    assert (forced.mask == 7).all() and not (plain == 7).all()

    sidecar["calibration"]["class_logit_offsets"] = offsets[:9]  # one short: refused, naming the sidecar
    ckpt.with_suffix(".json").write_text(json.dumps(sidecar))
    with pytest.raises(DataError, match="class_logit_offsets must be one finite number per class"):
        Localizer.from_checkpoint(ckpt)
