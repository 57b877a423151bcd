"""The streaming step replayed from a captured CUDA graph (``vlocnetpp bench --device cuda``).

At batch 1 on a fast GPU an eager step is bound by launching its kernels from Python, not by their
arithmetic (one plain ResNet-50 forward: about 3.1 ms on an H100 for 9.3 GMAC). A CUDA graph
records the kernels of one ``VLocNetPP.step`` with a previous-frame state once and replays them
with a single launch. Contract: CUDA only, the input size, batch and state shapes of the capture,
and the model in eval mode under ``torch.inference_mode``; the returned outputs and state are the
graph's own buffers, overwritten by the next call (copy what must outlive it).

Not yet used by the Localizer: measured in the bench first (it needs a GPU, which the development
machine does not have).
"""

from __future__ import annotations

from dataclasses import fields

import torch

from vlocnetpp_core.model import StepOutput, StreamState


class CudaGraphStep:
    """``step(image, state, K) -> (StepOutput, StreamState)`` of ``model`` as one captured CUDA graph."""

    def __init__(
        self, model: torch.nn.Module, image: torch.Tensor, state: StreamState, K: torch.Tensor, warmup: int = 3
    ):
        """``image (1, 3, H, W)``, ``K (1, 3, 3)`` and every tensor of ``state`` on the same CUDA device."""
        if image.device.type != "cuda":
            raise ValueError(f"CUDA graphs need CUDA tensors, got the image on {image.device}")
        self._image, self._K = image.clone(), K.clone()
        self._state = StreamState(
            **{
                f.name: None if getattr(state, f.name) is None else getattr(state, f.name).clone()
                for f in fields(state)
            }
        )
        side = torch.cuda.Stream(
            image.device
        )  # warm-up on a side stream (cuDNN autotuning, allocations), as capture requires
        side.wait_stream(torch.cuda.current_stream(image.device))
        with torch.cuda.stream(side):
            for _ in range(warmup):
                model.step(self._image, self._state, self._K)
        torch.cuda.current_stream(image.device).wait_stream(side)
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph):
            self._out, self._next = model.step(self._image, self._state, self._K)

    def __call__(self, image: torch.Tensor, state: StreamState, K: torch.Tensor) -> tuple[StepOutput, StreamState]:
        self._image.copy_(image)
        self._K.copy_(K)
        for f in fields(state):
            value = getattr(state, f.name)
            if value is not None:
                getattr(self._state, f.name).copy_(value)
        self.graph.replay()
        return self._out, self._next


def max_abs_difference(a: StepOutput, b: StepOutput) -> float:
    """Largest absolute difference over the pose, odometry and segmentation heads of two step outputs (heads that
    neither ran, such as the segmentation of a pose-only model, are left out)."""
    return max(
        float((x - y).abs().max())
        for x, y in (
            (a.xyz, b.xyz),
            (a.quat, b.quat),
            (a.rel_xyz, b.rel_xyz),
            (a.rel_quat, b.rel_quat),
            (a.seg_logits, b.seg_logits),
        )
        if x is not None or y is not None
    )
