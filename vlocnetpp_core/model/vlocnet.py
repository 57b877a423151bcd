"""The assembled VLocNet++ network: global pose, Siamese odometry and AdapNet semantic streams.

Data flow of one streaming :meth:`VLocNetPP.step` for frame ``t`` (``C_i`` = output channels of
Res_i, spatial strides in brackets; ``prev`` is the :class:`StreamState` of frame ``t-1``)::

    image -> trunk (stem, Res2, Res3) [8] ---------------------------- shared by global and odometry I_t
      odometry: Res4(res3) [16] = odo_res4_t;  Res5(odo_res4_{t-1} ++ odo_res4_t) [32] -> rel xyz, quat
      semantic: stem..Res3 [8] -> depth head -> D_t
                Res4 [16] = sem_res4f -> AWF(., warp(prev.sem_res4f)) -> Res5 (dilated) [16] = sem_res5c
                -> AWF(., warp(prev.sem_res5c)) -> decoder (+ skip from Res3) -> logits [1]
      global:   pool -> Res4[:k] [16 p] = res4c -> AWF(., fused sem_res5c) -> Res4[k:] = res4f
                -> Res5a [32 p] = res5a -> AWF(., prev.res5a) -> Res5b.. = res5c -> xyz, quat

``pool`` is average pooling by ``p``, the config's ``global_downsample`` (1 in the paper: none); the
semantic Res5c map is pooled the same way before the Res4c AWF, so both have the global stream's stride.
The warp (paper Eq. 4, :func:`geometry.warp_grid`) uses ``D_t`` and the predicted relative pose
(or the ``depth`` / ``warp_rel_pose`` given to ``step``); the grid is computed once at input
resolution and average-pooled to the OS16 feature size. Module names set the stream a weight
belongs to (see ``stages.py``): ``trunk`` and ``global_stream`` are the global stream (the
trunk is also the odometry I_t stream up to Res3), ``odometry``, ``semantic`` (encoder, warp
fusions, decoder), ``depth_head`` and ``semantic_fusion`` (the inter-task Res4c AWF). A pose-only
config (``semantic_stream: false``) has only the first three: ``semantic``, ``depth_head`` and
``semantic_fusion`` are ``None``.

Memory layout: the network is built channels-last (NHWC) and the normalised input follows the layout
of its weights (``model.to(memory_format=torch.contiguous_format)`` gives an NCHW network). On the CPU
(oneDNN) a training step of lite runs about 1.1-1.5x as fast channels-last (``vlocnetpp bench``), with
the same values to float rounding. Tensors keep their logical ``(B, C, H, W)`` shapes; checkpoints
store contiguous copies.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from vlocnetpp_core.geometry import pool_warp_grid, pose_to_matrix, warp_features, warp_grid
from vlocnetpp_core.model.anchors import kmeans_anchors, rotation_anchors
from vlocnetpp_core.model.backbone import init_weights
from vlocnetpp_core.model.config import TASKS, ModelConfig
from vlocnetpp_core.model.fusion import AdaptiveWeightedFusion
from vlocnetpp_core.model.heads import DepthHead, without_autocast
from vlocnetpp_core.model.step_types import StepOutput, StreamState
from vlocnetpp_core.model.streams import GlobalPoseStream, OdometryStream, SemanticStream, Trunk


class VLocNetPP(nn.Module):
    """VLocNet++ (paper Sec. III). Images are ``(B, 3, H, W)`` RGB in ``[0, 1]``; H, W multiples of 16.

    ``tasks`` (any of ``"loc"``, ``"vo"``, ``"seg"``; default: all the network has, ``config.tasks``)
    picks the streams a call runs, so a single-task stage computes only its stream. The inter-task
    Res4c fusion runs only when both ``loc`` and ``seg`` run; the odometry stream also runs for
    ``seg`` when warping needs its relative pose (no ``warp_rel_pose`` given). Ablation switches of
    the config remove their branch entirely (no parameters, no compute); without ``warping`` there
    is no depth head. A pose-only network (``semantic_stream: false``) runs ``loc`` and ``vo`` and
    refuses ``seg`` (``ValueError``).
    """

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.config = config
        c = config.stage_channels
        self.trunk = Trunk(config)
        self.global_stream = GlobalPoseStream(config)
        self.odometry = OdometryStream(config)
        self.semantic = SemanticStream(config) if config.semantic_stream else None
        self.depth_head = DepthHead(c[1], config.depth_width, config.depth_range) if config.warping else None
        self.semantic_fusion = AdaptiveWeightedFusion(c[2], c[3]) if config.semantic_fusion else None
        self.register_buffer("mean", torch.tensor(config.mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(config.std).view(1, 3, 1, 1), persistent=False)
        init_weights(self)
        self.to(memory_format=torch.channels_last)

    def set_pose_prior(self, positions: np.ndarray, quats: np.ndarray | None = None, seed: int = 0) -> None:
        """Fit the global pose outputs to the training poses: positions ``(M, 3)`` metres and unit
        quaternions ``(M, 4)`` ``(w, x, y, z)``, world frame.

        The paper's head (fc2 regressing the position) is centred on their mean with their spread (at
        least 1 m per axis) as its scale, so fc2 regresses numbers of order one instead of walking to
        the scene from the origin. A head with ``global_pose_anchors`` gets its anchors at their
        k-means centres, one with ``global_rotation_anchors`` its rotation anchors at the k-means
        centres of the quaternions (``quats`` then required; ``seed`` fixes both)."""
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        head = self.global_stream.head
        if self.config.global_rotation_anchors:
            if quats is None:
                raise ValueError("a head with global_rotation_anchors needs the training quaternions")
            anchors = rotation_anchors(
                np.asarray(quats, dtype=np.float64).reshape(-1, 4), self.config.global_rotation_anchors, seed
            )
            head.set_rotation_anchors(
                torch.as_tensor(anchors, dtype=head.anchor_quat.dtype, device=head.anchor_quat.device)
            )
        if self.config.global_pose_anchors:
            anchors = kmeans_anchors(positions, self.config.global_pose_anchors, seed)
            head.set_anchors(torch.as_tensor(anchors, dtype=head.anchor_xyz.dtype, device=head.anchor_xyz.device))
            return
        with torch.no_grad():
            head.xyz_offset.copy_(torch.as_tensor(positions.mean(axis=0), dtype=head.xyz_offset.dtype))
            head.xyz_scale.copy_(torch.as_tensor(np.maximum(positions.std(axis=0), 1.0), dtype=head.xyz_scale.dtype))

    @property
    def memory_format(self) -> torch.memory_format:
        """``torch.channels_last`` or ``torch.contiguous_format``: the layout of the weights, which the input
        follows."""
        weight = self.trunk.stem.conv.weight
        return (
            torch.channels_last if weight.is_contiguous(memory_format=torch.channels_last) else torch.contiguous_format
        )

    # ------------------------------------------------------------------ streaming

    def step(
        self,
        image: torch.Tensor,
        state: StreamState | None = None,
        K: torch.Tensor | None = None,
        depth: torch.Tensor | None = None,
        warp_rel_pose: torch.Tensor | None = None,
        tasks: Iterable[str] | None = None,
    ) -> tuple[StepOutput, StreamState]:
        """One frame. ``state=None`` is a first frame: every fusion with the previous frame uses
        the current frame's own features (a static camera); odometry outputs are then meaningless (the identity in
        training).

        Args:
            image: ``(B, 3, H, W)`` RGB in ``[0, 1]``.
            state: the state returned by the previous step (``None`` for a first frame).
            K: ``(B, 3, 3)`` intrinsics at ``H x W``; required when the semantic stream warps.
            depth: ``(B, 1, H, W)`` metres (0 = invalid) used for warping instead of the prediction.
            warp_rel_pose: ``(B, 4, 4)`` ``T_{t-1}^{-1} T_t`` used for warping instead of the odometry output.
            tasks: streams to run (default ``config.tasks``: ``("loc", "vo", "seg")``, or ``("loc", "vo")`` pose-only).

        Returns:
            ``(StepOutput, StreamState)``; the state keeps the autograd graph (call
            :meth:`StreamState.detach` to cut it).
        """
        run = _check_tasks(tasks, self.config.tasks)
        self._check_image(image)
        prev = state if state is not None else StreamState()
        x = ((image - self.mean) / self.std).contiguous(memory_format=self.memory_format)
        out, new = StepOutput(), StreamState()
        do_seg, do_loc = "seg" in run, "loc" in run
        do_warp = self.config.warping and do_seg
        do_odo = "vo" in run or (do_warp and warp_rel_pose is None)
        if do_warp and K is None:
            raise ValueError("K (B, 3, 3), the intrinsics at the network input size, is required for warping")

        res3 = self.trunk(x) if do_loc or do_odo else None
        if res3 is not None:
            out.taps["res3"] = res3
        if do_odo:
            self._odometry_step(res3, prev, out, new)
        sem_res5c = None
        if do_seg:
            if do_warp and warp_rel_pose is None:
                warp_rel_pose = pose_to_matrix(out.rel_xyz, out.rel_quat)
            sem_res5c = self._semantic_step(x, prev, out, new, K, depth, warp_rel_pose if do_warp else None)
        if do_loc:
            self._global_step(res3, sem_res5c, prev, out, new)
        return out, new

    def _odometry_step(self, res3: torch.Tensor, prev: StreamState, out: StepOutput, new: StreamState) -> None:
        """Siamese Res4 of this frame (cached for the next), Res5 on ``prev ++ current``, relative pose.

        A first frame (no ``prev.odo_res4``) pairs the frame with itself in eval mode (streaming, ONNX). In training it
        gives the identity without running Res5: no loss reads it, and the self-pair's zero-motion statistics would
        enter the running averages of Res5's and the head's BatchNorms (half of them with clips of 2) and bias every
        evaluation."""
        odo_res4 = self.odometry.res4(res3)
        out.taps["odo_res4"] = new.odo_res4 = odo_res4
        if prev.odo_res4 is None and self.training:
            out.rel_xyz = odo_res4.new_zeros(odo_res4.shape[0], 3, dtype=self.odometry.head.fc1.weight.dtype)
            out.rel_quat = out.rel_xyz.new_tensor([1.0, 0.0, 0.0, 0.0]).expand(odo_res4.shape[0], 4)
            return
        prev_res4 = prev.odo_res4 if prev.odo_res4 is not None else odo_res4
        _check_state(prev_res4, odo_res4, "odo_res4")
        out.rel_xyz, out.rel_quat, out.taps["odo_res5"] = self.odometry(prev_res4, odo_res4)

    def _semantic_step(
        self,
        x: torch.Tensor,
        prev: StreamState,
        out: StepOutput,
        new: StreamState,
        K: torch.Tensor | None,
        depth: torch.Tensor | None,
        warp_rel_pose: torch.Tensor | None,
    ) -> torch.Tensor:
        """Encoder, depth head, Res4f / Res5c warp fusions (when ``warp_rel_pose`` is given), decoder.

        Returns the (fused) Res5c features that the global stream fuses at Res4c.
        """
        sem, taps = self.semantic, out.taps
        sem_res3 = taps["sem_res3"] = sem.res3(sem.res2(sem.stem(x)))
        if self.depth_head is not None:
            out.depth = self.depth_head(sem_res3, tuple(x.shape[-2:]))
        sem_res4f = taps["sem_res4f"] = sem.res4(sem_res3)
        if warp_rel_pose is None:  # warping switched off
            sem_res5c = taps["sem_res5c"] = sem.res5(sem_res4f)
            out.seg_logits = sem.decoder(sem_res5c, sem_res3)
            return sem_res5c
        warper = None
        if prev.sem_res4f is not None:
            warper = _Warper(depth.to(x.dtype) if depth is not None else out.depth, warp_rel_pose, K)
        fused4f = self._warp_fuse(sem.warp_fusion_res4f, sem_res4f, prev.sem_res4f, warper, "sem_res4f", taps)
        sem_res5c = taps["sem_res5c"] = sem.res5(fused4f)
        fused5c = self._warp_fuse(sem.warp_fusion_res5c, sem_res5c, prev.sem_res5c, warper, "sem_res5c", taps)
        new.sem_res4f, new.sem_res5c = sem_res4f, sem_res5c
        out.seg_logits = sem.decoder(fused5c, sem_res3)
        return fused5c

    def _global_step(
        self, res3: torch.Tensor, sem_res5c: torch.Tensor | None, prev: StreamState, out: StepOutput, new: StreamState
    ) -> None:
        """Res4 with the semantic AWF after block ``res4_fusion_block``, Res5a with the temporal AWF, Res5, pose."""
        g, taps, k = self.global_stream, out.taps, self.config.res4_fusion_block
        h = self.global_pool(res3)
        for block in g.res4[:k]:
            h = block(h)
        taps["res4c"] = h
        if self.semantic_fusion is not None and sem_res5c is not None:
            h = taps["res4c_fused"] = self.semantic_fusion(h, self.global_pool(sem_res5c))
        for block in g.res4[k:]:
            h = block(h)
        taps["res4f"] = h
        res5a = h = taps["res5a"] = g.res5[0](h)
        if g.temporal_fusion is not None:
            prev5a = prev.res5a if prev.res5a is not None else res5a
            _check_state(prev5a, res5a, "res5a")
            h = taps["res5a_fused"] = g.temporal_fusion(res5a, prev5a)
            new.res5a = res5a
        for block in g.res5[1:]:
            h = block(h)
        taps["res5c"] = h
        out.xyz, out.quat, out.anchor_logits, out.rotation_logits = g.head(h)
        if out.anchor_logits is not None:
            out.anchor_xyz = g.head.anchor_xyz
        if out.rotation_logits is not None:
            out.anchor_quat = g.head.anchor_quat

    def global_pool(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, C, h, w) -> (B, C, ceil(h/p), ceil(w/p))``: average pooling by ``config.global_downsample`` (``p``),
        for the trunk's Res3 map entering the global stream and the semantic Res5c map fused into its Res4c."""
        f = self.config.global_downsample
        return x if f == 1 else F.avg_pool2d(x, f, ceil_mode=True)

    def _warp_fuse(
        self,
        fusion: nn.Module,
        current: torch.Tensor,
        previous: torch.Tensor | None,
        warper: _Warper | None,
        name: str,
        taps: dict[str, torch.Tensor],
    ) -> torch.Tensor:
        """AWF of ``current`` with the previous frame's features warped into this view (own features on a first
        frame)."""
        if previous is None:
            warped = current
        else:
            _check_state(previous, current, name)
            warped = warper(previous)
        taps[f"{name}_warped"] = warped
        fused = fusion(current, warped)
        taps[f"{name}_fused"] = fused
        return fused

    # ------------------------------------------------------------------ clips

    def forward_clip(
        self,
        images: torch.Tensor,
        K: torch.Tensor | None = None,
        depth: torch.Tensor | None = None,
        warp_rel_pose: torch.Tensor | None = None,
        tasks: Iterable[str] | None = None,
    ) -> list[StepOutput]:
        """Unroll :meth:`step` over a clip, the state coming from the network's own previous step.

        ``images (B, T, 3, H, W)``, ``K (B, T, 3, 3)`` (or ``(B, 3, 3)`` for all frames),
        ``depth (B, T, 1, H, W)``, ``warp_rel_pose (B, T, 4, 4)`` -> ``T`` :class:`StepOutput`.
        The graph runs through the state, so gradients flow across frames.
        """
        if images.dim() != 5:
            raise ValueError(f"images must be (B, T, 3, H, W), got {tuple(images.shape)}")
        T = images.shape[1]
        state = None
        outputs = []
        for t in range(T):
            out, state = self.step(
                images[:, t],
                state,
                K=None if K is None else (K if K.dim() == 3 else K[:, t]),
                depth=None if depth is None else depth[:, t],
                warp_rel_pose=None if warp_rel_pose is None else warp_rel_pose[:, t],
                tasks=tasks,
            )
            outputs.append(out)
        return outputs

    def forward(
        self,
        images: torch.Tensor,
        K: torch.Tensor | None = None,
        depth: torch.Tensor | None = None,
        warp_rel_pose: torch.Tensor | None = None,
        tasks: Iterable[str] | None = None,
    ) -> list[StepOutput]:
        """Same as :meth:`forward_clip` (so wrappers such as DistributedDataParallel work)."""
        return self.forward_clip(images, K, depth, warp_rel_pose, tasks)

    def _check_image(self, image: torch.Tensor) -> None:
        if image.dim() != 4 or image.shape[1] != 3:
            raise ValueError(f"image must be (B, 3, H, W) RGB, got {tuple(image.shape)}")
        h, w = image.shape[-2:]
        if h % 16 or w % 16:
            raise ValueError(
                f"image height and width must be multiples of 16 (semantic stream at output stride 16), got {w}x{h}"
            )


class _Warper:
    """Warps previous-frame features into the current view; one float32 input-resolution grid, pooled per feature
    size."""

    def __init__(self, depth: torch.Tensor, T_rel: torch.Tensor, K: torch.Tensor):
        dtype = torch.promote_types(
            depth.dtype, torch.float32
        )  # pixel coordinates in float32 (or 64), also under autocast
        with without_autocast(depth):
            self.grid, self.valid = warp_grid(depth.to(dtype), T_rel.to(dtype), K.to(dtype))
        self.pooled: dict[tuple[int, int], tuple[torch.Tensor, torch.Tensor]] = {}

    def __call__(self, features: torch.Tensor) -> torch.Tensor:
        size = tuple(features.shape[-2:])
        if size not in self.pooled:
            self.pooled[size] = pool_warp_grid(self.grid, self.valid, size)
        return warp_features(features, *self.pooled[size])


def _check_tasks(tasks: Iterable[str] | None, available: tuple[str, ...]) -> frozenset[str]:
    run = frozenset(available if tasks is None else tasks)
    unknown = run - set(TASKS)
    if unknown or not run:
        raise ValueError(f"tasks must be a non-empty subset of {TASKS}, got {sorted(run)}")
    if run - set(available):
        raise ValueError(
            f"this network has no semantic stream (model config semantic_stream: false), so it cannot run "
            f"{sorted(run - set(available))}; its tasks are {', '.join(available)}"
        )
    return run


def _check_state(previous: torch.Tensor, current: torch.Tensor, name: str) -> None:
    if previous.shape != current.shape:
        raise ValueError(
            f"state {name} has shape {tuple(previous.shape)} but this frame gives {tuple(current.shape)}: "
            "the input size or batch changed, start again with state=None"
        )
