"""The paper-config step of ``vlocnetpp bench`` (:func:`paper_step`): the cached streaming step against recomputing
the previous frame and a plain ResNet-50, with its ONNX Runtime, CUDA-graph and ``torch.compile`` variants."""

from __future__ import annotations

import contextlib
import dataclasses
import time
from pathlib import Path

import numpy as np
import torch

from vlocnetpp_core.bench.cuda_graph import max_abs_difference
from vlocnetpp_core.bench.timing import interleaved, median, synchronizer
from vlocnetpp_core.errors import UserError


def paper_step(
    config: str,
    input_size: tuple[int, int] | None,
    frames: list[np.ndarray],
    device: str,
    repetitions: int,
    warmup: int,
    workdir: Path,
    threads: int = 0,
) -> dict:
    """Paper-config streaming step with the cached state (torch, the ONNX Runtime graph of the same
    weights, and on CUDA the torch step replayed from a CUDA graph and compiled by ``torch.compile``)
    vs recomputing the previous frame, and one plain ResNet-50 forward (torch, eager) at the same input size; torch in
    ``torch.inference_mode``, eval mode. Also the compute of the cached step and of the ResNet-50
    (``paper_step_gmac``, ``resnet50_gmac``: multiply-accumulates of convolutions and matrix products).

    "Recompute" is what a network without the cache does for frame t: a first-frame step on frame
    t-1 (which yields its Res5a, odometry Res4 and semantic Res4f/Res5c; its heads and decoder
    are computed too, a few percent of the step) followed by the step on frame t. The graph is
    exported into ``workdir``; where it cannot be exported or run (no ``onnx`` or ``onnxruntime``
    package, no ONNX Runtime provider for ``device``), ``paper_step_onnx`` is None and
    ``onnx_error`` says why; likewise ``paper_step_cuda_graph`` / ``cuda_graph_error`` and
    ``paper_step_compiled`` / ``compiled_error`` on CUDA, with ``cuda_graph_max_abs_diff`` /
    ``compiled_max_abs_diff`` against the eager step.
    """
    from torch.utils.flop_counter import FlopCounterMode

    from vlocnetpp_core.bench.resnet50 import ResNet50
    from vlocnetpp_core.model import VLocNetPP, load_model_config

    cfg = load_model_config(config)
    if input_size is not None:
        cfg = dataclasses.replace(cfg, input_size=tuple(input_size))
    W, H = cfg.input_size
    torch.manual_seed(0)
    model = VLocNetPP(cfg).eval().to(device)
    resnet = ResNet50().eval().to(device)
    prev, cur = (_image_tensor(f, (W, H), device) for f in (frames[0], frames[1]))
    K = torch.tensor([[[0.55 * W, 0.0, (W - 1) / 2], [0.0, 0.55 * W, (H - 1) / 2], [0.0, 0.0, 1.0]]], device=device)
    result: dict = {"input_size": [W, H], "paper_step_onnx": None}
    onnx_step = _onnx_paper_step(model, workdir / f"{cfg.name}-{W}x{H}.onnx", device, threads, result)
    with torch.inference_mode():
        _, state = model.step(prev, None, K)
        for name, call in (
            ("paper_step_gmac", lambda: model.step(cur, state, K)),
            ("resnet50_gmac", lambda: resnet(cur)),
        ):
            counter = FlopCounterMode(display=False)
            with counter:
                call()
            result[name] = counter.get_total_flops() / 2e9

        def recompute() -> None:
            _, s = model.step(prev, None, K)
            model.step(cur, s, K)

        cases = {"cached": lambda: model.step(cur, state, K), "recompute": recompute, "resnet50": lambda: resnet(cur)}
        if onnx_step is not None:
            _, onnx_state = onnx_step(prev, None, K)
            cases["onnx"] = lambda: onnx_step(cur, onnx_state, K)
        if torch.device(device).type == "cuda":
            for name, make in (("cuda_graph", _cuda_graph_step), ("compiled", _compiled_step)):
                fast_step = make(model, cur, state, K, result)
                if fast_step is not None:
                    cases[name] = lambda fast_step=fast_step: fast_step(cur, state, K)
        times = interleaved(cases, repetitions, warmup, synchronizer(device))
    result.update(
        {
            "paper_step_cached": median(times["cached"]),
            "paper_step_recompute": median(times["recompute"]),
            "resnet50_forward": median(times["resnet50"]),
        }
    )
    for name in ("onnx", "cuda_graph", "compiled"):
        if name in times:
            result[f"paper_step_{name}"] = median(times[name])
    return result


def _onnx_paper_step(model: torch.nn.Module, path: Path, device: str, threads: int, result: dict):
    """The ONNX Runtime session of ``model``'s exported step, or None with ``result["onnx_error"]`` set."""
    from vlocnetpp_core.inference.onnx_backend import OnnxStep
    from vlocnetpp_core.inference.onnx_export import export_step

    try:
        start = time.perf_counter()
        graph = export_step(model, path)
        result["paper_onnx_export"] = time.perf_counter() - start
        return OnnxStep(graph, device, threads)
    except UserError as err:
        result["onnx_error"] = str(err)
    return None


def _cuda_graph_step(model: torch.nn.Module, image: torch.Tensor, state, K: torch.Tensor, result: dict):
    """The captured step (:class:`.cuda_graph.CudaGraphStep`) checked against the eager one, or None with
    ``result["cuda_graph_error"]`` set (capture fails on an operation that synchronises with the host)."""
    from vlocnetpp_core.bench.cuda_graph import CudaGraphStep

    try:
        start = time.perf_counter()
        graph_step = CudaGraphStep(model, image, state, K)
        result["cuda_graph_capture"] = time.perf_counter() - start
        result["cuda_graph_max_abs_diff"] = max_abs_difference(
            graph_step(image, state, K)[0], model.step(image, state, K)[0]
        )
        return graph_step
    except (RuntimeError, ValueError) as err:
        result["cuda_graph_error"] = f"capture failed: {_first_line(err)}"
        with contextlib.suppress(Exception):  # the device may be unusable after a failed capture
            torch.cuda.synchronize()
        return None


def _compiled_step(model: torch.nn.Module, image: torch.Tensor, state, K: torch.Tensor, result: dict):
    """``torch.compile(model.step, mode="reduce-overhead")`` (inductor kernels replayed from CUDA graphs),
    compiled by its first calls here (``paper_compile`` seconds) and checked against the eager step, or
    None with ``result["compiled_error"]`` set. CUDA only: on this CPU it compiled for minutes to run
    slower than eager (docs/performance.md)."""
    try:
        start = time.perf_counter()
        step = torch.compile(model.step, mode="reduce-overhead")
        for _ in range(3):  # compile, then record the CUDA graph
            out, _ = step(image, state, K)
        torch.cuda.synchronize()
        result["paper_compile"] = time.perf_counter() - start
        result["compiled_max_abs_diff"] = max_abs_difference(out, model.step(image, state, K)[0])
        return step
    except Exception as err:  # dynamo / inductor raise many types; the variant is optional
        result["compiled_error"] = f"torch.compile failed: {_first_line(err)}"
        return None


def _first_line(err: BaseException) -> str:
    """The first line of an exception's message (compiler errors run to pages), else its type."""
    return (str(err).strip().splitlines() or [type(err).__name__])[0]


def _image_tensor(rgb: np.ndarray, size: tuple[int, int], device: str) -> torch.Tensor:
    from vlocnetpp_core.inference.network_input import image_tensor
    from vlocnetpp_core.inference.preprocess import resize_image

    return image_tensor(resize_image(rgb, size)).to(device)
