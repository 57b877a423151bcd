"""ONNX Runtime backend of the :class:`~vlocnetpp_core.inference.localizer.Localizer` (``backend="onnx"``).

:class:`OnnxStep` runs the graph written by :mod:`vlocnetpp_core.inference.onnx_export` behind the same call
as ``VLocNetPP.step(image, state, K, depth) -> (StepOutput, StreamState)``, so the Localizer's
code path is the same for both backends (only the heads the Localizer reads are filled; ``taps``
stay empty; ``seg_logits`` stays None for the graph of a pose-only model, which has no such output).
Tensors cross the boundary without copies (``numpy()`` / ``from_numpy`` on CPU).

Which file (:func:`onnx_step_for`): ``NAME.onnx`` next to the checkpoint ``NAME.safetensors`` when
it was exported from these weights (its ``weights_id`` metadata matches the sidecar's), else a
graph exported once into the cache folder ``$VLOCNETPP_CACHE`` (default
``$XDG_CACHE_HOME/vlocnetpp``, i.e. ``~/.cache/vlocnetpp``) as ``onnx/<weights_id>.onnx``, reused on
the next start. A stale ``NAME.onnx`` (exported from other weights) is never used.

Session settings: graph optimisations all on (ONNX Runtime folds the batch norms into the
convolutions and fuses activations), ``intra_op_num_threads`` = ``num_threads`` (0: all cores but
one, as everywhere: :mod:`vlocnetpp_core.threads`), and idle worker threads sleep instead of spinning
(``session.intra_op.allow_spinning = 0``): in the node the CPU is shared with DDS and the camera
driver, and on a loaded machine spinning threads slow every step several times (see
docs/performance.md). ``device`` ``cuda``/``cuda:N`` uses the CUDA execution provider, which needs
the ``onnxruntime-gpu`` build.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import torch

from vlocnetpp_core.errors import DataError, UserError, require
from vlocnetpp_core.inference.onnx_export import export_step, read_metadata
from vlocnetpp_core.model import StepOutput, StreamState
from vlocnetpp_core.threads import resolve_threads


def cache_dir() -> Path:
    """``$VLOCNETPP_CACHE``, else ``$XDG_CACHE_HOME/vlocnetpp``, else ``~/.cache/vlocnetpp``."""
    if os.environ.get("VLOCNETPP_CACHE"):
        return Path(os.environ["VLOCNETPP_CACHE"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "vlocnetpp"


class OnnxStep:
    """One ONNX Runtime session of an exported streaming step; call it like ``VLocNetPP.step``."""

    def __init__(self, path: str | Path, device: str | torch.device = "cpu", num_threads: int = 0):
        ort = require("onnxruntime", "backend 'onnx'")

        self.path = Path(path)
        meta = read_metadata(self.path)
        self.weights_id = meta.get("weights_id", "")
        self.state_names: list[str] = json.loads(meta["state_names"])
        options = ort.SessionOptions()
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        options.intra_op_num_threads = resolve_threads(num_threads)
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        try:
            self.session = ort.InferenceSession(str(self.path), options, providers=_providers(torch.device(device)))
        except UserError:
            raise
        except Exception as err:  # onnxruntime's own exception types
            raise DataError(self.path, f"ONNX Runtime cannot load it: {err}") from None
        inputs = {i.name: i for i in self.session.get_inputs()}
        self.head_outputs = [o.name for o in self.session.get_outputs() if not o.name.startswith("next_")]
        self._zeros = {n: np.zeros(inputs[f"state_{n}"].shape, np.float32) for n in self.state_names}
        self.input_size = (int(inputs["image"].shape[3]), int(inputs["image"].shape[2]))  # (W, H)
        self._no_depth = np.zeros((1, 1, self.input_size[1], self.input_size[0]), np.float32)
        self._inputs = set(
            inputs
        )  # the exporter drops inputs the graph never reads: depth, use_depth without a depth head

    def __call__(
        self,
        image: torch.Tensor,
        state: StreamState | None = None,
        K: torch.Tensor | None = None,
        depth: torch.Tensor | None = None,
    ) -> tuple[StepOutput, StreamState]:
        """``image (1, 3, H, W)`` in [0, 1], ``K (1, 3, 3)``, ``depth (1, 1, H, W)`` metres or None -> heads and next
        state."""
        if tuple(image.shape) != (1, 3, self.input_size[1], self.input_size[0]):
            raise ValueError(
                f"{self.path} takes one (1, 3, {self.input_size[1]}, "
                f"{self.input_size[0]}) image, got {tuple(image.shape)}"
            )
        if K is None:
            raise ValueError("K (1, 3, 3), the intrinsics at the network input size, is required")
        feed = {
            "image": _array(image),
            "K": _array(K),
            "depth": self._no_depth if depth is None else _array(depth),
            "use_depth": np.array(depth is not None),
            "first": np.array(state is None),
        }
        for name in self.state_names:
            feed[f"state_{name}"] = self._zeros[name] if state is None else _array(getattr(state, name))
        feed = {k: v for k, v in feed.items() if k in self._inputs}
        results = [torch.from_numpy(r) for r in self.session.run(None, feed)]
        n = len(self.head_outputs)
        heads = dict(zip(self.head_outputs, results[:n], strict=True))
        new = StreamState(**dict(zip(self.state_names, results[n:], strict=True)))
        return StepOutput(**heads), new


def _array(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to("cpu", torch.float32).numpy())


def _providers(device: torch.device) -> list:
    ort = require("onnxruntime", "backend 'onnx'")

    if device.type == "cpu":
        return ["CPUExecutionProvider"]
    if device.type == "cuda":
        if "CUDAExecutionProvider" not in ort.get_available_providers():
            raise UserError(
                f"backend 'onnx' on device {str(device)!r} needs onnxruntime-gpu (the installed onnxruntime "
                f"offers {', '.join(ort.get_available_providers())})"
            )
        return [("CUDAExecutionProvider", {"device_id": device.index or 0}), "CPUExecutionProvider"]
    raise UserError(f"backend 'onnx' supports devices cpu and cuda, not {str(device)!r}")


def onnx_step_for(
    model: torch.nn.Module,
    meta: dict,
    device: str | torch.device = "cpu",
    num_threads: int = 0,
    next_to: str | Path | None = None,
) -> OnnxStep:
    """The :class:`OnnxStep` of a loaded checkpoint: ``next_to`` (``NAME.onnx``) when it matches these
    weights, else the cached export (made now when missing; see module doc)."""
    require("onnxruntime", "backend 'onnx'")  # before a possibly long export
    weights_id = str(meta.get("weights_id") or "")
    W, H = model.config.input_size
    if next_to is not None and Path(next_to).is_file():
        found = read_metadata(next_to)
        if weights_id and found.get("weights_id") == weights_id and found.get("input_size") == f"{W}x{H}":
            return OnnxStep(next_to, device, num_threads)
    if not weights_id:
        raise UserError(
            "backend 'onnx': the checkpoint has no weights_id to match an export with; "
            "export one with 'vlocnetpp export-onnx --checkpoint NAME.safetensors --out NAME.onnx'"
        )
    cached = cache_dir() / "onnx" / f"{weights_id}.onnx"
    if not cached.is_file():
        try:
            export_step(model, cached, weights_id=weights_id)
        except OSError as err:
            raise UserError(
                f"backend 'onnx': cannot write the exported graph to {cached} ({err}); set VLOCNETPP_CACHE "
                "to a writable folder or export next to the checkpoint with 'vlocnetpp export-onnx'"
            ) from None
    return OnnxStep(cached, device, num_threads)
