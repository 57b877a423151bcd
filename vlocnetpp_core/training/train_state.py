"""Resumable training state (optimiser, learned loss weights, RNG, step) without pickle.

Written as ``train_state.safetensors`` (every tensor) + ``train_state.json`` (everything
else) into the run folder, atomically: both go to temporary names first and the JSON, which
names the step, is renamed last, so an interrupted write leaves the previous state intact.
"""

from __future__ import annotations

import json
import os
import random
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from vlocnetpp_core.errors import UserError

STATE_NAME = "train_state"


def _flatten_optimizer(opt_state: dict) -> tuple[dict[str, torch.Tensor], dict]:
    tensors: dict[str, torch.Tensor] = {}
    scalars: dict[str, dict[str, Any]] = {}
    for pid, entry in opt_state["state"].items():
        for key, value in entry.items():
            if isinstance(value, torch.Tensor):
                tensors[f"optimizer.{pid}.{key}"] = value.detach().cpu().contiguous()
            else:
                scalars.setdefault(str(pid), {})[key] = value
    return tensors, {"param_groups": opt_state["param_groups"], "scalars": scalars}


def _unflatten_optimizer(tensors: dict[str, torch.Tensor], meta: dict) -> dict:
    state: dict[int, dict[str, Any]] = {}
    for name, value in tensors.items():
        if name.startswith("optimizer."):
            _, pid, key = name.split(".", 2)
            state.setdefault(int(pid), {})[key] = value
    for pid, entry in meta["scalars"].items():
        state.setdefault(int(pid), {}).update(entry)
    return {"state": state, "param_groups": meta["param_groups"]}


def save_train_state(
    run_dir: Path, *, step: int, optimizer: torch.optim.Optimizer, criterion: torch.nn.Module, extra: dict
) -> None:
    """Write the resumable state of a run at ``step`` (after the optimiser update of that step)."""
    run_dir = Path(run_dir)
    tensors, opt_meta = _flatten_optimizer(optimizer.state_dict())
    for name, value in criterion.state_dict().items():
        tensors[f"criterion.{name}"] = value.detach().cpu().contiguous()
    tensors["rng.torch"] = torch.get_rng_state()
    meta = {
        "step": step,
        "optimizer": opt_meta,
        "rng": {"python": _jsonable(random.getstate()), "numpy": _jsonable(np.random.get_state())},
        **extra,
    }
    tmp_st = run_dir / f".{STATE_NAME}.safetensors.tmp"
    tmp_js = run_dir / f".{STATE_NAME}.json.tmp"
    save_file(tensors, str(tmp_st))
    tmp_js.write_text(json.dumps(meta))
    os.replace(tmp_st, run_dir / f"{STATE_NAME}.safetensors")
    os.replace(tmp_js, run_dir / f"{STATE_NAME}.json")


def load_train_state(
    run_dir: Path, *, optimizer: torch.optim.Optimizer | None, criterion: torch.nn.Module | None
) -> dict:
    """Restore optimiser, loss weights and RNG from ``run_dir``; returns the JSON metadata (with ``step``)."""
    run_dir = Path(run_dir)
    st, js = run_dir / f"{STATE_NAME}.safetensors", run_dir / f"{STATE_NAME}.json"
    if not (st.is_file() and js.is_file()):
        raise UserError(f"{run_dir}: no training state to resume ({st.name} and {js.name} missing)")
    try:
        meta = json.loads(js.read_text())
        tensors = load_file(str(st))
    except (OSError, ValueError) as err:
        raise UserError(f"{st}: unreadable training state ({err})") from err
    if optimizer is not None:
        optimizer.load_state_dict(_unflatten_optimizer(tensors, meta["optimizer"]))
    if criterion is not None:
        crit = {k[len("criterion.") :]: v for k, v in tensors.items() if k.startswith("criterion.")}
        criterion.load_state_dict(crit)
    torch.set_rng_state(tensors["rng.torch"])
    random.setstate(_tuplify(meta["rng"]["python"]))
    np.random.set_state(_tuplify(meta["rng"]["numpy"]))
    return meta


def load_criterion_weights(run_dir: Path) -> dict[str, torch.Tensor]:
    """The learned loss weights saved with a run (empty if the run has no state)."""
    st = Path(run_dir) / f"{STATE_NAME}.safetensors"
    if not st.is_file():
        return {}
    return {k[len("criterion.") :]: v for k, v in load_file(str(st)).items() if k.startswith("criterion.")}


def _jsonable(obj):
    if isinstance(obj, np.ndarray):
        return {"__ndarray__": obj.tolist(), "dtype": str(obj.dtype)}
    if isinstance(obj, (tuple, list)):
        return [_jsonable(o) for o in obj]
    return obj


def _tuplify(obj):
    if isinstance(obj, dict) and "__ndarray__" in obj:
        return np.array(obj["__ndarray__"], dtype=obj["dtype"])
    if isinstance(obj, list):
        return tuple(_tuplify(o) for o in obj)
    return obj
