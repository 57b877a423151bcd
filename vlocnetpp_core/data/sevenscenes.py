"""Microsoft 7-Scenes reader (one scene folder, e.g. ``chess/``).

Layout::

    TrainSplit.txt, TestSplit.txt       lines 'sequence1', 'sequence2', ... (the seq-XX of a split)
    seq-XX/frame-NNNNNN.color.png       RGB 640x480
    seq-XX/frame-NNNNNN.depth.png       uint16 millimetres, 0 and 65535 invalid -> metres, 0 invalid
    seq-XX/frame-NNNNNN.pose.txt        4x4 camera-to-world matrix T_wc (metres)

Intrinsics default to :data:`vlocnetpp_core.camera.intrinsics.SEVEN_SCENES_DEFAULT` (focal 585,
principal point (320, 240)); stamps are 30 Hz from the frame order. Each ``seq-XX`` is one
sequence with id ``XX``.

Note: 7-Scenes depth comes from the Kinect depth camera and is *not registered* to the colour
camera (different viewpoint and intrinsics), so warping colour images or features with it is
approximate: edges are misplaced by a few pixels. Use it as a sanity check, not as exact geometry.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from vlocnetpp_core import geometry
from vlocnetpp_core.camera.intrinsics import SEVEN_SCENES_DEFAULT, Intrinsics
from vlocnetpp_core.data import imageio
from vlocnetpp_core.data.sample import DatasetIndex, FrameRecord, resolve_intrinsics, sequence_stamps
from vlocnetpp_core.errors import DataError, UserError

RATE_HZ = 30.0
SPLIT_FILES = {"train": "TrainSplit.txt", "test": "TestSplit.txt"}
_FRAME = re.compile(r"^frame-(\d+)\.color\.png$")


def read_split_file(path: Path) -> list[int]:
    """Sequence numbers listed in a ``TrainSplit.txt`` / ``TestSplit.txt`` (lines ``sequenceN``)."""
    if not path.is_file():
        raise DataError(path, "split file not found (expected lines 'sequence1', 'sequence2', ...)")
    out = []
    for lineno, raw in enumerate(path.read_text(errors="replace").splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        m = re.fullmatch(r"(?:sequence|seq-?)(\d+)", line, flags=re.IGNORECASE)
        if m is None:
            raise DataError(path, f"expected a line 'sequenceN', got {line!r}", lineno)
        out.append(int(m.group(1)))
    if not out:
        raise DataError(path, "no sequences listed")
    return out


def read_pose_matrix(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(t (3,), q (4,))`` of a 4x4 camera-to-world matrix file (the rotation is checked)."""
    try:
        T = np.array([float(v) for v in path.read_text().split()], dtype=np.float64)
    except FileNotFoundError:
        raise DataError(path, "pose file not found") from None
    except ValueError:
        raise DataError(path, "expected 16 numbers (a 4x4 matrix)") from None
    if T.size != 16 or not np.isfinite(T).all():
        raise DataError(path, f"expected 16 finite numbers (a 4x4 matrix), got {T.size}")
    T = T.reshape(4, 4)
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-2) or np.linalg.det(R) < 0:
        raise DataError(path, "the 3x3 block is not a rotation matrix")
    t, q = geometry.matrix_to_pose(T)
    return t, q


def read_sevenscenes(
    path: str | Path, split: str = "train", intrinsics: Intrinsics | str | None = None
) -> DatasetIndex:
    """Index the ``split`` (``train`` / ``test``) of the 7-Scenes scene folder ``path``."""
    root = Path(path)
    if not root.is_dir():
        raise DataError(root, "dataset folder not found")
    if split not in SPLIT_FILES:
        raise UserError(f"split must be one of {sorted(SPLIT_FILES)}, got {split!r}")
    seq_numbers = read_split_file(root / SPLIT_FILES[split])
    records: list[FrameRecord] = []
    sequences: list[range] = []
    per_seq: list[tuple[int, list[tuple[int, Path]]]] = []
    for n in seq_numbers:
        folder = root / f"seq-{n:02d}"
        if not folder.is_dir():
            raise DataError(folder, f"sequence folder listed in {SPLIT_FILES[split]} not found")
        frames = sorted((int(m.group(1)), f) for f in folder.iterdir() if (m := _FRAME.match(f.name)))
        if not frames:
            raise DataError(folder, "no frame-NNNNNN.color.png files")
        per_seq.append((n, frames))
    stamps = sequence_stamps([len(f) for _, f in per_seq], RATE_HZ)
    for (n, frames), seq_stamps in zip(per_seq, stamps, strict=True):
        start = len(records)
        for (_, color), stamp in zip(frames, seq_stamps, strict=True):
            stem = color.name[: -len(".color.png")]
            t, q = read_pose_matrix(color.with_name(stem + ".pose.txt"))
            depth = color.with_name(stem + ".depth.png")
            records.append(
                FrameRecord(
                    image=str(color),
                    t=tuple(float(v) for v in t),
                    q=tuple(float(v) for v in q),
                    stamp=float(stamp),
                    sequence=n,
                    frame_id=f"{color.parent.name}/{stem}",
                    depth=str(depth) if depth.is_file() else None,
                )
            )
        sequences.append(range(start, len(records)))
    h, w = imageio.read_rgb(records[0].image).shape[:2]
    K = resolve_intrinsics(intrinsics, SEVEN_SCENES_DEFAULT, w, h)
    source = "given" if intrinsics is not None else "default (7-Scenes focal 585, centre (320, 240))"
    notes = (
        ["depth is not registered to the colour camera: warping with it is approximate"]
        if any(r.depth for r in records)
        else []
    )
    return DatasetIndex("7scenes", root, split, records, sequences, K, source, notes)
