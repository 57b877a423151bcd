"""Poses of a bag at arbitrary stamps: from a pose topic or a chain of ``/tf`` + ``/tf_static`` transforms.

A :class:`PoseTrack` holds the samples of one transform ``T_parent,child`` over time (stamps in
integer nanoseconds, translation metres, quaternion ``(w, x, y, z)``, ``w >= 0``) or one static
value. :meth:`PoseTrack.at` interpolates it at query stamps: translation linearly, rotation by
SLERP (``scipy.spatial.transform.Slerp``). A stamp is usable when it equals a sample, or lies
between two samples that are at most ``max_gap_s`` apart; otherwise it gets a reason (before the
first sample, after the last, or a gap) and no pose. No extrapolation, ever.

A :class:`PoseChain` composes tracks along a path of the TF tree (some of them inverted), e.g.
``map -> odom -> base_link -> camera_link -> camera_optical``: ``T_map,optical(s)`` is the product
of every edge at ``s``, and a stamp is usable only where every dynamic edge is. The collectors
are fed the bag's messages (one pass, any order) and build the chain at the end:

* :class:`PoseTopicCollector`: ``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped`` or
  ``geometry_msgs/PoseWithCovarianceStamped`` (``header.stamp``; the pose of the child /
  robot in ``header.frame_id``);
* :class:`TfCollector`: ``tf2_msgs/TFMessage`` from ``/tf`` (samples) and ``/tf_static`` (the
  latest value per edge). Leading ``/`` in frame names is ignored (ROS 1 habit).
"""

from __future__ import annotations

from array import array
from collections import defaultdict
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from vlocnetpp_core import geometry
from vlocnetpp_core.bag import messages
from vlocnetpp_core.errors import UserError

POSE_TYPES = (messages.ODOMETRY, messages.POSE_STAMPED, messages.POSE_WITH_COVARIANCE_STAMPED)


@dataclass
class PoseTrack:
    """Samples of ``T_parent,child``: ``stamps (N,) int64`` ns strictly increasing, ``t (N, 3)`` metres,
    ``q (N, 4)`` ``(w, x, y, z)``. ``static``: one value valid at every stamp (``stamps`` unused)."""

    name: str
    stamps: np.ndarray
    t: np.ndarray
    q: np.ndarray
    static: bool = False

    @classmethod
    def from_samples(cls, name: str, stamps, t, q) -> PoseTrack:
        """From ``stamps (N,)`` ns, ``t (N, 3)``, ``q (N, 4)`` (any order, any norm); sorted by stamp, of samples
        sharing a stamp the last one given is kept."""
        s = np.asarray(stamps, dtype=np.int64)
        order = np.argsort(s, kind="stable")
        s = s[order]
        last = np.append(s[1:] != s[:-1], True)  # the last of each run of equal stamps
        keep = order[last]
        return cls(
            name, s[last], np.asarray(t, np.float64)[keep], geometry.quat_normalize(np.asarray(q, np.float64)[keep])
        )

    @classmethod
    def constant(cls, name: str, t: np.ndarray, q: np.ndarray) -> PoseTrack:
        return cls(
            name,
            np.zeros(1, np.int64),
            np.asarray(t, np.float64)[None],
            geometry.quat_normalize(np.asarray(q, np.float64))[None],
            True,
        )

    def at(self, stamps_ns: np.ndarray, max_gap_s: float) -> tuple[np.ndarray, np.ndarray, list[str | None]]:
        """``(t (M, 3), q (M, 4), reasons)`` at ``stamps_ns (M,)``; ``reasons[i]`` is None where usable (else
        the pose there is NaN)."""
        query = np.asarray(stamps_ns, dtype=np.int64)
        m = len(query)
        if self.static:
            return np.repeat(self.t, m, 0), np.repeat(self.q, m, 0), [None] * m
        s = self.stamps
        lo = np.searchsorted(s, query, side="right") - 1
        exact = (lo >= 0) & (s[np.clip(lo, 0, None)] == query)
        before, after = lo < 0, (lo >= len(s) - 1) & ~exact
        inside = ~before & ~after & ~exact
        hi = np.clip(lo + 1, 0, len(s) - 1)
        gap = inside & ((s[hi] - s[np.clip(lo, 0, None)]) > max_gap_s * 1e9)
        ok = exact | (inside & ~gap)
        reasons = np.full(m, None, dtype=object)
        reasons[before] = f"no pose: before the first sample of {self.name}"
        reasons[after] = f"no pose: after the last sample of {self.name}"
        reasons[gap] = f"no pose: samples of {self.name} more than {max_gap_s:g} s apart"
        t = np.full((m, 3), np.nan)
        q = np.full((m, 4), np.nan)
        t[exact], q[exact] = self.t[lo[exact]], self.q[lo[exact]]
        mid = ok & ~exact
        if mid.any():
            i0, i1 = lo[mid], lo[mid] + 1
            w = ((query[mid] - s[i0]) / (s[i1] - s[i0]).astype(np.float64))[:, None]
            t[mid] = (1 - w) * self.t[i0] + w * self.t[i1]
            q[mid] = self._slerp(query[mid])
        return t, q, list(reasons)

    def _slerp(self, query: np.ndarray) -> np.ndarray:
        """SLERP of the rotations at ``query`` stamps (all strictly inside the sample range)."""
        times = (self.stamps - self.stamps[0]) / 1e9
        slerp = Slerp(times, Rotation.from_quat(self.q, scalar_first=True))
        return geometry.quat_normalize(slerp((query - self.stamps[0]) / 1e9).as_quat(scalar_first=True))


@dataclass
class PoseChain:
    """``T_parent,child`` as a product of tracks, each used as is or inverted (``edges[k] = (track, inverted)``)."""

    parent: str
    child: str
    edges: list[tuple[PoseTrack, bool]]

    @property
    def name(self) -> str:
        return f"{self.parent} -> {self.child}"

    def at(self, stamps_ns: np.ndarray, max_gap_s: float) -> tuple[np.ndarray, np.ndarray, list[str | None]]:
        """``(t (M, 3), q (M, 4), reasons)`` of the composed transform at ``stamps_ns``; the reason of the
        first unusable edge (None where every edge is usable)."""
        m = len(stamps_ns)
        t, q = np.zeros((m, 3)), np.tile([1.0, 0.0, 0.0, 0.0], (m, 1))
        reasons: list[str | None] = [None] * m
        for track, inverted in self.edges:
            te, qe, why = track.at(stamps_ns, max_gap_s)
            reasons = [a if a is not None else b for a, b in zip(reasons, why, strict=True)]
            te, qe = np.nan_to_num(te), np.where(np.isnan(qe), [1.0, 0.0, 0.0, 0.0], qe)
            if inverted:
                te, qe = geometry.pose_inverse(te, qe)
            t, q = geometry.pose_compose(t, q, te, qe)
        bad = np.array([r is not None for r in reasons], dtype=bool)
        t[bad], q[bad] = np.nan, np.nan
        return t, q, reasons

    def camera_at(
        self, stamps_ns: np.ndarray, max_gap_s: float, extrinsics: tuple[np.ndarray, np.ndarray] | None
    ) -> tuple[np.ndarray, np.ndarray, list[str | None]]:
        """:meth:`at`, then (where usable) the fixed ``extrinsics = (t, q)`` ``T_child,camera`` composed on the
        right: the camera's pose ``T_parent,camera`` when the chain ends at the robot's frame."""
        t, q, reasons = self.at(stamps_ns, max_gap_s)
        if extrinsics is not None:
            ok = np.array([r is None for r in reasons], dtype=bool)
            t[ok], q[ok] = geometry.pose_compose(t[ok], q[ok], *extrinsics)
        return t, q, reasons

    def dynamic_span_ns(self) -> tuple[int, int] | None:
        """``(first, last)`` stamp where every dynamic edge has samples; None when all edges are static."""
        dyn = [tr for tr, _ in self.edges if not tr.static]
        if not dyn:
            return None
        return max(int(tr.stamps[0]) for tr in dyn), min(int(tr.stamps[-1]) for tr in dyn)


def _frame(name: str) -> str:
    return name.lstrip("/")


class PoseTopicCollector:
    """Pose samples from one ``Odometry`` / ``PoseStamped`` / ``PoseWithCovarianceStamped`` topic."""

    def __init__(self, topic: str):
        self.topic = topic
        self.stamps: list[int] = []
        self.t: list[np.ndarray] = []
        self.q: list[np.ndarray] = []
        self.frame_id = ""
        self.child_frame_id = ""

    def add(self, msg) -> None:
        """One message (its ``header.stamp`` is the sample's time)."""
        t, q = messages.stamped_pose(msg)
        self.stamps.append(messages.stamp_ns(msg))
        self.t.append(t)
        self.q.append(q)
        self.frame_id = _frame(msg.header.frame_id)
        self.child_frame_id = _frame(getattr(msg, "child_frame_id", ""))

    def chain(self) -> PoseChain:
        if not self.stamps:
            raise UserError(f"--pose-topic {self.topic}: the topic has no messages")
        track = PoseTrack.from_samples(self.topic, self.stamps, self.t, self.q)
        return PoseChain(self.frame_id or "?", self.child_frame_id or self.topic, [(track, False)])


class TfCollector:
    """The TF tree of a bag: dynamic samples per edge from ``/tf``, the latest value per edge from ``/tf_static``.

    Every edge of ``/tf`` is kept (which ones the chain needs is known only once the tree is), compactly:
    64 bytes per sample in ``array`` buffers, so that an hour of joint states stays in memory.
    """

    def __init__(self):
        self.samples: dict[tuple[str, str], tuple[array, array]] = defaultdict(lambda: (array("q"), array("d")))
        self.static: dict[tuple[str, str], tuple[np.ndarray, np.ndarray]] = {}

    def add(self, msg, static: bool) -> None:
        """One ``tf2_msgs/TFMessage`` (from ``/tf_static`` when ``static``)."""
        for tf in msg.transforms:
            key = (_frame(tf.header.frame_id), _frame(tf.child_frame_id))
            if static:
                self.static[key] = messages.transform_from_msg(tf.transform)
                continue
            v, o = tf.transform.translation, tf.transform.rotation
            stamps, values = self.samples[key]
            stamps.append(messages.stamp_ns(tf))
            values.extend((v.x, v.y, v.z, o.w, o.x, o.y, o.z))  # core quaternion order (w, x, y, z)

    def parents(self) -> dict[str, tuple[str, PoseTrack]]:
        """``child -> (parent, track)``; a frame with two parents or on both ``/tf`` and ``/tf_static`` is an error."""
        out: dict[str, tuple[str, PoseTrack]] = {}
        edges = [((p, c), PoseTrack.constant(f"{p}->{c} (static)", *v)) for (p, c), v in self.static.items()]
        for (p, c), (stamps, values) in self.samples.items():
            v = np.frombuffer(values, dtype=np.float64).reshape(-1, 7)
            edges.append(
                ((p, c), PoseTrack.from_samples(f"{p}->{c}", np.frombuffer(stamps, dtype=np.int64), v[:, :3], v[:, 3:]))
            )
        for (parent, child), track in edges:
            if child in out:
                other = out[child][0]
                what = "on both /tf and /tf_static" if other == parent else f"with two parents, {other} and {parent}"
                raise UserError(f"--tf: frame {child!r} is published {what}; the TF tree is ambiguous")
            out[child] = (parent, track)
        return out

    def chain(self, parent: str, child: str) -> PoseChain:
        """The path ``parent -> child`` through the tree: up from ``parent`` to the lowest common ancestor
        (edges inverted), then down to ``child``."""
        parent, child = _frame(parent), _frame(child)
        tree = self.parents()
        frames = set(tree) | {p for p, _ in tree.values()}
        if not frames:
            raise UserError("--tf: the bag has no transforms on /tf or /tf_static")
        for f in (parent, child):
            if f not in frames:
                raise UserError(f"--tf: frame {f!r} is not in /tf or /tf_static (frames: {', '.join(sorted(frames))})")
        up_p, up_c = _ancestors(tree, parent), _ancestors(tree, child)
        common = next((f for f in up_p if f in set(up_c)), None)
        if common is None:
            raise UserError(
                f"--tf: frames {parent!r} and {child!r} are not connected "
                f"in the TF tree (roots {up_p[-1]!r} and {up_c[-1]!r})"
            )
        edges = [(tree[f][1], True) for f in up_p[: up_p.index(common)]]
        edges += [(tree[f][1], False) for f in reversed(up_c[: up_c.index(common)])]
        return PoseChain(parent, child, edges)


def _ancestors(tree: dict[str, tuple[str, PoseTrack]], frame: str) -> list[str]:
    """``[frame, its parent, ..., root]`` (a cycle is an error)."""
    path = [frame]
    while path[-1] in tree:
        nxt = tree[path[-1]][0]
        if nxt in path:
            raise UserError(f"--tf: the TF tree has a cycle through {nxt!r}")
        path.append(nxt)
    return path
