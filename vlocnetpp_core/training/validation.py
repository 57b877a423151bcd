"""A training stage's forward pass (:func:`forward_stage`, what the trainer and the learning probes run) and its
validation (:func:`validate`: mean losses and pose residual variances over held-out clips)."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from vlocnetpp_core.model.stages import stage_spec, stage_tasks
from vlocnetpp_core.model.step_types import StepOutput


def float32_outputs(out: StepOutput) -> StepOutput:
    """``out`` with its heads' outputs in float32 (an autocast forward gives the segmentation logits and depth in
    bfloat16)."""
    heads = {f.name: v.float() for f in dataclasses.fields(out) if isinstance(v := getattr(out, f.name), torch.Tensor)}
    return dataclasses.replace(out, **heads)


def forward_stage(net, batch: dict, stage: str):
    """Unroll the clip (the stage's tasks that the network has); a stage that ``warps_with_ground_truth`` (``stl-seg``,
    whose odometry stream is untrained) warps with the true relative pose."""
    from vlocnetpp_core import geometry

    warp = None
    if stage_spec(stage).warps_with_ground_truth:
        warp = geometry.pose_to_matrix(batch["rel_t"], batch["rel_q"])
    tasks = stage_tasks(stage, getattr(net, "module", net).config.tasks)  # module: inside DistributedDataParallel
    return net(batch["image"], batch["K"], warp_rel_pose=warp, tasks=tasks)  # forward = forward_clip


@torch.no_grad()
def validate(model, criterion, clips: list, stage: str, device) -> tuple[dict, dict]:
    """Mean validation losses (eval mode) over the ``ClipDataset`` of every training stride, smallest first, and the
    covariance calibration of pose and odometry errors from the first alone (at stride 1: the camera's own frame
    spacing).

    Every stride counts: validated at one frame spacing, an odometry stream that predicts the same step for any
    pair scores as well as one that measures the motion whenever that spacing is the mean of the training ones.
    """
    from vlocnetpp_core import geometry

    model.eval()
    sums: dict[str, float] = {}
    n = 0
    pose_err, odo_err = [], []
    for k, stride_clips in enumerate(clips):
        for batch in torch.utils.data.DataLoader(stride_clips, batch_size=8, shuffle=False, num_workers=0):
            batch = {key: v.to(device) for key, v in batch.items()}
            outputs = forward_stage(model, batch, stage)
            loss, parts = criterion(outputs, batch)
            for key, v in {"loss": loss, **parts}.items():
                sums[key] = sums.get(key, 0.0) + float(v)
            n += 1
            if k:
                continue
            for i, o in enumerate(outputs):
                if o.xyz is not None:
                    pose_err.append(_pose_residual(o.xyz, o.quat, batch["t"][:, i], batch["q"][:, i], geometry))
                if i > 0 and o.rel_xyz is not None:
                    odo_err.append(
                        _pose_residual(o.rel_xyz, o.rel_quat, batch["rel_t"][:, i], batch["rel_q"][:, i], geometry)
                    )
    model.train()
    metrics = {key: v / max(n, 1) for key, v in sums.items()}
    calib = {
        "pose_variance": _variance(pose_err),
        "odometry_variance": _variance(odo_err),
        "frames": int(sum(len(e) for e in pose_err)),
        "source": f"validation ({stage}, {len(clips[0])} clips at frame stride {clips[0].stride})",
        "note": "per-axis variance of validation errors: x, y, z (m^2), "
        "rotation about x, y, z (rad^2); odometry per frame",
    }
    return metrics, calib


def _pose_residual(xyz, quat, t, q, geometry) -> np.ndarray:
    """``(B, 6)`` residual: translation error (m) and rotation-vector error (rad) of prediction vs truth."""
    dq = geometry.quat_normalize(geometry.quat_mul(geometry.quat_inverse(q.double()), quat.double()))
    angle = 2 * torch.atan2(dq[:, 1:].norm(dim=1), dq[:, 0].clamp_min(0))
    axis = dq[:, 1:] / dq[:, 1:].norm(dim=1, keepdim=True).clamp_min(1e-12)
    return torch.cat((xyz.double() - t.double(), axis * angle[:, None]), 1).cpu().numpy()


def _variance(chunks: list[np.ndarray]) -> list[float] | None:
    if not chunks:
        return None
    e = np.concatenate(chunks)
    return [float(v) for v in np.mean(e**2, axis=0)]
