"""DeepLoc reader (docs/conventions.md, Formats), tolerant of what public copies of the dataset contain.

Layout (``DIR`` is the folder holding ``DeepLoc/``, or the ``DeepLoc`` folder itself)::

    DeepLoc/{train,test}/LeftImages/Image_<id>.png    RGB or RGBA (alpha dropped)
    DeepLoc/{train,test}/labels/Image_<id>.png        optional, class ids 0..9 (255 = ignore)
    DeepLoc/{train,test}/poses.txt                     name x y z qw qx qy qz (T_wc, metres)
    DeepLoc_stereo/{train,test}/DepthImages/Image_<id>.{pfm,png}  optional depth
    intrinsics.json                                    optional {"fx","fy","cx","cy","width","height"}

* Ids are not zero-padded: frames are matched across folders and sorted by the number in the
  file name. A name in ``poses.txt`` may have an extension or not.
* ``poses.txt`` may start with a non-data line and/or a header line (up to two leading lines
  without numbers are skipped; ``#`` comments and blank lines anywhere). The quaternion column
  order is ``quaternion_order="wxyz"`` (the likely one) or ``"xyzw"``; quaternions are
  normalised to ``w >= 0``.
* The loops of a split are merged in one folder: a new sequence starts where the id jumps by
  more than ``max_id_gap`` or consecutive poses are more than ``max_jump_m`` / ``max_jump_deg``
  apart. Stamps are 20 Hz from the frame order (the dataset has none).
* Depth is looked up in ``DeepLoc_stereo`` next to ``DeepLoc`` (or inside it). PFM holds metres,
  16-bit PNG millimetres.
* Intrinsics: the ``intrinsics`` argument, else ``intrinsics.json`` at ``DIR`` (or next to the
  ``DeepLoc`` folder), else :data:`vlocnetpp_core.camera.intrinsics.DEEPLOC_DEFAULT` (approximate ZED
  values; DeepLoc publishes none), rescaled when the images are not 1280x720.
* Poses without an image are skipped and images without a pose ignored; both are counted in
  ``DatasetIndex.notes`` (``vlocnetpp data-info`` prints them).
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np

from vlocnetpp_core import geometry
from vlocnetpp_core.camera.intrinsics import DEEPLOC_DEFAULT, Intrinsics
from vlocnetpp_core.data import imageio
from vlocnetpp_core.data.sample import DatasetIndex, FrameRecord, resolve_intrinsics, sequence_stamps
from vlocnetpp_core.errors import DataError, UserError

RATE_HZ = 20.0
_LAST_INT = re.compile(r"(\d+)(?!.*\d)")


def frame_number(name: str) -> int | None:
    """The last integer in a file name's stem (``Image_123.png`` -> 123), or None."""
    m = _LAST_INT.search(Path(name).stem if Path(name).suffix.lower() in imageio.IMAGE_EXTENSIONS + (".pfm",) else name)
    return int(m.group(1)) if m else None


def find_deeploc_root(path: str | Path) -> tuple[Path, Path]:
    """``(deeploc_dir, dataset_root)`` for ``DIR`` = the folder holding ``DeepLoc/`` or ``DeepLoc`` itself."""
    p = Path(path)
    if not p.is_dir():
        raise DataError(p, "dataset folder not found")
    if (p / "DeepLoc").is_dir():
        return p / "DeepLoc", p
    if any((p / s / "LeftImages").is_dir() for s in ("train", "test")):
        return p, p.parent
    raise DataError(
        p, "not a DeepLoc dataset: expected DeepLoc/{train,test}/LeftImages/ (or {train,test}/LeftImages/ inside it)"
    )


def _files_by_number(folder: Path, extensions: tuple[str, ...]) -> dict[int, Path]:
    out: dict[int, Path] = {}
    if folder.is_dir():
        for f in folder.iterdir():
            if f.suffix.lower() in extensions:
                n = frame_number(f.name)
                if n is not None:
                    out.setdefault(n, f)
    return out


def _is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def read_poses(path: str | Path, quaternion_order: str = "wxyz") -> list[tuple[int, str, np.ndarray, np.ndarray]]:
    """Parse a DeepLoc ``poses.txt`` into ``(id, name, t (3,), q (4,) w,x,y,z w>=0)`` in file order.

    Raises ``DataError`` with the line number on a line with the wrong number of fields,
    non-numbers, a non-finite translation or a non-normalisable quaternion, or a repeated id.
    """
    if quaternion_order not in ("wxyz", "xyzw"):
        raise UserError(f"quaternion_order must be 'wxyz' or 'xyzw', got {quaternion_order!r}")
    p = Path(path)
    if not p.is_file():
        raise DataError(p, "poses file not found (expected 'ImageName x y z qw qx qy qz' lines)")
    out: list[tuple[int, str, np.ndarray, np.ndarray]] = []
    seen: dict[int, int] = {}
    leading = 0
    with open(p, encoding="utf-8", errors="replace") as f:
        for lineno, raw in enumerate(f, start=1):
            line = raw.strip()
            if not line or line.startswith("#"):
                continue
            fields = line.replace(",", " ").split()
            if not out and leading < 2 and sum(_is_float(v) for v in fields[1:]) < 2:
                leading += 1  # a title or header line before the data
                continue
            if len(fields) != 8:
                raise DataError(p, f"expected 8 fields 'ImageName x y z qw qx qy qz', got {len(fields)}", lineno)
            try:
                vals = np.array([float(v) for v in fields[1:]])
            except ValueError:
                raise DataError(
                    p, f"expected 7 numbers after the image name, got {' '.join(fields[1:])!r}", lineno
                ) from None
            n = frame_number(fields[0])
            if n is None:
                raise DataError(p, f"image name {fields[0]!r} has no frame number", lineno)
            if n in seen:
                raise DataError(p, f"frame {n} ({fields[0]}) already listed on line {seen[n]}", lineno)
            t, q = vals[:3], vals[3:]
            if quaternion_order == "xyzw":
                q = q[[3, 0, 1, 2]]
            norm = float(np.linalg.norm(q))
            if not np.isfinite(vals).all() or not math.isfinite(norm) or norm < 1e-3:
                raise DataError(
                    p, f"pose is not finite or its quaternion cannot be normalised (norm {norm:.3g})", lineno
                )
            seen[n] = lineno
            out.append((n, fields[0], t, q / norm))
    if not out:
        raise DataError(p, "no pose lines found (expected 'ImageName x y z qw qx qy qz')")
    return out


# a new sequence starts after a gap of more frame numbers than this, or at a larger jump of the pose between frames
MAX_ID_GAP = 10
MAX_JUMP_M = 5.0
MAX_JUMP_DEG = 45.0


def split_sequences(
    ids: np.ndarray, t: np.ndarray, q: np.ndarray, max_id_gap: int, max_jump_m: float, max_jump_deg: float
) -> list[range]:
    """Contiguous ranges of id-sorted frames; a new one starts at an id gap or an implausible pose jump."""
    if len(ids) == 0:
        return []
    step_m = np.linalg.norm(np.diff(t, axis=0), axis=1)
    step_deg = geometry.rotation_error_deg(q[:-1], q[1:])
    cut = (np.diff(ids) > max_id_gap) | (step_m > max_jump_m) | (step_deg > max_jump_deg)
    starts = [0, *(np.nonzero(cut)[0] + 1).tolist(), len(ids)]
    return [range(a, b) for a, b in zip(starts[:-1], starts[1:], strict=True)]


def _load_intrinsics_json(root: Path, deeploc_dir: Path) -> tuple[Intrinsics, str] | None:
    for f in (root / "intrinsics.json", deeploc_dir / "intrinsics.json"):
        if f.is_file():
            try:
                return Intrinsics.from_dict(json.loads(f.read_text())), str(f)
            except (ValueError, KeyError, TypeError) as err:
                raise DataError(f, f"expected a JSON object with fx, fy, cx, cy, width, height ({err})") from err
    return None


def read_deeploc(
    path: str | Path,
    split: str = "train",
    intrinsics: Intrinsics | str | None = None,
    quaternion_order: str = "wxyz",
    max_id_gap: int = MAX_ID_GAP,
    max_jump_m: float = MAX_JUMP_M,
    max_jump_deg: float = MAX_JUMP_DEG,
) -> DatasetIndex:
    """Index the ``split`` (``train`` / ``test``) of the DeepLoc dataset at ``path`` (see module doc)."""
    deeploc_dir, root = find_deeploc_root(path)
    split_dir = deeploc_dir / split
    images = _files_by_number(split_dir / "LeftImages", imageio.IMAGE_EXTENSIONS)
    if not images:
        raise DataError(split_dir / "LeftImages", f"no images found (expected {split}/LeftImages/Image_<id>.png)")
    poses = read_poses(split_dir / "poses.txt", quaternion_order)
    labels = _files_by_number(split_dir / "labels", (".png",))
    depth_dir = next(
        (
            d
            for d in (
                root / "DeepLoc_stereo" / split / "DepthImages",
                deeploc_dir / "DeepLoc_stereo" / split / "DepthImages",
            )
            if d.is_dir()
        ),
        None,
    )
    depths = _files_by_number(depth_dir, imageio.DEPTH_EXTENSIONS) if depth_dir is not None else {}

    posed = sorted((p for p in poses if p[0] in images), key=lambda p: p[0])
    notes = []
    if len(posed) < len(poses):
        notes.append(f"{len(poses) - len(posed)} poses in {split}/poses.txt have no image in LeftImages/ (skipped)")
    if len(images) > len(posed):
        notes.append(f"{len(images) - len(posed)} images in {split}/LeftImages/ have no pose (ignored)")
    if not posed:
        raise DataError(split_dir / "poses.txt", "no pose matches an image in LeftImages/ (frame numbers differ?)")
    ids = np.array([p[0] for p in posed])
    t = np.stack([p[2] for p in posed])
    q = geometry.quat_normalize(np.stack([p[3] for p in posed]))
    sequences = split_sequences(ids, t, q, max_id_gap, max_jump_m, max_jump_deg)
    stamps = np.concatenate(sequence_stamps([len(s) for s in sequences], RATE_HZ))

    records = []
    for k, rng in enumerate(sequences):
        for i in rng:
            n = int(ids[i])
            records.append(
                FrameRecord(
                    image=str(images[n]),
                    t=tuple(float(v) for v in t[i]),
                    q=tuple(float(v) for v in q[i]),
                    stamp=float(stamps[i]),
                    sequence=k,
                    frame_id=images[n].stem,
                    depth=str(depths[n]) if n in depths else None,
                    labels=str(labels[n]) if n in labels else None,
                )
            )
    h, w = imageio.read_rgb(records[0].image).shape[:2]
    if intrinsics is not None:
        source = "given"
        K = resolve_intrinsics(intrinsics, DEEPLOC_DEFAULT, w, h)
    else:
        found = _load_intrinsics_json(root, deeploc_dir)
        default, source = found if found else (DEEPLOC_DEFAULT, "default (approximate ZED values)")
        K = resolve_intrinsics(default, default, w, h)
    return DatasetIndex("deeploc", root, split, records, sequences, K, source, notes)
