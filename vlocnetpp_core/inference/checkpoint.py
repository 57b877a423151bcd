"""Checkpoints: ``NAME.safetensors`` (weights) + ``NAME.json`` (everything needed to run them).

Loading never unpickles: weights are safetensors, the sidecar is JSON. Writing is atomic: both
files are written to temporary names in the target folder and moved into place with
``os.replace``, the sidecar last, so a reader sees either the old pair or the new one (a crash
between the two moves leaves new weights with the old sidecar, which the shared random
``weights_id`` in both files detects).

Sidecar keys (``docs/architecture.md`` "Checkpoint"):

* ``format`` / ``version``: ``"vlocnetpp-checkpoint"`` / 1; ``weights``: the weights file name;
  ``weights_id``: random id also stored in the safetensors metadata; ``dtype``: of the stored floats.
* ``model_config``: :meth:`ModelConfig.to_dict`; ``input_size``: ``[W, H]`` of the network input;
  ``normalization``: ``{"mean": [3], "std": [3]}`` (RGB in ``[0, 1]``, applied inside the model).
* ``class_names``, ``class_colors`` (RGB 0..255), one per class id.
* ``intrinsics``: default :class:`Intrinsics` at the network input size (used when a caller
  gives none); when the saver gives none, the approximate DeepLoc/ZED default scaled to it.
* ``training``: free-form summary (data, stage, step, ...).
* ``calibration``: ``pose_variance`` and ``odometry_variance``, six variances each for
  x, y, z (m^2) and rotation about x, y, z (rad^2) in the camera frame: the global pose error
  and the per-frame relative motion error, measured on validation data by ``vlocnetpp train``.
  Missing (or ``null``) entries take the conservative defaults :data:`DEFAULT_POSE_VARIANCE`
  (1 m, 5 deg standard deviation) and :data:`DEFAULT_ODOMETRY_VARIANCE` (10 cm, 1 deg per frame),
  and the sidecar then says ``"source": "default"``. Optional ``class_logit_offsets``: one offset per class added
  to the segmentation scores before the argmax (:mod:`vlocnetpp_core.inference.class_offsets`), with
  ``class_logit_offsets_source``.
"""

from __future__ import annotations

import json
import math
import os
import stat
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import torch

from vlocnetpp_core.camera.intrinsics import DEEPLOC_DEFAULT, Intrinsics
from vlocnetpp_core.classes import CLASS_COLORS, CLASS_NAMES
from vlocnetpp_core.errors import DataError

FORMAT = "vlocnetpp-checkpoint"
VERSION = 1
DEFAULT_POSE_VARIANCE: tuple[float, ...] = (1.0, 1.0, 1.0) + (math.radians(5.0) ** 2,) * 3
DEFAULT_ODOMETRY_VARIANCE: tuple[float, ...] = (0.1**2,) * 3 + (math.radians(1.0) ** 2,) * 3
_SUFFIXES = (".safetensors", ".json")
# The model shipped with the package, relative to share/vlocnetpp_ros/ (installed) or the source tree.
SHIPPED_MODEL = "models/vlocnetpp_lite.safetensors"


def checkpoint_paths(path: str | Path) -> tuple[Path, Path]:
    """``(NAME.safetensors, NAME.json)`` for ``NAME``, ``NAME.safetensors`` or ``NAME.json``."""
    path = Path(path)
    base = path.with_suffix("") if path.suffix in _SUFFIXES else path
    return base.with_name(base.name + ".safetensors"), base.with_name(base.name + ".json")


# --------------------------------------------------------------------------- writing


def save_checkpoint(
    path: str | Path, model: torch.nn.Module, meta: dict | None = None, dtype: torch.dtype = torch.float32
) -> Path:
    """Write ``model`` (a ``VLocNetPP``) and its sidecar atomically; returns the weights path.

    ``meta`` entries (``training``, ``intrinsics`` as a dict or :class:`Intrinsics`,
    ``calibration``, or any other JSON-able key) override the defaults derived from the model.
    Floating-point tensors are stored as ``dtype`` (``torch.float32`` or ``torch.float16``).
    """
    from safetensors.torch import save_file

    if dtype not in (torch.float32, torch.float16):
        raise ValueError(f"dtype must be torch.float32 or torch.float16, got {dtype}")
    weights, sidecar = checkpoint_paths(path)
    weights.parent.mkdir(parents=True, exist_ok=True)
    weights_id = uuid.uuid4().hex
    tensors = {
        k: (v.detach().to("cpu", dtype) if v.is_floating_point() else v.detach().cpu()).contiguous().clone()
        for k, v in model.state_dict().items()
    }
    info = build_sidecar(model.config, meta or {})
    info.update(weights=weights.name, weights_id=weights_id, dtype=str(dtype).removeprefix("torch."))
    text = _sidecar_text(info)
    tmp_w = weights.with_name(f".{weights.name}.tmp-{os.getpid()}")
    tmp_s = sidecar.with_name(f".{sidecar.name}.tmp-{os.getpid()}")
    try:
        save_file(tensors, str(tmp_w), metadata={"format": FORMAT, "weights_id": weights_id})
        tmp_s.write_text(text)
        os.chmod(tmp_w, stat.S_IMODE(tmp_s.stat().st_mode))  # safetensors creates 0600; use the umask's mode
        os.replace(tmp_w, weights)
        os.replace(tmp_s, sidecar)
    finally:
        for tmp in (tmp_w, tmp_s):
            tmp.unlink(missing_ok=True)
    return weights


def build_sidecar(config, meta: dict) -> dict[str, Any]:
    """The sidecar dict of a ``ModelConfig`` with ``meta`` entries on top (see the module doc)."""
    w, h = config.input_size
    n = config.num_classes
    names = list(CLASS_NAMES[:n]) + [f"class_{i}" for i in range(len(CLASS_NAMES), n)]
    colors = CLASS_COLORS[:n].tolist() + [[255, 255, 255]] * max(0, n - len(CLASS_COLORS))
    info: dict[str, Any] = {
        "format": FORMAT,
        "version": VERSION,
        "model_config": config.to_dict(),
        "input_size": [w, h],
        "normalization": {"mean": list(config.mean), "std": list(config.std)},
        "class_names": names,
        "class_colors": colors,
        "intrinsics": DEEPLOC_DEFAULT.resized(w, h).to_dict(),
        "training": {},
        "calibration": {},
    }
    info.update({k: (v.to_dict() if isinstance(v, Intrinsics) else v) for k, v in meta.items()})
    info["calibration"] = _complete_calibration(info.get("calibration") or {})
    return info


def _complete_calibration(calib: dict) -> dict:
    out = dict(calib)
    defaulted = False
    for key, default in (("pose_variance", DEFAULT_POSE_VARIANCE), ("odometry_variance", DEFAULT_ODOMETRY_VARIANCE)):
        if out.get(key) is None:
            out[key] = list(default)
            defaulted = True
    if defaulted:
        out.setdefault("source", "default")
    return out


def _sidecar_text(info: dict) -> str:
    return json.dumps(info, indent=2, default=_jsonable) + "\n"


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, (np.generic,)):
        return obj.item()
    if isinstance(obj, (np.ndarray, torch.Tensor)):
        return obj.tolist()
    if isinstance(obj, (Path, torch.dtype)):
        return str(obj)
    raise TypeError(f"checkpoint meta value of type {type(obj).__name__} is not JSON-serialisable")


def init_checkpoint(config, out: str | Path, seed: int = 0, meta: dict | None = None) -> Path:
    """Save a freshly initialised (untrained) model of ``config`` (``ModelConfig``, ``"lite"``,
    ``"paper"`` or a YAML path) to ``out``; returns the weights path. Deterministic for a seed."""
    from vlocnetpp_core.model import ModelConfig, VLocNetPP, load_model_config

    cfg = config if isinstance(config, ModelConfig) else load_model_config(config)
    torch.manual_seed(seed)
    model = VLocNetPP(cfg)
    info = {"training": {"stage": "init", "step": 0, "seed": seed, "note": "freshly initialised, untrained"}}
    return save_checkpoint(out, model, {**info, **(meta or {})})


# --------------------------------------------------------------------------- reading


def read_checkpoint_meta(path: str | Path) -> dict[str, Any]:
    """The sidecar of a checkpoint, checked (format, model config, intrinsics, calibration)."""
    weights, sidecar = checkpoint_paths(path)
    if not weights.is_file():
        raise DataError(weights, "no such checkpoint weights file")
    if not sidecar.is_file():
        raise DataError(
            sidecar, f"missing checkpoint sidecar (the JSON written next to {weights.name} by save_checkpoint)"
        )
    try:
        meta = json.loads(sidecar.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise DataError(sidecar, f"not valid JSON (truncated or corrupt?): {err}") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise DataError(sidecar, f'not a VLocNet++ checkpoint sidecar (expected "format": "{FORMAT}")')
    if int(meta.get("version", 0)) > VERSION:
        raise DataError(
            sidecar, f"checkpoint format version {meta.get('version')} is newer than this code reads ({VERSION})"
        )
    for key in ("model_config", "intrinsics"):
        if not isinstance(meta.get(key), dict):
            raise DataError(sidecar, f"missing or malformed '{key}'")
    try:
        Intrinsics.from_dict(meta["intrinsics"])
    except (KeyError, TypeError, ValueError) as err:
        raise DataError(sidecar, f"malformed 'intrinsics' ({err!r}); expected fx, fy, cx, cy, width, height") from None
    meta["calibration"] = calib = _complete_calibration(meta.get("calibration") or {})
    for key in ("pose_variance", "odometry_variance"):
        v = calib[key]
        if not (
            isinstance(v, list)
            and len(v) == 6
            and all(isinstance(x, (int, float)) and math.isfinite(x) and x >= 0 for x in v)
        ):
            raise DataError(
                sidecar, f"calibration.{key} must be 6 finite non-negative variances (x, y, z, rx, ry, rz), got {v!r}"
            )
    offsets = calib.get("class_logit_offsets")
    if offsets is not None and not (
        isinstance(offsets, list)
        and all(isinstance(x, (int, float)) and math.isfinite(x) for x in offsets)
        and len(offsets) == int(meta["model_config"].get("num_classes", len(offsets)))
    ):
        raise DataError(
            sidecar, f"calibration.class_logit_offsets must be one finite number per class, got {offsets!r}"
        )
    return meta


def update_calibration(path: str | Path, entries: dict) -> None:
    """Add ``entries`` to the sidecar's ``calibration`` in place (atomically; the weights and their ``weights_id``
    stay as they are)."""
    _, sidecar = checkpoint_paths(path)
    read_checkpoint_meta(path)  # refuses a sidecar that is not a checkpoint's
    raw = json.loads(sidecar.read_text())
    raw["calibration"] = {**(raw.get("calibration") or {}), **entries}
    tmp = sidecar.with_name(f".{sidecar.name}.tmp-{os.getpid()}")
    try:
        tmp.write_text(_sidecar_text(raw))
        os.replace(tmp, sidecar)
    finally:
        tmp.unlink(missing_ok=True)


def read_checkpoint_tensors(path: str | Path) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """``(tensors as stored, sidecar)`` without building a model (what training initialises from)."""
    from safetensors import safe_open

    weights, sidecar = checkpoint_paths(path)
    meta = read_checkpoint_meta(path)
    try:
        with safe_open(str(weights), framework="pt", device="cpu") as f:
            stored = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as err:  # safetensors raises its own error types (and OSError) for bad files
        raise DataError(weights, f"not a readable safetensors file (truncated or corrupt?): {err}") from None
    wid = meta.get("weights_id")
    if wid is not None and stored.get("weights_id") not in (None, wid):
        raise DataError(
            sidecar, f"sidecar does not belong to {weights.name} (weights_id differs; an interrupted save?)"
        )
    return tensors, meta


def load_checkpoint(path: str | Path, device: str | torch.device = "cpu"):
    """``(VLocNetPP in eval mode on device, float32; sidecar dict)``. Raises :class:`DataError`
    naming the file when it is missing, corrupt, or does not fit the model config it names."""
    from vlocnetpp_core.model import ModelConfig, VLocNetPP

    weights, sidecar = checkpoint_paths(path)
    tensors, meta = read_checkpoint_tensors(path)
    config = ModelConfig.from_dict(meta["model_config"], source=f"{sidecar} (model_config)")
    model = VLocNetPP(config)
    own = model.state_dict()
    missing = sorted(set(own) - set(tensors))
    unexpected = sorted(set(tensors) - set(own))
    wrong = sorted(k for k in set(own) & set(tensors) if own[k].shape != tensors[k].shape)
    if missing or unexpected or wrong:
        parts = [
            f"{len(v)} {what} (e.g. {v[0]})"
            for what, v in (("missing", missing), ("unexpected", unexpected), ("of another shape", wrong))
            if v
        ]
        raise DataError(
            weights, f"weights do not fit the model config in {sidecar.name}: " + ", ".join(parts) + " tensors"
        )
    bad = [k for k, v in tensors.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise DataError(weights, f"{len(bad)} weight tensors hold NaN or infinite values (e.g. {bad[0]})")
    model.load_state_dict(tensors)
    return model.to(device).eval(), meta


def calibration_variances(meta: dict) -> tuple[np.ndarray, np.ndarray]:
    """``(pose_variance (6,), odometry_variance (6,))`` float64 of a sidecar (defaults filled in)."""
    calib = _complete_calibration(meta.get("calibration") or {})
    return np.asarray(calib["pose_variance"], dtype=np.float64), np.asarray(
        calib["odometry_variance"], dtype=np.float64
    )


def shipped_checkpoint() -> Path:
    """The shipped model: ``share/vlocnetpp_ros/models/vlocnetpp_lite.safetensors`` of the installed
    package (found with ``ament_index_python`` when ``vlocnetpp_ros`` is on ``AMENT_PREFIX_PATH``), else
    the source tree's ``models/``. Raises ``FileNotFoundError`` naming where it looked."""
    candidates = []
    try:
        from ament_index_python.packages import get_package_share_directory

        candidates.append(Path(get_package_share_directory("vlocnetpp_ros")) / SHIPPED_MODEL)
    except Exception:  # PackageNotFoundError, or ament_index not importable
        pass
    source = Path(__file__).resolve().parents[2]
    if (source / "package.xml").is_file():  # a source checkout (editable install)
        candidates.append(source / SHIPPED_MODEL)
    for path in candidates:
        if path.is_file():
            return path
    looked = (
        ", ".join(map(str, candidates))
        or f"share/vlocnetpp_ros/{SHIPPED_MODEL} (vlocnetpp_ros is not on AMENT_PREFIX_PATH)"
    )
    raise FileNotFoundError(f"the shipped model is missing (looked for {looked})")


MAP_AUTO = "auto"  # the map setting that means NAME.map.npz beside NAME.safetensors


def resolve_map_path(checkpoint: str | Path, value: str | Path | None, what: str = "map", warn=None) -> Path | None:
    """The keyframe map a localizer of ``checkpoint`` refines against, from a map setting (the node's parameter
    ``map``, ``--map`` of ``replay`` and ``evaluate-bag``), named ``what`` in messages: None or ``""``: none (no
    refinement); ``"auto"``: ``NAME.map.npz`` beside ``NAME.safetensors`` when that file exists, else none, and
    ``warn`` (a callable, if given) gets one line saying so (not when the checkpoint itself is missing: loading it
    says so); anything else: that file, a :class:`DataError` naming it when it is missing or a folder."""
    if value is None or str(value) == "":
        return None
    if str(value) == MAP_AUTO:
        weights = checkpoint_paths(checkpoint)[0]
        path = weights.with_name(weights.name.removesuffix(".safetensors") + ".map.npz")
        if path.is_file():
            return path
        if warn is not None and weights.is_file():
            warn(
                f"{what} '{MAP_AUTO}': no keyframe map beside the checkpoint "
                f"({path} is missing): running without refinement "
                "(build one with 'vlocnetpp map build')"
            )
        return None
    path = Path(value).expanduser()
    if path.is_dir():
        raise DataError(path, f"{what}: a folder, not a keyframe map file (.npz from 'vlocnetpp map build')")
    if not path.is_file():
        raise DataError(
            path,
            f"{what}: no such keyframe map file (build one with 'vlocnetpp map build', or give '{MAP_AUTO}' "
            "for NAME.map.npz beside the checkpoint, or empty for no refinement)",
        )
    return path
