"""``--init-backbone FILE``: copy a standard ResNet-50 state dict onto every backbone of the network.

The file holds torchvision key names (``conv1.weight``, ``bn1.*``, ``layer1.0.conv1.weight``, ...,
``layer4.2.bn3.*``, ``fc.*``), as safetensors or as a weights-only torch file (never unpickled
beyond tensors). It is copied onto three backbone copies: ``global`` (trunk stem..Res3 plus the
global Res4, Res5), ``odometry`` (its Res4, Res5) and ``semantic`` (the AdapNet encoder).

What is mapped:

* Convolutions 1:1: ``conv1`` -> stem conv, ``layerN.i.conv{1,2,3}`` -> ``res{N+1}.i.conv{1,2,3}``,
  ``layerN.i.downsample.0`` -> ``shortcut``. A multiscale block's two parallel 3x3 convolutions
  get the first and second half of ``conv2``'s output channels. The odometry Res5a sees the
  concatenation of two Res4 outputs, so its ``conv1`` and ``shortcut`` have twice the input
  channels and are skipped (reported).
* Batch norm: torchvision's blocks are post-activation (BN after each convolution), ours are
  pre-activation (BN before). ``bn1`` and ``bn2`` normalise the outputs of ``conv1`` and
  ``conv2``, exactly what our ``bn2`` and ``bn3`` normalise, so they are copied there; the
  stem ``bn1`` goes to the stem BN. ``bn3`` and ``downsample.1`` normalise the block output
  before the residual sum, a tensor the pre-activation design never normalises: skipped. Our
  ``bn1`` (block input pre-activation) and the final BN before each head stay at their init.
* ``fc.*`` (the ImageNet classifier) and the BN ``num_batches_tracked`` counters are skipped.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import nn

from vlocnetpp_core.errors import DataError

_BLOCK = re.compile(r"^layer([1-4])\.(\d+)\.(.+)$")
_BN_FIELDS = ("weight", "bias", "running_mean", "running_var")


@dataclass
class BackboneLoadReport:
    """What :func:`load_backbone_weights` did.

    ``loaded``: ``(copy, source key, target name)``; ``skipped``: ``(copy, source key, reason)``;
    ``missing``: ``(copy, target conv weight)`` our convolutions that received nothing;
    ``unexpected``: source keys that are not part of a ResNet-50 state dict.
    """

    loaded: list[tuple[str, str, str]] = field(default_factory=list)
    skipped: list[tuple[str, str, str]] = field(default_factory=list)
    missing: list[tuple[str, str]] = field(default_factory=list)
    unexpected: list[str] = field(default_factory=list)

    def __str__(self) -> str:
        copies = sorted({c for c, _, _ in self.loaded})
        reasons: dict[str, int] = {}
        for _, _, why in self.skipped:
            reasons[why] = reasons.get(why, 0) + 1
        why = "; ".join(f"{n} x {r}" for r, n in sorted(reasons.items(), key=lambda kv: -kv[1])[:4])
        text = f"{len(self.loaded)} tensors loaded into {', '.join(copies) or 'nothing'}; {len(self.skipped)} skipped"
        text += f" ({why})" if why else ""
        if self.missing:
            text += f"; {len(self.missing)} conv weights left at init (e.g. {self.missing[0][0]}: {self.missing[0][1]})"
        if self.unexpected:
            text += f"; {len(self.unexpected)} unexpected keys (e.g. {self.unexpected[0]})"
        return text


def backbone_copies(model: nn.Module) -> dict[str, dict[str, nn.Module]]:
    """The ResNet-50 shaped parts of a :class:`VLocNetPP`: ``copy -> {"stem" | "res2".."res5": module}``
    (no ``semantic`` copy in a pose-only network)."""
    sem = model.semantic
    copies = {
        "global": {
            "stem": model.trunk.stem,
            "res2": model.trunk.res2,
            "res3": model.trunk.res3,
            "res4": model.global_stream.res4,
            "res5": model.global_stream.res5,
        },
        "odometry": {"res4": model.odometry.res4, "res5": model.odometry.res5},
    }
    if sem is not None:
        copies["semantic"] = {"stem": sem.stem, "res2": sem.res2, "res3": sem.res3, "res4": sem.res4, "res5": sem.res5}
    return copies


def read_state_dict(path: str | Path) -> dict[str, torch.Tensor]:
    """Tensors of a safetensors or weights-only torch file; a nested ``state_dict`` / ``model`` and ``module.`` prefixes
    are unwrapped."""
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "no such file")
    with open(path, "rb") as f:
        head = f.read(2)
    try:
        if head[:2] == b"PK" or head[:1] == b"\x80":  # torch zip archive or legacy pickle
            data = torch.load(path, map_location="cpu", weights_only=True)
        else:
            from safetensors.torch import load_file

            data = load_file(str(path))
    except Exception as err:  # safetensors / pickle / zip errors all mean "not a weights file"
        raise DataError(
            path, f"cannot read a state dict (safetensors or weights-only torch file): {err}".splitlines()[0]
        ) from None
    for key in ("state_dict", "model"):
        if isinstance(data, dict) and isinstance(data.get(key), dict):
            data = data[key]
    if not isinstance(data, dict) or not all(isinstance(v, torch.Tensor) for v in data.values()):
        raise DataError(path, "expected a mapping of tensor names to tensors (a ResNet-50 state dict)")
    return {k.removeprefix("module."): v for k, v in data.items()}


def _targets(key: str, parts: dict[str, nn.Module]) -> tuple[list[tuple[nn.Module, str, slice | None]], str | None]:
    """Where a torchvision key goes in one backbone copy: ``[(module, local name, output-channel slice)]`` or a skip
    reason."""
    if key.startswith("fc."):
        return [], "classifier (fc), the pose heads differ"
    if key.endswith(".num_batches_tracked"):
        return [], "BN update counter (not a weight)"
    if key == "conv1.weight" or key.startswith("bn1."):
        if "stem" not in parts:
            return [], "this copy has no stem"
        return [(parts["stem"], "conv.weight" if key == "conv1.weight" else "bn." + key[4:], None)], None
    m = _BLOCK.match(key)
    if m is None:
        raise KeyError(key)
    stage, index, rest = f"res{int(m.group(1)) + 1}", int(m.group(2)), m.group(3)
    if stage not in parts:
        return [], f"this copy has no {stage}"
    blocks = parts[stage]
    if index >= len(blocks):
        return [], f"{stage} has {len(blocks)} blocks in this config"
    block = blocks[index]
    name, _, leaf = rest.rpartition(".")
    if name in ("bn3", "downsample.1"):
        return [], "post-activation BN of the block output (no pre-activation counterpart)"
    if name == "conv2" and getattr(block, "conv2_dilated", None) is not None:
        half = block.conv2.out_channels
        return [(block, "conv2.weight", slice(0, half)), (block, "conv2_dilated.weight", slice(half, None))], None
    mapped = {
        "conv1": "conv1",
        "conv2": "conv2",
        "conv3": "conv3",
        "downsample.0": "shortcut",
        "bn1": "bn2",
        "bn2": "bn3",
    }.get(name)
    if mapped is None or (name.startswith("bn") and leaf not in _BN_FIELDS):
        raise KeyError(key)
    return [(block, f"{mapped}.{leaf}", None)], None


def load_backbone_weights(model: nn.Module, path: str | Path) -> BackboneLoadReport:
    """Copy a standard ResNet-50 state dict (torchvision names) onto every backbone copy of ``model``.

    See the module docstring for the mapping. Raises :class:`DataError` naming the file when it
    cannot be read or when nothing at all fits (e.g. a ResNet-50 file for the ``lite`` widths).
    """
    source = read_state_dict(path)
    report = BackboneLoadReport()
    names = {id(m): n for n, m in model.named_modules()}
    for copy, parts in backbone_copies(model).items():
        filled: set[str] = set()
        for key, value in source.items():
            try:
                targets, reason = _targets(key, parts)
            except KeyError:
                if copy == "global":
                    report.unexpected.append(key)
                continue
            if reason:
                report.skipped.append((copy, key, reason))
                continue
            for module, local, channels in targets:
                tensors = dict(module.named_parameters()) | dict(module.named_buffers())
                dest = tensors.get(local)
                src = value if channels is None else value[channels]
                full = f"{names[id(module)]}.{local}"
                if dest is None:
                    report.skipped.append((copy, key, f"no {local} in this block"))
                elif dest.shape != src.shape:
                    report.skipped.append((copy, key, f"shape {tuple(src.shape)} does not fit {tuple(dest.shape)}"))
                else:
                    with torch.no_grad():
                        dest.copy_(src.to(dest.dtype))
                    report.loaded.append((copy, key, full))
                    filled.add(full)
        for part in parts.values():
            for mod_name, module in part.named_modules():
                if isinstance(module, nn.Conv2d):
                    full = f"{names[id(part)]}.{mod_name}.weight" if mod_name else f"{names[id(part)]}.weight"
                    if full not in filled:
                        report.missing.append((copy, full))
    if not report.loaded:
        raise DataError(path, f"no tensor fits this network's backbones: {report}")
    return report
