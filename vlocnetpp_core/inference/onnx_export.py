"""``vlocnetpp export-onnx``: one streaming step of a checkpoint as an ONNX graph, state in and out.

The graph is the model's own :meth:`VLocNetPP.step` traced at the checkpoint's input size, batch 1,
opset :data:`OPSET`, with the temporal state as explicit tensors:

============================ ============================ =============================================
inputs                       shape                        meaning
============================ ============================ =============================================
``image``                    ``(1, 3, H, W)`` float32     RGB in ``[0, 1]`` at the network input size
``K``                        ``(1, 3, 3)`` float32        intrinsics at ``W x H``
``depth``                    ``(1, 1, H, W)`` float32     metres (0 = invalid), used when ``use_depth``
``use_depth``                ``()`` bool                  warp with ``depth`` instead of the predicted one
``first``                    ``()`` bool                  first frame: the ``state_*`` inputs are ignored
``state_<name>``             see :class:`StreamState`     previous frame's features (zeros when ``first``)
============================ ============================ =============================================

A model without a depth head (``warping`` off, or a pose-only model) never reads ``depth`` and
``use_depth``, and the exporter leaves them out of its graph; :class:`~vlocnetpp_core.inference.onnx_backend.OnnxStep`
feeds only the inputs a graph has.

Outputs: ``xyz (1, 3)``, ``quat (1, 4)``, ``rel_xyz (1, 3)``, ``rel_quat (1, 4)``, ``seg_logits
(1, C, H, W)`` (not in the graph of a pose-only model: :func:`head_outputs`) and ``next_<name>``
(the state to feed to the next step). ``<name>`` are the
:class:`StreamState` fields the config produces (``res5a``, ``odo_res4``, ``sem_res4f``, ``sem_res5c``
for the shipped configs), listed in the ``state_names`` metadata entry.

First frame (the choice): one graph, not two. ``first`` selects, with ``Where`` nodes at the four
places where the model fuses the previous frame (odometry Res5 input, temporal Res5a AWF, the two
warp AWFs), the current frame's own features, which is exactly what ``step(state=None)`` does;
the state inputs are then zeros and the warp of zeros that is computed alongside is discarded. So
one graph (one copy of the weights) reproduces the PyTorch stream frame for frame, the first frame
included. The selections are made by forward hooks on those modules while tracing; the model's
code runs unchanged.

Metadata (``metadata_props``): ``vlocnetpp_format`` (:data:`FORMAT`), ``weights_id`` of the
checkpoint it came from (a stale export is detected), ``input_size`` ``WxH``, ``state_names``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import tempfile
import warnings
from collections.abc import Iterator
from dataclasses import fields
from pathlib import Path

import torch
from torch import nn

from vlocnetpp_core.errors import DataError, UserError, require
from vlocnetpp_core.outputs import refuse_existing

FORMAT = "vlocnetpp-onnx-step"
VERSION = 1
OPSET = 17
HEAD_OUTPUTS = ("xyz", "quat", "rel_xyz", "rel_quat", "seg_logits")


def head_outputs(model: nn.Module) -> list[str]:
    """The :data:`HEAD_OUTPUTS` a step of ``model`` fills: no ``seg_logits`` without the semantic stream."""
    return [k for k in HEAD_OUTPUTS if k != "seg_logits" or model.config.semantic_stream]


def state_names(model: nn.Module) -> list[str]:
    """The :class:`StreamState` fields a step of ``model`` fills (depends on the config's ablation switches)."""
    from vlocnetpp_core.model import StreamState

    cfg = model.config
    present = {"res5a": cfg.temporal_fusion, "odo_res4": True, "sem_res4f": cfg.warping, "sem_res5c": cfg.warping}
    return [f.name for f in fields(StreamState) if present[f.name]]


class StreamingStepGraph(nn.Module):
    """``VLocNetPP.step`` with the state as flat tensors and a ``first`` flag (see module doc)."""

    def __init__(self, model: nn.Module):
        super().__init__()
        self.model = model
        self.state_names = state_names(model)
        self.head_outputs = head_outputs(model)

    def forward(
        self,
        image: torch.Tensor,
        K: torch.Tensor,
        depth: torch.Tensor,
        use_depth: torch.Tensor,
        first: torch.Tensor,
        *state: torch.Tensor,
    ) -> tuple[torch.Tensor, ...]:
        from vlocnetpp_core.model import StreamState

        with _first_frame_selection(self.model, first, depth, use_depth):
            out, new = self.model.step(image, StreamState(**dict(zip(self.state_names, state, strict=True))), K)
        return tuple(getattr(out, k) for k in self.head_outputs) + tuple(getattr(new, k) for k in self.state_names)


@contextlib.contextmanager
def _first_frame_selection(
    model: nn.Module, first: torch.Tensor, depth: torch.Tensor, use_depth: torch.Tensor
) -> Iterator[None]:
    """Hooks: where ``first``, every fusion with the previous frame gets the current frame's own
    features (what ``step(state=None)`` does); where ``use_depth``, the given depth replaces the
    predicted one (what ``step(depth=...)`` does)."""

    def own_as_previous(previous_arg: int, own_arg: int):
        def hook(_module, args):
            args = list(args)
            args[previous_arg] = torch.where(first, args[own_arg], args[previous_arg])
            return tuple(args)

        return hook

    handles = [model.odometry.register_forward_pre_hook(own_as_previous(0, 1))]  # OdometryStream(prev_res4, res4)
    warp_awfs = () if model.semantic is None else (model.semantic.warp_fusion_res4f, model.semantic.warp_fusion_res5c)
    for awf in (model.global_stream.temporal_fusion, *warp_awfs):
        if awf is not None:  # AWF(current, previous)
            handles.append(awf.register_forward_pre_hook(own_as_previous(1, 0)))
    if model.depth_head is not None:
        handles.append(
            model.depth_head.register_forward_hook(lambda _m, _a, predicted: torch.where(use_depth, depth, predicted))
        )
    try:
        yield
    finally:
        for h in handles:
            h.remove()


def example_inputs(model: nn.Module, input_size: tuple[int, int] | None = None) -> tuple[torch.Tensor, ...]:
    """Inputs of a first frame, in graph order: mid-grey image, plausible K, zero depth and state."""
    W, H = input_size or tuple(model.config.input_size)
    device = next(model.parameters()).device
    image = torch.full((1, 3, H, W), 0.5, device=device)
    K = torch.tensor([[[0.9 * W, 0.0, (W - 1) / 2], [0.0, 0.9 * W, (H - 1) / 2], [0.0, 0.0, 1.0]]], device=device)
    with torch.inference_mode():
        _, state = model.step(image, None, K)
    zeros = [torch.zeros_like(getattr(state, name)) for name in state_names(model)]
    flag = torch.tensor(True, device=device)
    return (image, K, torch.zeros(1, 1, H, W, device=device), torch.tensor(False, device=device), flag, *zeros)


def export_step(
    model: nn.Module, out: str | Path, weights_id: str | None = None, input_size: tuple[int, int] | None = None
) -> Path:
    """Write the streaming-step graph of ``model`` (eval mode, CPU or GPU) to ``out`` atomically; returns the path."""
    onnx = require("onnx", "ONNX export")

    out = Path(out)
    model = model.eval()
    graph = StreamingStepGraph(model).eval()  # the exporter restores the wrapper's mode onto the model afterwards
    inputs = example_inputs(model, input_size)
    W, H = inputs[0].shape[-1], inputs[0].shape[-2]
    names_in = ["image", "K", "depth", "use_depth", "first"] + [f"state_{n}" for n in graph.state_names]
    names_out = graph.head_outputs + [f"next_{n}" for n in graph.state_names]
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent)
    os.close(fd)
    try:
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")  # TracerWarnings about Python-side shape checks, deprecation notes
            torch.onnx.export(
                graph,
                inputs,
                tmp,
                dynamo=False,
                opset_version=OPSET,
                input_names=names_in,
                output_names=names_out,
                do_constant_folding=True,
            )
        proto = onnx.load(tmp)
        meta = {
            "vlocnetpp_format": f"{FORMAT}/{VERSION}",
            "weights_id": weights_id or "",
            "input_size": f"{W}x{H}",
            "state_names": json.dumps(graph.state_names),
        }
        for key, value in meta.items():
            proto.metadata_props.add(key=key, value=value)
        onnx.save(proto, tmp)
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return out


def export_checkpoint(checkpoint: str | Path, out: str | Path) -> Path:
    """Load a checkpoint (``NAME.safetensors`` + ``NAME.json``) and export its streaming step to ``out``."""
    from vlocnetpp_core.inference.checkpoint import load_checkpoint

    model, meta = load_checkpoint(checkpoint)
    return export_step(model, out, weights_id=meta.get("weights_id"))


def read_metadata(path: str | Path) -> dict[str, str]:
    """The ``metadata_props`` of an exported step graph; :class:`DataError` when it is not one."""
    onnx = require("onnx", "reading an exported ONNX graph")

    path = Path(path)
    if not path.is_file():
        raise DataError(path, "no such ONNX file")
    try:
        proto = onnx.load(str(path), load_external_data=False)
    except Exception as err:  # onnx raises DecodeError / its own errors for bad files
        raise DataError(path, f"not a readable ONNX model (truncated or corrupt?): {err}") from None
    meta = {p.key: p.value for p in proto.metadata_props}
    if meta.get("vlocnetpp_format") != f"{FORMAT}/{VERSION}":
        raise DataError(
            path, f"not a VLocNet++ streaming-step graph (made by 'vlocnetpp export-onnx', format {FORMAT}/{VERSION})"
        )
    return meta


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--checkpoint", required=True, metavar="NAME.safetensors", help="checkpoint to export (NAME.json next to it)"
    )
    p.add_argument(
        "--out",
        required=True,
        metavar="MODEL.onnx",
        help="output ONNX file (the Localizer's onnx backend looks for NAME.onnx next to the checkpoint)",
    )
    p.add_argument("--force", action="store_true", help="replace MODEL.onnx if it exists")


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    refuse_existing(out, args.force)
    if out.suffix != ".onnx":
        raise UserError(f"--out {out}: expected a .onnx file name")
    path = export_checkpoint(args.checkpoint, out)
    meta = read_metadata(path)
    print(
        f"wrote {path} ({path.stat().st_size / 2**20:.1f} MiB): streaming step at {meta['input_size']}, "
        f"state {', '.join(json.loads(meta['state_names']))}, opset {OPSET}"
    )
    return 0
