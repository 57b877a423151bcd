"""What ``vlocnetpp bench`` runs: :class:`BenchSettings`, with the defaults, ``--quick`` and a YAML file's overrides
(``--config``), checked field by field."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from vlocnetpp_core.errors import DataError

ZERO_ALLOWED = ("threads", "warmup")  # whole-number settings that may be 0


@dataclass
class BenchSettings:
    """What ``vlocnetpp bench`` runs. Sizes are ``(W, H)``; ``threads`` as everywhere (:mod:`vlocnetpp_core.threads`; 0:
    all cores but one, like the node)."""

    repetitions: int = 7
    warmup: int = 2
    paper_config: str = "paper"
    paper_input_size: tuple[int, int] | None = None  # None: the config's (448x256 for paper)
    lite_config: str = "lite"
    camera_size: tuple[int, int] = (640, 360)
    threads: int = 0
    node: bool = True
    refinement: bool = True  # the refinement figures (shipped model and map, :mod:`.refinement`)
    refinement_map: str = "auto"  # their keyframe map: a file, or auto (NAME.map.npz beside the shipped model)
    node_backend: str = "onnx"  # the launch YAML's (config/localizer.yaml)
    node_transport: str = "large_data"  # or "environment" (see the latency-bench program, docs/performance.md)
    node_repetitions: int = 30
    node_warmup: int = 3
    node_stream_frames: int = 240  # frames sent at the refinement's camera rate (30/s) for node_refined_hz
    converter_frames: int = 120
    synth_frames: int = 20
    synth_size: tuple[int, int] = (320, 180)
    scene: str = "campus"
    soak_minutes: float = 0.0  # > 0: the soak figures (the node at 15 Hz with depth, :func:`.figures.soak`); 10 in docs
    soak_out: str = "bench_soak"  # where the soak writes soak.md, soak.json and soak.png

    @classmethod
    def quick(cls) -> BenchSettings:
        return cls(
            repetitions=3,
            warmup=1,
            paper_input_size=(224, 128),
            node_repetitions=8,
            node_warmup=2,
            node_stream_frames=60,
            converter_frames=30,
            synth_frames=6,
        )

    def updated(self, values: dict, source: str) -> BenchSettings:
        """A copy with ``values`` (from a YAML file ``source``) applied, checked field by field."""
        known = {f.name: f for f in dataclasses.fields(self)}
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise DataError(source, f"unknown bench setting(s) {', '.join(unknown)}; known: {', '.join(known)}")
        out = {}
        for name, value in values.items():
            default = getattr(self, name)
            if name.endswith("_size"):
                if value is not None and not (
                    isinstance(value, (list, tuple))
                    and len(value) == 2
                    and all(isinstance(v, int) and v > 0 for v in value)
                ):
                    raise DataError(source, f"{name} must be [width, height] in pixels, got {value!r}")
                value = None if value is None else tuple(value)
            elif isinstance(default, bool):
                if not isinstance(value, bool):
                    raise DataError(source, f"{name} must be true or false, got {value!r}")
            elif isinstance(default, float):
                if not isinstance(value, (int, float)) or isinstance(value, bool) or not 0 <= value < 1e6:
                    raise DataError(source, f"{name} must be a number >= 0, got {value!r}")
                value = float(value)
            elif isinstance(default, int):
                if not isinstance(value, int) or isinstance(value, bool) or value < (0 if name in ZERO_ALLOWED else 1):
                    raise DataError(
                        source,
                        f"{name} must be a whole number >= {0 if name in ZERO_ALLOWED else 1}, got {value!r}",
                    )
            elif not isinstance(value, str):
                raise DataError(source, f"{name} must be a string, got {value!r}")
            out[name] = value
        if out.get("node_backend", self.node_backend) not in ("torch", "onnx"):
            raise DataError(source, f"node_backend must be torch or onnx, got {out['node_backend']!r}")
        if out.get("node_transport", self.node_transport) not in ("large_data", "environment"):
            raise DataError(source, f"node_transport must be large_data or environment, got {out['node_transport']!r}")
        return dataclasses.replace(self, **out)
