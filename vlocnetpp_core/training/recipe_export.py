"""The ``export`` step of a recipe: final weights in the shipped precision, calibration, retrieval reference."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from vlocnetpp_core.errors import UserError


def export_weights(recipe, out: Path) -> Path:
    """Write ``recipe.export`` (see :mod:`vlocnetpp_core.training.recipe`) and return the weights path.

    The covariance calibration is the exported run's (from its validation); when that run did not
    validate, the pose variances come from the ``calibration.pose`` stage and the odometry variances
    from the ``calibration.odometry`` stage (their ``best`` sidecars).
    """
    from vlocnetpp_core.evaluation.retrieval import ReferenceSet, open_reference, reference_of
    from vlocnetpp_core.inference.checkpoint import load_checkpoint, save_checkpoint
    from vlocnetpp_core.training.recipe import dataset_path

    spec = recipe.export  # checked by load_recipe
    weights = spec.get("weights", "best")
    source = out / spec["stage"] / weights
    if not source.with_suffix(".safetensors").is_file():  # best: no validation of the run scored (every score NaN)
        raise UserError(
            f"{recipe.path}: export weights '{weights}': {source.with_suffix('.safetensors')} was not written "
            f"by stage {spec['stage']}"
        )
    dtype = getattr(torch, str(spec.get("dtype", "float16")))  # one of recipe.EXPORT_DTYPES
    model, meta = load_checkpoint(source)
    calibration = meta.get("calibration") or {}
    if calibration.get("source", "default") == "default" and spec.get("calibration"):
        calibration = _stage_calibration(recipe, out, spec["calibration"])
    target = Path(spec["to"])
    if not target.is_absolute():
        target = Path.cwd() / target
    path = save_checkpoint(
        target,
        model,
        {"training": meta["training"], "calibration": calibration, "intrinsics": meta["intrinsics"]},
        dtype=dtype,
    )
    if spec.get("reference"):
        names = spec["reference"]  # a list of dataset names (load_recipe)
        reference = ReferenceSet.concat([open_reference(dataset_path(recipe, name, out)) for name in names])
        reference.source = (
            f"recipe {recipe.path.name}, "
            + "; ".join(f"dataset '{n}' ({recipe.datasets[n]})" for n in names)
            + ", train split"
        )
        reference.save(reference_of(path))
    if spec.get("class_offsets"):
        from vlocnetpp_core.inference.class_offsets import calibrate

        name = spec["class_offsets"]
        before, after = calibrate(path, dataset_path(recipe, name, out), "test", progress=False)
        print(f"class offsets fitted on dataset '{name}' (test split): mean IoU {before:.4f} -> {after:.4f}")
    return path


def _stage_calibration(recipe, out: Path, stages: dict) -> dict:
    """Pose variances from the sidecar of ``stages['pose']``'s weights (``best`` or ``last``), odometry variances from
    ``stages['odometry']``'s."""
    from vlocnetpp_core.training.recipe import stage_weights

    parts = {}
    for kind, stage in stages.items():
        sidecar = stage_weights(recipe, stage, out).with_suffix(".json")
        if not sidecar.is_file():
            raise UserError(f"calibration: {sidecar} not found")
        parts[kind] = json.loads(sidecar.read_text())["calibration"]
    return {
        "pose_variance": parts["pose"]["pose_variance"],
        "odometry_variance": parts["odometry"]["odometry_variance"],
        "source": "validation of the single-task stages: " + ", ".join(f"{k} from {v}" for k, v in stages.items()),
    }
