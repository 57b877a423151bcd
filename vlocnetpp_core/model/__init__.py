"""The VLocNet++ network: config, assembly, streaming state, stage rules, backbone init.

See ``docs/architecture.md`` ("Model") for the contract and ``vlocnet.py`` for the data flow. The names
below load their module on first use, so that ``model.config`` and ``model.stages`` (the stage table a
recipe is checked against) import without torch.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from vlocnetpp_core import lazy_getattr

_EXPORTS = {
    "ModelConfig": "config",
    "load_model_config": "config",
    "AdaptiveWeightedFusion": "fusion",
    "BackboneLoadReport": "init_backbone",
    "load_backbone_weights": "init_backbone",
    "STAGE_SPECS": "stages",
    "STAGE_TASKS": "stages",
    "STAGES": "stages",
    "STREAMS": "stages",
    "StageSpec": "stages",
    "is_trained_in": "stages",
    "params_per_stream": "stages",
    "stage_spec": "stages",
    "stage_tasks": "stages",
    "stream_of": "stages",
    "train_only": "stages",
    "trainable_parameters": "stages",
    "TASKS": "vlocnet",
    "StepOutput": "step_types",
    "StreamState": "step_types",
    "VLocNetPP": "vlocnet",
}
__all__ = list(_EXPORTS)

if TYPE_CHECKING:
    from vlocnetpp_core.model.config import ModelConfig, load_model_config  # noqa: F401
    from vlocnetpp_core.model.fusion import AdaptiveWeightedFusion  # noqa: F401
    from vlocnetpp_core.model.init_backbone import BackboneLoadReport, load_backbone_weights  # noqa: F401
    from vlocnetpp_core.model.stages import (  # noqa: F401
        STAGE_SPECS,
        STAGE_TASKS,
        STAGES,
        STREAMS,
        StageSpec,
        is_trained_in,
        params_per_stream,
        stage_spec,
        stage_tasks,
        stream_of,
        train_only,
        trainable_parameters,
    )
    from vlocnetpp_core.model.step_types import StepOutput, StreamState  # noqa: F401
    from vlocnetpp_core.model.vlocnet import TASKS, VLocNetPP  # noqa: F401


__getattr__ = lazy_getattr(__name__, _EXPORTS, globals())
