"""The VLocNet++ network: config, assembly, streaming state, stage helpers, backbone init.

See ``docs/architecture.md`` ("Model") for the contract and ``vlocnet.py`` for the data flow.
"""

from vlocnetpp_core.model.config import ModelConfig, load_model_config
from vlocnetpp_core.model.fusion import AdaptiveWeightedFusion
from vlocnetpp_core.model.init_backbone import BackboneLoadReport, load_backbone_weights
from vlocnetpp_core.model.stages import (
    STAGE_TASKS,
    STAGES,
    STREAMS,
    is_trained_in,
    params_per_stream,
    stage_tasks,
    stream_of,
    train_only,
    trainable_parameters,
)
from vlocnetpp_core.model.vlocnet import TASKS, StepOutput, StreamState, VLocNetPP

__all__ = [
    "ModelConfig",
    "load_model_config",
    "AdaptiveWeightedFusion",
    "BackboneLoadReport",
    "load_backbone_weights",
    "STAGE_TASKS",
    "STAGES",
    "STREAMS",
    "TASKS",
    "is_trained_in",
    "params_per_stream",
    "stage_tasks",
    "stream_of",
    "train_only",
    "trainable_parameters",
    "StepOutput",
    "StreamState",
    "VLocNetPP",
]
