"""A :class:`~.keyframe_map.KeyframeMap` from frames with known poses (the training images of a model).

Keyframes (:mod:`.sources`: of datasets, or rendered from a synthetic scene): in each sequence the first frame,
then every frame at least ``spacing_m`` from the last keyframe or turned by at least ``angle_deg`` from it. Each
keyframe's SIFT keypoints (:mod:`.features`) become map points:

* with the dataset's depth: back-projected through the keyframe's intrinsics (depth along z, metres; keypoints
  whose depth is 0, beyond ``max_depth_m`` or whose 3x3 neighbourhood spans over 10 % of it, a depth edge, are dropped)
  and placed in the map frame with the keyframe's pose;
* without depth: triangulated with the next keyframe of the sequence (the previous one for the last), whose pose is
  known: matched keypoints kept where both reprojection errors are under 2 px, the point lies in front of both
  cameras, and the rays meet at an angle of at least 1 deg.

Where the dataset has labels, keypoints on moving objects (class ``Dynamic``, :func:`.features.off_dynamic`) are left
out.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from vlocnetpp_core import geometry
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.mapping.features import FeatureConfig, FeatureExtractor, Features, match, off_dynamic, to_grey
from vlocnetpp_core.mapping.keyframe_map import KeyframeMap
from vlocnetpp_core.mapping.sources import dataset_keyframes, scene_keyframes, scene_source

SPACING_M = 7.0  # keyframe spacing and turn of the shipped map (docs/refinement.md, "The map")
ANGLE_DEG = 25.0
MAX_DEPTH_M = 100.0
EDGE_FRACTION = (
    0.1  # a keypoint whose 3x3 depth neighbourhood spans more than this fraction of its depth sits on a depth edge
)
MIN_TRIANGULATION_DEG = 1.0
MAX_TRIANGULATION_PX = 2.0


def lift_with_depth(
    uv: np.ndarray, depth: np.ndarray, K: np.ndarray, t: np.ndarray, q: np.ndarray, max_depth_m: float = MAX_DEPTH_M
) -> tuple[np.ndarray, np.ndarray]:
    """``(keep (N,) bool, points (n, 3) float32)``: the keypoints ``uv (N, 2)`` with valid depth in ``depth (H, W)``,
    in the map frame of a camera at ``T_map,cam = (t, q)``."""
    h, w = depth.shape
    col = np.clip(np.round(uv[:, 0]).astype(int), 0, w - 1)
    row = np.clip(np.round(uv[:, 1]).astype(int), 0, h - 1)
    z = depth[row, col].astype(np.float64)
    patch_max = cv2.dilate(depth, np.ones((3, 3), np.uint8))[row, col]
    patch_min = -cv2.dilate(-depth, np.ones((3, 3), np.uint8))[row, col]
    keep = (z > 0) & (z <= max_depth_m) & (patch_min > 0) & (patch_max - patch_min <= EDGE_FRACTION * z)
    camera = geometry.backproject(uv[keep].astype(np.float64), z[keep], K)
    return keep, (camera @ geometry.quat_to_matrix(q).T + t).astype(np.float32)


def triangulate(
    a: Features, b: Features, K_a: np.ndarray, K_b: np.ndarray, pose_a, pose_b, ratio: float
) -> tuple[np.ndarray, np.ndarray]:
    """``(keep (N_a,) bool, points (n, 3) float32)``: keypoints of ``a`` triangulated with their matches in ``b``
    (poses ``(t, q)`` ``T_map,cam``), kept under the module docstring's checks."""
    keep = np.zeros(len(a), bool)
    qi, ki, _ = match(a.descriptors, b.descriptors, ratio)
    if len(qi) == 0:
        return keep, np.zeros((0, 3), np.float32)
    P = [K @ _world_to_camera(*pose) for K, pose in ((K_a, pose_a), (K_b, pose_b))]
    X = cv2.triangulatePoints(P[0], P[1], a.uv[qi].T.astype(np.float64), b.uv[ki].T.astype(np.float64))
    X = (X[:3] / np.where(np.abs(X[3]) < 1e-12, 1e-12, X[3])).T  # (n, 3)
    ok = np.ones(len(X), bool)
    for P_i, uv in ((P[0], a.uv[qi]), (P[1], b.uv[ki])):
        x = np.c_[X, np.ones(len(X))] @ P_i.T
        ok &= x[:, 2] > 1e-6
        ok &= np.linalg.norm(x[:, :2] / np.maximum(x[:, 2:], 1e-6) - uv, axis=1) < MAX_TRIANGULATION_PX
    rays = [X - pose[0] for pose in (pose_a, pose_b)]
    cos = np.sum(rays[0] * rays[1], 1) / np.maximum(
        np.linalg.norm(rays[0], axis=1) * np.linalg.norm(rays[1], axis=1), 1e-12
    )
    ok &= cos <= np.cos(np.radians(MIN_TRIANGULATION_DEG))
    keep[qi[ok]] = True
    order = np.argsort(qi[ok])  # points in the order of the kept keypoints
    return keep, X[ok][order].astype(np.float32)


def _world_to_camera(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    R = geometry.quat_to_matrix(q)
    return np.c_[R.T, -R.T @ t]


def build_map(
    indexes: Sequence,
    spacing_m: float = SPACING_M,
    angle_deg: float = ANGLE_DEG,
    features: FeatureConfig = FeatureConfig(),
    progress: bool = True,
    workers: int = 1,
) -> KeyframeMap:
    """The map of the frames of ``indexes`` (``DatasetIndex``es with poses); ``UserError`` naming the dataset when one
    has no frames, or when the map would have no points."""
    sequences = dataset_keyframes(indexes, spacing_m, angle_deg)
    return build_map_of(sequences, "; ".join(f"{ix.root} ({ix.split})" for ix in indexes), features, progress, workers)


def build_scene_map(
    scene: str,
    seed: int,
    loops: int,
    frames_per_loop: int,
    spacing_m: float = SPACING_M,
    angle_deg: float = ANGLE_DEG,
    size: tuple[int, int] = (320, 180),
    lane_wander: float = 0.0,
    features: FeatureConfig = FeatureConfig(),
    progress: bool = True,
    workers: int = 1,
) -> KeyframeMap:
    """The map of the train split ``vlocnetpp synth`` renders with these arguments, rendering only its keyframes
    (:func:`.sources.scene_keyframes`: the same map as :func:`build_map` of the rendered dataset)."""
    sequences = scene_keyframes(scene, seed, loops, frames_per_loop, spacing_m, angle_deg, size, lane_wander)
    source = scene_source(scene, seed, loops, frames_per_loop, size, lane_wander)
    return build_map_of(sequences, source, features, progress, workers)


def build_map_of(
    sequences: Sequence, source: str, features: FeatureConfig = FeatureConfig(), progress: bool = True, workers: int = 1
) -> KeyframeMap:
    """The map of keyframe ``sequences`` (:mod:`.sources`), described as ``source``; ``workers`` processes (1: this
    one) each take whole sequences, and the map is the same for any number. ``UserError`` when it has no points."""
    from tqdm import tqdm

    bar = tqdm(
        total=sum(len(s) for s in sequences),
        desc="map keyframes",
        unit="keyframe",
        disable=not progress,
        dynamic_ncols=True,
    )
    with bar:
        if workers <= 1 or len(sequences) < 2:
            done = []
            for seq in sequences:
                done.append(_sequence_parts(seq, features))
                bar.update(len(seq))
        else:
            done = _in_processes(sequences, features, min(workers, len(sequences)), bar)
    parts: dict[str, list] = {k: [] for k in PARTS}
    for part in done:
        for k in PARTS:
            parts[k].extend(part[k])
    if sum(parts["counts"]) == 0:
        raise UserError("no map points: the keyframes have no SIFT features with depth (or none could be triangulated)")
    return _assemble(parts, features, source)


def _in_processes(sequences: Sequence, features: FeatureConfig, workers: int, bar) -> list[dict]:
    """:func:`_sequence_parts` of each sequence in ``workers`` fresh processes (spawned: no threads of this one are
    inherited), in the order of ``sequences``."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(
        workers, multiprocessing.get_context("spawn"), initializer=cv2.setNumThreads, initargs=(1,)
    ) as pool:
        futures = [pool.submit(_sequence_parts, seq, features) for seq in sequences]
        for future, seq in zip(futures, sequences, strict=True):
            future.add_done_callback(lambda _f, n=len(seq): bar.update(n))
        return [f.result() for f in futures]


PARTS = ("t", "q", "intrinsics", "image_sizes", "uv", "points", "descriptors", "thumbnails", "counts")


def _sequence_parts(sequence, features: FeatureConfig) -> dict[str, list]:
    """The map's arrays (:data:`PARTS`, one entry per keyframe) of one keyframe sequence."""
    from vlocnetpp_core.evaluation.retrieval import describe

    extractor = FeatureExtractor(features)
    frames = sequence.frames()
    found = [_static_features(extractor, f) for f in frames]
    parts: dict[str, list] = {k: [] for k in PARTS}
    for j, (frame, feats) in enumerate(zip(frames, found, strict=True)):
        keep, points = _points_of(frames, found, j, features.ratio)
        _append(parts, frame, feats, keep, points, describe(frame.image))
    return parts


def _static_features(extractor: FeatureExtractor, frame) -> Features:
    """The frame's SIFT features, without those on moving objects where the frame has labels."""
    feats = extractor(to_grey(frame.image))
    return feats if frame.labels is None else feats.select(off_dynamic(feats.uv, frame.labels))


def _points_of(frames: list, found: list[Features], j: int, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints of keyframe ``j`` of a sequence that become map points, and the points: from depth, else
    triangulated."""
    f = frames[j]
    K = f.intrinsics.matrix()
    if f.depth is not None:
        return lift_with_depth(found[j].uv, f.depth, K, f.t, f.q)
    if len(frames) < 2:
        return np.zeros(len(found[j]), bool), np.zeros((0, 3), np.float32)
    o = j + 1 if j + 1 < len(frames) else j - 1
    return triangulate(
        found[j], found[o], K, frames[o].intrinsics.matrix(), (f.t, f.q), (frames[o].t, frames[o].q), ratio
    )


def _append(parts: dict, frame, feats: Features, keep: np.ndarray, points: np.ndarray, thumbnail: np.ndarray) -> None:
    i = frame.intrinsics
    parts["t"].append(frame.t)
    parts["q"].append(frame.q)
    parts["intrinsics"].append((i.fx, i.fy, i.cx, i.cy))
    parts["image_sizes"].append(frame.image.shape[1::-1])
    parts["uv"].append(feats.uv[keep])
    parts["points"].append(points)
    parts["descriptors"].append(feats.descriptors[keep])
    parts["thumbnails"].append(thumbnail)
    parts["counts"].append(int(keep.sum()))


def _assemble(parts: dict, features: FeatureConfig, source: str) -> KeyframeMap:
    offsets = np.concatenate(([0], np.cumsum(parts["counts"]))).astype(np.int64)
    return KeyframeMap(
        t=np.asarray(parts["t"], np.float64),
        q=np.asarray(parts["q"], np.float64),
        intrinsics=np.asarray(parts["intrinsics"], np.float64),
        image_sizes=np.asarray(parts["image_sizes"], np.int32),
        offsets=offsets,
        uv=np.concatenate(parts["uv"]).astype(np.float32),
        points=np.concatenate(parts["points"]).astype(np.float32),
        descriptors=np.concatenate(parts["descriptors"]).astype(np.uint8),
        thumbnails=np.asarray(parts["thumbnails"], np.float16),
        features=features,
        source=source,
    )
