"""``ModelConfig``: every size and switch of the network, loaded from ``config/<name>.yaml``.

``load_model_config("paper")`` / ``"lite"`` / ``"lite_pose"`` read the YAML shipped with the
package (found by walking up from this file to the repository's ``config/`` or the install's
``share/vlocnetpp_ros/config/``); any other argument is a path to a YAML file with the same keys.
Keys left out take the paper's values; unknown keys are an error naming the file. ``base: NAME`` (a
built-in name or a YAML file relative to this one) takes every key of that config first, so a variant
names only what it changes.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from vlocnetpp_core.classes import NUM_CLASSES
from vlocnetpp_core.errors import DataError, UserError

PACKAGE = "vlocnetpp_ros"
BUILTIN_CONFIGS = ("paper", "lite", "lite_pose")
TASKS = ("loc", "vo", "seg")  # global pose, odometry, segmentation
POSE_POOLINGS = ("average", "flatten")


@dataclass(frozen=True)
class ModelConfig:
    """Sizes and switches of :class:`~vlocnetpp_core.model.VLocNetPP`. Defaults are the paper's.

    Backbone stages are Res2..Res5 of a pre-activation bottleneck ResNet: stage ``i`` has
    ``depths[i]`` blocks of ``widths[i]`` inner channels and ``expansion * widths[i]`` outputs.
    ``res4_fusion_block`` is how many Res4 blocks run before the semantic fusion (3: after
    Res4c, the paper's best). The semantic encoder runs at output stride 16: Res4 blocks after
    the first have a ``semantic_res4_dilation`` branch next to the plain 3x3, Res5 uses
    dilation 2 instead of stride and its blocks get ``semantic_res5_dilations`` branches.

    ``semantic_stream: false`` builds a pose-only network (global pose and odometry streams; for
    data without semantic labels): no AdapNet stream, no depth head, no Res4c semantic fusion, no
    warping. ``warping`` and ``semantic_fusion`` must then be false too (an error otherwise: they
    are not silently switched off); the ``semantic_*``, ``num_classes`` and ``depth_*`` sizes are
    unused.

    Five departures from the paper, all off by default (``lite`` uses them; ablation in
    docs/results.md): ``global_downsample`` average-pools the trunk's Res3 map by this factor before
    the global stream's Res4, so the global stream runs at a lower resolution than the trunk, the
    odometry stream and the semantic stream (whose Res5c map is pooled by the same factor for the
    Res4c fusion);
    ``global_pose_pooling: flatten`` feeds the whole Res5c map of the global stream into fc1
    instead of its global average (``average``, the paper's), which keeps where things are in
    the image but fixes the input size to ``input_size``;
    ``global_pose_anchors: N`` (0: the paper's fc2 regressing the position) makes the position
    head score ``N`` anchor positions (k-means of the training positions) and regress an offset
    from each: the position is the softmax-weighted sum of ``anchor + offset``;
    ``global_rotation_anchors: R`` likewise for the rotation (0: fc3 regresses the quaternion): ``R``
    anchor rotations (k-means of the training quaternions) scored, each turned by a residual rotation;
    ``odometry_pose_pooling: flatten`` likewise feeds the odometry stream's whole Res5 map into its fc1:
    where in the image the two frames' features differ is what the motion is.
    """

    name: str = "paper"
    input_size: tuple[int, int] = (448, 256)  # (width, height), multiples of 16
    mean: tuple[float, float, float] = (0.485, 0.456, 0.406)
    std: tuple[float, float, float] = (0.229, 0.224, 0.225)
    num_classes: int = NUM_CLASSES
    stem_width: int = 64
    widths: tuple[int, int, int, int] = (64, 128, 256, 512)
    depths: tuple[int, int, int, int] = (3, 4, 6, 3)
    expansion: int = 4
    fc_width: int = 1024
    dropout: float = 0.2
    res4_fusion_block: int = 3
    semantic_res4_dilation: int = 2
    semantic_res5_dilations: tuple[int, ...] = (4, 8, 16)
    depth_width: int = 64
    depth_range: tuple[float, float] = (0.1, 300.0)  # metres, bounds of the predicted depth
    temporal_fusion: bool = True
    semantic_fusion: bool = True
    warping: bool = True
    semantic_stream: bool = True
    global_downsample: int = 1  # the global stream pools the trunk's Res3 map by this factor
    global_pose_pooling: str = (
        "average"  # "average" (paper: global average pooling) or "flatten" (whole Res5c map into fc1)
    )
    global_pose_anchors: int = 0  # position anchors of the global pose head (0: the paper's direct regression)
    global_rotation_anchors: int = 0  # rotation anchors of the global pose head (0: the paper's direct regression)
    odometry_pose_pooling: str = "average"  # "average" (paper) or "flatten" (the odometry's whole Res5 map into fc1)

    def __post_init__(self) -> None:
        problems = self.problems()
        if problems:
            raise ValueError("; ".join(problems))

    def problems(self) -> list[str]:
        """Human-readable reasons this config cannot build a network (empty when fine)."""
        out = []
        w, h = self.input_size
        if w <= 0 or h <= 0 or w % 16 or h % 16:
            out.append(
                f"input_size must be positive multiples of 16 (semantic stream at output stride 16), got {w}x{h}"
            )
        if len(self.widths) != 4 or len(self.depths) != 4:
            out.append("widths and depths need 4 entries (Res2..Res5)")
        elif min(self.depths) < 1 or min(self.widths) < 2 or any(v % 2 for v in self.widths):
            out.append("depths must be >= 1 and widths even and >= 2")
        elif not 1 <= self.res4_fusion_block <= self.depths[2]:
            out.append(f"res4_fusion_block must be in 1..{self.depths[2]} (the number of Res4 blocks)")
        sizes = (
            "num_classes",
            "stem_width",
            "expansion",
            "fc_width",
            "depth_width",
            "semantic_res4_dilation",
            "global_downsample",
        )
        out += [f"{k} must be >= 1, got {getattr(self, k)}" for k in sizes if getattr(self, k) < 1]
        if len(self.semantic_res5_dilations) < 1 or min(self.semantic_res5_dilations) < 1:
            out.append("semantic_res5_dilations needs at least one entry, all >= 1")
        lo, hi = self.depth_range
        if not 0 < lo < hi:
            out.append(f"depth_range must be 0 < min < max, got {self.depth_range}")
        if not 0 <= self.dropout < 1:
            out.append(f"dropout must be in [0, 1), got {self.dropout}")
        for key in ("global_pose_anchors", "global_rotation_anchors"):
            if getattr(self, key) < 0:
                out.append(f"{key} must be >= 0 (0: the paper's direct regression), got {getattr(self, key)}")
        for key in ("global_pose_pooling", "odometry_pose_pooling"):
            if getattr(self, key) not in POSE_POOLINGS:
                out.append(f"{key} must be one of {list(POSE_POOLINGS)}, got {getattr(self, key)!r}")
        needs_semantics = [k for k in ("warping", "semantic_fusion") if getattr(self, k)]
        if not self.semantic_stream and needs_semantics:
            out.append(
                f"semantic_stream is false (a pose-only network) but {' and '.join(needs_semantics)} "
                f"{'is' if len(needs_semantics) == 1 else 'are'} true: without the semantic stream there are no "
                f"semantic features to warp or fuse; set {' and '.join(f'{k}: false' for k in needs_semantics)}"
            )
        return out

    @property
    def tasks(self) -> tuple[str, ...]:
        """The tasks the network runs: ``("loc", "vo", "seg")``, or ``("loc", "vo")`` without the semantic stream."""
        return TASKS if self.semantic_stream else TASKS[:2]

    @property
    def stage_channels(self) -> tuple[int, int, int, int]:
        """Output channels of Res2..Res5."""
        return tuple(self.expansion * v for v in self.widths)  # type: ignore[return-value]

    @property
    def global_res5_size(self) -> tuple[int, int]:
        """``(h, w)`` of the global stream's Res5 map at ``input_size``: stride ``32 * global_downsample``
        (every stride-2 layer and the pooling round up)."""
        return self._map_size(32 * self.global_downsample)

    @property
    def odometry_res5_size(self) -> tuple[int, int]:
        """``(h, w)`` of the odometry stream's Res5 map at ``input_size``: stride 32 (the trunk's full resolution)."""
        return self._map_size(32)

    def _map_size(self, stride: int) -> tuple[int, int]:
        """``(h, w)`` of a map at ``stride`` of ``input_size`` (every stride-2 layer and pooling rounds up)."""
        w, h = self.input_size
        return -(-h // stride), -(-w // stride)

    def res5_dilations(self) -> tuple[int, ...]:
        """Dilation of the parallel branch of each semantic Res5 block (the list is repeated if short)."""
        d = self.semantic_res5_dilations
        return tuple(d[i % len(d)] for i in range(self.depths[3]))

    def to_dict(self) -> dict[str, Any]:
        """Plain types (lists, not tuples): what the checkpoint sidecar and YAML files hold."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "<dict>") -> ModelConfig:
        """Build from a mapping; ``source`` names the file in error messages."""
        if not isinstance(data, dict):
            raise DataError(source, f"expected a mapping of model config keys, got {type(data).__name__}")
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - set(fields))
        if unknown:
            raise DataError(source, f"unknown model config key(s) {unknown}; known keys: {sorted(fields)}")
        kwargs: dict[str, Any] = {}
        defaults = cls()
        for key, value in data.items():
            try:
                kwargs[key] = _coerce(value, getattr(defaults, key), fixed_length=key not in _VARIABLE_LENGTH)
            except (TypeError, ValueError) as err:
                raise DataError(source, f"key '{key}': {err}") from None
        try:
            return cls(**kwargs)
        except ValueError as err:
            raise DataError(source, str(err)) from None


_VARIABLE_LENGTH = {"semantic_res5_dilations"}


def _coerce(value: Any, default: Any, fixed_length: bool = True) -> Any:
    """Convert a YAML value to the type of the field's default (tuples from lists, ints from floats)."""
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise TypeError(f"expected true/false, got {value!r}")
        return value
    if isinstance(default, tuple):
        if not isinstance(value, (list, tuple)):
            raise TypeError(f"expected a list, got {value!r}")
        kind = type(default[0]) if default else float
        items = tuple(_coerce(v, kind()) for v in value)
        if fixed_length and len(items) != len(default):
            raise ValueError(f"expected {len(default)} values, got {len(items)}")
        return items
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or int(value) != value:
            raise TypeError(f"expected an integer, got {value!r}")
        return int(value)
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise TypeError(f"expected a number, got {value!r}")
        return float(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise TypeError(f"expected a string, got {value!r}")
        return value
    return value


def config_dir() -> Path | None:
    """The folder holding ``paper.yaml`` / ``lite.yaml``: the repository's or the install's, else ament's."""
    here = Path(__file__).resolve()
    for parent in here.parents:
        for cand in (parent / "config", parent / "share" / PACKAGE / "config"):
            if (cand / "paper.yaml").is_file():
                return cand
    try:
        from ament_index_python.packages import get_package_share_directory
    except ImportError:
        return None
    try:
        cand = Path(get_package_share_directory(PACKAGE)) / "config"
    except Exception:  # PackageNotFoundError and friends
        return None
    return cand if (cand / "paper.yaml").is_file() else None


def load_model_config(name_or_path: str | Path) -> ModelConfig:
    """``"paper"`` / ``"lite"`` / ``"lite_pose"`` (shipped YAML) or a path to a YAML file -> :class:`ModelConfig`."""
    path = _config_path(str(name_or_path))
    return ModelConfig.from_dict(_config_keys(path, ()), source=str(path))


def _config_path(text: str, next_to: Path | None = None) -> Path:
    """A built-in config's shipped YAML, or the file ``text`` (relative to ``next_to``'s folder when given)."""
    if text in BUILTIN_CONFIGS:
        folder = config_dir()
        if folder is None:
            raise UserError(
                f"cannot find the shipped config folder holding {text}.yaml (looked above {Path(__file__).parent})"
            )
        path = folder / f"{text}.yaml"
    else:
        path = Path(text) if next_to is None else next_to.parent / text
    if not path.is_file():
        raise DataError(path, f"no such model config file (or use one of {list(BUILTIN_CONFIGS)})")
    return path


def _config_keys(path: Path, chain: tuple[Path, ...]) -> dict[str, Any]:
    """The keys of the YAML file ``path`` over those of its ``base`` (a built-in name or a file relative to it), and so
    on."""
    if path.resolve() in chain:
        raise DataError(path, "'base' loops back: " + " -> ".join(str(p) for p in (*chain, path.resolve())))
    try:
        data = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as err:
        raise DataError(path, f"not valid YAML: {err}".splitlines()[0]) from None
    data = {} if data is None else data
    if not isinstance(data, dict):
        raise DataError(path, f"expected a mapping of model config keys, got {type(data).__name__}")
    if "base" not in data:
        return data
    base = data.pop("base")
    if not isinstance(base, str):
        raise DataError(path, f"'base' must name a model config (a built-in name or a YAML file), got {base!r}")
    return {**_config_keys(_config_path(base, next_to=path), (*chain, path.resolve())), **data}
