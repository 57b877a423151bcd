"""Which images of a bag ``vlocnetpp extract`` keeps, in which split and sequence, under which DeepLoc id.

Pure numpy on the image stamps and their interpolated camera poses (no bag access), in this order:

1. an image without a pose (see :mod:`vlocnetpp_core.bag.pose_source`) or with the stamp of an
   earlier image is skipped, with its reason;
2. split: an image whose stamp, in seconds after the first image stamp of the bag, lies in one of
   the ``test_ranges`` ``[a, b)`` goes to ``test``, every other one to ``train``;
3. sequences: consecutive usable images (stamp order) more than ``max_gap_s`` apart, or in
   different splits, start a new sequence;
4. within a sequence: every ``stride``-th usable image is kept (the first one always), and of
   those only the ones that moved at least ``min_motion_m`` metres or ``min_motion_deg`` degrees
   from the last kept one (the first one always).

DeepLoc ids (what ``vlocnetpp_core.data.deeploc`` reads back as the same sequences): sequence
``k`` of a split has ids ``k * id_stride + 1, k * id_stride + 2, ...`` with ``id_stride`` 10000
(grown by tens for longer sequences), as the synthetic campus writes them; the reader starts a new
sequence at any id jump over 10.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from vlocnetpp_core import geometry

ID_STRIDE = 10000
SPLITS = ("train", "test")


@dataclass(frozen=True)
class Selection:
    """The rules of steps 2-4: ``test_ranges`` seconds after the first image, sequence gap, stride, minimum motion."""

    test_ranges: tuple[tuple[float, float], ...] = ()
    max_gap_s: float = 1.0
    stride: int = 1
    min_motion_m: float = 0.0
    min_motion_deg: float | None = None


@dataclass(frozen=True)
class PlannedFrame:
    """One kept image: its ``ordinal`` on the image topic (log order), ``stamp_ns``, camera pose ``T_wc``
    (``t (3,)`` metres, ``q (4,)`` ``(w, x, y, z)``), ``split``, ``sequence`` (within the split) and DeepLoc ``id``."""

    ordinal: int
    stamp_ns: int
    t: np.ndarray
    q: np.ndarray
    split: str
    sequence: int
    id: int

    @property
    def name(self) -> str:
        return f"Image_{self.id}.png"


@dataclass
class Plan:
    """Kept ``frames`` (stamp order) and ``skipped`` image counts per reason."""

    frames: list[PlannedFrame] = field(default_factory=list)
    skipped: Counter = field(default_factory=Counter)


def in_ranges(rel_s: np.ndarray, ranges: tuple[tuple[float, float], ...]) -> np.ndarray:
    """Boolean ``(N,)``: ``rel_s`` in any ``[a, b)`` of ``ranges``."""
    out = np.zeros(len(rel_s), dtype=bool)
    for a, b in ranges:
        out |= (rel_s >= a) & (rel_s < b)
    return out


def _moved_enough(t: np.ndarray, q: np.ndarray, t_ref: np.ndarray, q_ref: np.ndarray, sel: Selection) -> bool:
    if sel.min_motion_m <= 0 and sel.min_motion_deg is None:
        return True
    if sel.min_motion_m > 0 and np.linalg.norm(t - t_ref) >= sel.min_motion_m:
        return True
    return sel.min_motion_deg is not None and float(geometry.rotation_error_deg(q, q_ref)) >= sel.min_motion_deg


def _sequence_runs(order: np.ndarray, stamps: np.ndarray, test: np.ndarray, max_gap_s: float) -> list[list[int]]:
    """Indices of usable images (``order``: stamp-sorted) grouped into sequences (step 3)."""
    runs: list[list[int]] = []
    for i in order:
        if runs:
            prev = runs[-1][-1]
            if test[i] == test[prev] and stamps[i] - stamps[prev] <= max_gap_s * 1e9:
                runs[-1].append(int(i))
                continue
        runs.append([int(i)])
    return runs


def plan_frames(stamps_ns: np.ndarray, t: np.ndarray, q: np.ndarray, reasons: list[str | None], sel: Selection) -> Plan:
    """The kept frames of images with header stamps ``stamps_ns (N,)`` (log order; index = ordinal), camera
    poses ``t (N, 3)``, ``q (N, 4)`` and pose ``reasons`` (None = usable), under ``sel`` (module doc)."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    plan = Plan()
    if len(stamps) == 0:
        return plan
    order = np.argsort(stamps, kind="stable")
    dup = np.zeros(len(stamps), dtype=bool)
    dup[order[1:]] = stamps[order[1:]] == stamps[order[:-1]]
    usable = []
    for i in order:
        why = "same stamp as an earlier image" if dup[i] else reasons[i]
        if why is None:
            usable.append(i)
        else:
            plan.skipped[why] += 1
    test = in_ranges((stamps - stamps[order[0]]) / 1e9, sel.test_ranges)
    kept_runs: dict[str, list[list[int]]] = {s: [] for s in SPLITS}
    for run in _sequence_runs(np.asarray(usable, dtype=np.int64), stamps, test, sel.max_gap_s):
        kept = []
        for k, i in enumerate(run):
            if k % sel.stride:
                plan.skipped["stride"] += 1
            elif kept and not _moved_enough(t[i], q[i], t[kept[-1]], q[kept[-1]], sel):
                plan.skipped["min motion"] += 1
            else:
                kept.append(i)
        kept_runs["test" if test[run[0]] else "train"].append(kept)
    for split, runs in kept_runs.items():
        stride = ID_STRIDE
        while runs and max(len(r) for r in runs) >= stride:
            stride *= 10
        for k, run in enumerate(runs):
            plan.frames += [
                PlannedFrame(i, int(stamps[i]), t[i], q[i], split, k, k * stride + j + 1) for j, i in enumerate(run)
            ]
    plan.frames.sort(key=lambda f: f.stamp_ns)
    return plan


def match_nearest(query_ns: np.ndarray, stamps_ns: np.ndarray, tolerance_s: float) -> np.ndarray:
    """Index into ``stamps_ns`` of the nearest stamp to each ``query_ns`` within ``tolerance_s``, else -1, ``(M,)``."""
    query = np.asarray(query_ns, dtype=np.int64)
    s = np.asarray(stamps_ns, dtype=np.int64)
    if len(s) == 0:
        return np.full(len(query), -1, dtype=np.int64)
    order = np.argsort(s, kind="stable")
    ss = s[order]
    j = np.clip(np.searchsorted(ss, query), 1, max(len(ss) - 1, 1))
    left = np.clip(j - 1, 0, len(ss) - 1)
    right = np.clip(j, 0, len(ss) - 1)
    best = np.where(np.abs(ss[right] - query) < np.abs(query - ss[left]), right, left)
    ok = np.abs(ss[best] - query) <= tolerance_s * 1e9
    return np.where(ok, order[best], -1)
