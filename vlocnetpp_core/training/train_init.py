"""Initialising a training run's network from earlier runs' checkpoints (``vlocnetpp train --init``).

Which tensors each source gives follows :mod:`vlocnetpp_core.model.assembly` (``init_rule``/``init_tensors``);
a run's learned loss weights come with its checkpoint. A Res4c semantic fusion that no source holds starts
as an identity of the global stream (:func:`identity_fusion_init`), so an assembled network behaves as its stages.
"""

from __future__ import annotations

from pathlib import Path

import torch

from vlocnetpp_core.errors import UserError
from vlocnetpp_core.model.assembly import init_rule, init_tensors


def load_inits(model, criterion, paths: list[str], stage: str, log) -> list[dict]:
    """Initialise from checkpoints. For ``mtl`` each stream is taken from the checkpoint of its stage.

    A tensor that a later checkpoint gives too is taken from the later one, and only the tensors
    taken must fit this model config: an ``mtl`` checkpoint whose odometry head has another shape can
    give every other stream when a later ``stl-vo`` checkpoint gives the odometry."""
    from vlocnetpp_core.inference.checkpoint import read_checkpoint_tensors
    from vlocnetpp_core.training.train_state import load_criterion_weights

    own = model.state_dict()
    picked = []
    for path in paths:
        tensors, meta = read_checkpoint_tensors(path)
        src_stage = meta.get("training", {}).get("stage")
        keep = init_tensors(init_rule(stage, src_stage, len(paths)), src_stage, tensors, own)
        if not keep:
            raise UserError(
                f"--init {path}: none of its {len(tensors)} tensors matches a tensor of this {stage} network "
                f"(checkpoint stage {src_stage or 'unknown'}); a checkpoint of another network or task?"
            )
        picked.append((path, src_stage, keep))
    sources, loaded = [], {}
    for i, (path, src_stage, keep) in enumerate(picked):
        later = set().union(*(k for _, _, k in picked[i + 1 :]))
        keep = {k: v for k, v in keep.items() if k not in later}
        bad = [k for k, v in keep.items() if v.shape != own[k].shape]
        if bad:
            raise UserError(
                f"{path}: {len(bad)} tensors do not match this model config "
                f"(e.g. {bad[0]}); was it trained with another --config?"
            )
        model.load_state_dict({k: v.to(own[k].dtype) for k, v in keep.items()}, strict=False)
        loaded.update(keep)
        sources.append({"path": str(path), "stage": src_stage})
        crit = load_criterion_weights(Path(path).parent)
        if crit:
            own_c = criterion.state_dict()
            criterion.load_state_dict({**own_c, **{k: v for k, v in crit.items() if k in own_c}})
        log(f"init: {len(keep)} tensors from {path} (stage {src_stage})")
    fusion = getattr(model, "semantic_fusion", None)
    if fusion is not None and not any(k.startswith("semantic_fusion.") for k in loaded):
        identity_fusion_init(model)
        log("init: semantic fusion (Res4c) starts as an identity of the global stream's Res4c features")
    return sources


@torch.no_grad()
def identity_fusion_init(model, margin: float = 8.0) -> None:
    """Start the Res4c semantic fusion added to trained streams as an identity of the global stream.

    The AWF is ``ReLU(pool(...) + b)`` and the global stream's Res4c features are signed, so the
    pooling passes them through shifted by a per-channel ``c >= 0`` that lifts ``margin`` standard
    deviations below their mean to zero (the statistics of the next block's BatchNorm, which reads
    them), and every BatchNorm that reads the shifted features takes ``c`` off again: their
    running means move by ``c`` (in training their batch means do). The shift rides the residual
    path up to the first block with a projection shortcut (Res5a), whose BatchNorm removes it. So
    the assembled network's outputs are unchanged wherever the features stay within ``margin``
    standard deviations. The semantic half of the pooling starts at zero: it still receives
    gradients (through the non-zero semantic features), and the per-channel semantic weights do
    from the second step on.
    """
    fusion, g, k = model.semantic_fusion, model.global_stream, model.config.res4_fusion_block
    readers = []
    for block in [*g.res4[k:], *g.res5]:
        readers.append(block.bn1)
        if block.shortcut is not None:
            break
    else:
        raise RuntimeError("no block with a projection shortcut after the Res4c fusion")
    bn = readers[0]
    c = torch.clamp(margin * torch.sqrt(bn.running_var + bn.eps) - bn.running_mean, min=0.0)
    w = fusion.pool.weight  # (C_a, C_a + C_b, 1, 1)
    ca = fusion.weight_a.numel()
    w.zero_()
    w[:, :ca, 0, 0] = torch.eye(ca, dtype=w.dtype)
    fusion.pool.bias.copy_(c)
    for reader in readers:
        reader.running_mean += c
